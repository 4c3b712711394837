"""The HTTP service in-process (fastapi TestClient = httpx over ASGI, the lifespan runs): every endpoint and every
status of issue 12 item 5 (docs/api.md's error table), backpressure, API keys, CORS, a reconstruction worker
that dies, metrics.

One app per module (startup ~2 s, with a real reconstruction worker process), and the example rig is
reconstructed once and shared (``env.sid``). Apps that only need the middleware or the dependencies (413, API
keys, CORS, readiness before the model loads) are built without running their lifespan ("cold" apps: no worker
processes). The main app runs with render_threads=1, render_queue=0 and reconstruct_queue=0 so that the
backpressure tests can fill the queues deterministically; TestClient sends one request at a time, so the other
tests are unaffected. Tests run in file order and each leaves no job running behind it.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import signal
import struct
import subprocess
import threading
import time
import zipfile
import zlib
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "synth_nuscenes"
MODEL_NAME = "xyzcyl-cpu-v1"
BODY_LIMIT = 2 << 20            # the example rig's upload is ~0.95 MB
CHUNK = 64 << 10


# ----------------------------------------------------------------------------------------------- helpers


@functools.cache
def example_rig() -> dict:
    return json.loads((EXAMPLE / "rig.json").read_text())


@functools.cache
def example_images() -> dict[str, bytes]:
    return {c["name"]: (EXAMPLE / c["image"]).read_bytes() for c in example_rig()["cameras"]}


def rig_files(rig: dict | None = None, images: dict[str, Any] | None = None, rig_bytes: bytes | None = None,
              drop: tuple[str, ...] = (), extra: list | None = None) -> list:
    """The multipart parts of POST /v1/scenes: ("rig", rig.json) + one image part per camera."""
    rig = example_rig() if rig is None else rig
    imgs = {**example_images(), **(images or {})}
    parts = []
    if "rig" not in drop:
        parts.append(("rig", ("rig.json", rig_bytes if rig_bytes is not None else json.dumps(rig).encode(),
                              "application/json")))
    for c in rig["cameras"]:
        if c["name"] in drop:
            continue
        img = imgs.get(c["name"], imgs["CAM_FRONT"])
        parts.append((c["name"], img if isinstance(img, tuple) else (f"{c['name']}.png", img, "image/png")))
    return parts + list(extra or [])


def multipart_body(files: list) -> tuple[bytes, str]:
    req = httpx.Request("POST", "http://x/v1/scenes", files=files)
    return req.read(), req.headers["content-type"]


def wall_npy() -> bytes:
    """A LiDAR sweep as .npy bytes: a round wall 15 m from the ego origin, [N, 4] float32 (x, y, z, intensity)."""
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-1.0, 4.0, 30))
    pts = np.stack([15 * np.cos(az).ravel(), 15 * np.sin(az).ravel(), z.ravel(), np.ones(az.size)], axis=1)
    buf = io.BytesIO()
    np.save(buf, pts.astype(np.float32))
    return buf.getvalue()


def _lidar_to_ego_2x2(rig):
    rig["lidar"] = {"file": "sweep.npy", "lidar_to_ego": [[1, 0], [0, 1]]}


def png_bytes(w: int, h: int, channels: int = 3, dtype=np.uint8) -> bytes:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 200, (h, w, channels) if channels > 1 else (h, w)).astype(dtype)
    ok, buf = cv2.imencode(".png", a)
    assert ok
    return buf.tobytes()


def mask_array(w: int = 800, h: int = 450, dtype=np.uint8, channels: int = 1) -> np.ndarray:
    """An ego mask of the example's camera size: the bottom third non-zero (the ego's own body)."""
    a = np.zeros((h, w, channels) if channels > 1 else (h, w), dtype)
    a[h - h // 3:] = np.iinfo(dtype).max
    return a


def mask_png(**kw) -> bytes:
    ok, buf = cv2.imencode(".png", mask_array(**kw))
    assert ok
    return buf.tobytes()


def png_header_only(w: int, h: int) -> bytes:
    """A tiny PNG whose header claims w x h (a decompression bomb's shape: the server must refuse it from the
    header, before decoding)."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def decode(data: bytes, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    assert img is not None, "not a decodable image"
    return img


def read_exr_bytes(data: bytes, tmp_path: Path) -> np.ndarray:
    from xyzcyl.runtime.imageio import read_exr

    assert data[:4] == b"\x76\x2f\x31\x01", "not an OpenEXR file"
    p = tmp_path / f"x{len(data)}.exr"
    p.write_bytes(data)
    return read_exr(p)


def err(r: httpx.Response, status: int, field: str | None = "<any>", code: str | None = None) -> dict:
    """Assert the status and the one error body; return the error object."""
    assert r.status_code == status, (r.status_code, r.text[:400])
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message", "field"}, body
    e = body["error"]
    assert isinstance(e["message"], str) and e["message"]
    if field != "<any>":
        assert e["field"] == field, e
    if code is not None:
        assert e["code"] == code, e
    return e


def front() -> dict:
    return example_rig()["cameras"][0]


def flat(m) -> str:
    return ",".join(repr(float(v)) for row in m for v in row)


@contextlib.contextmanager
def worker_held(env: Env, tmp_path: Path):
    """Keep the reconstruction worker process busy until the block ends (or ``release()`` is called): it runs a
    shell loop that waits for a flag file (subprocess.call pickles by reference into the spawned worker), so a
    job posted meanwhile stays queued/running for as long as the test needs, whatever the machine's speed."""
    flag = tmp_path / f"release-{time.monotonic_ns()}"
    worker = env.service.reconstructions.workers[0]
    fut = worker.pool.submit(subprocess.call, ["sh", "-c", f"while [ ! -e '{flag}' ]; do sleep 0.02; done"])

    def release():
        flag.touch()

    try:
        yield fut, release
    finally:
        release()


def wait_state(client: TestClient, sid: str, states: tuple[str, ...], timeout: float = 60.0) -> dict:
    t0 = time.monotonic()
    while True:
        r = client.get(f"/v1/scenes/{sid}")
        assert r.status_code == 200, r.text
        if r.json()["state"] in states:
            return r.json()
        assert time.monotonic() - t0 < timeout, f"scene {sid} still {r.json()['state']} after {timeout} s"
        time.sleep(0.05)


def wait_ready(client: TestClient, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while client.get("/v2/health/ready").status_code != 200:
        assert time.monotonic() - t0 < timeout, "the service never became ready"
        time.sleep(0.1)


def cold_client(tmp_path: Path, **kw) -> TestClient:
    """An app whose lifespan does not run (no worker processes; the model counts as not loaded yet)."""
    from xyzcyl.server import Settings, create_app

    return TestClient(create_app(Settings(store=str(tmp_path / "cold-store"), **kw)))


# ----------------------------------------------------------------------------------------------- the app


@dataclass
class Env:
    app: Any
    client: TestClient
    service: Any
    store_root: Path
    first_ready: httpx.Response
    created: httpx.Response
    sid: str
    responses: list = field(default_factory=list)


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    from xyzcyl.server import Settings, create_app

    root = tmp_path_factory.mktemp("store")
    settings = Settings(store=str(root), max_body_bytes=BODY_LIMIT, render_threads=1, render_queue=0,
                        reconstruct_queue=0)
    app = create_app(settings)
    seen: list = []
    with TestClient(app) as client:
        client.event_hooks = {"request": [], "response": [seen.append]}
        first = client.get("/v2/health/ready")
        wait_ready(client)
        created = client.post("/v1/scenes?wait=60", files=rig_files())
        assert created.status_code == 201, created.text
        yield Env(app, client, app.state.service, root, first, created, created.json()["id"], seen)


@pytest.fixture
def client(env) -> TestClient:
    return env.client


def metric(env: Env, name: str, **labels) -> float:
    """A sample of the app's own Prometheus registry (0 when it has not been recorded yet)."""
    return env.service.metrics.registry.get_sample_value(name, labels) or 0.0


def records(env: Env) -> int:
    return env.service.store.list()[1]


def url(env: Env, tail: str = "") -> str:
    return f"/v1/scenes/{env.sid}{tail}"


def tmp_left(env: Env) -> list[str]:
    return [p.name for p in (env.store_root / "tmp").iterdir() if not p.name.startswith("deleted-")]


# ----------------------------------------------------------------------------------------------- readiness


def test_ready_is_503_until_the_model_is_loaded(env, tmp_path):
    r = env.first_ready                      # asked right after startup, while the worker loads the model
    assert r.status_code == 503 and r.headers["retry-after"] == "1"
    assert r.json() == {"ready": False, "reason": "loading the model"}
    assert env.client.get("/v2/health/ready").json()["ready"] is True

    cold = cold_client(tmp_path)
    assert cold.get("/v2/health/live").status_code == 200
    r = cold.get("/v2/health/ready")
    assert r.status_code == 503 and r.json()["ready"] is False
    r = cold.get(f"/v2/models/{MODEL_NAME}/ready")
    assert r.status_code == 503 and r.json() == {"name": MODEL_NAME, "ready": False}
    r = cold.post("/v1/scenes", files=rig_files())
    err(r, 503, None, "busy")
    assert r.headers["retry-after"] == "1"


# ----------------------------------------------------------------------------------------------- POST /v1/scenes


def test_post_wait_answers_201_with_the_metadata(env):
    r = env.created
    info = r.json()
    assert r.headers["location"] == f"/v1/scenes/{info['id']}"
    assert info["state"] == "ready" and info["error"] is None
    assert [c["name"] for c in info["cameras"]] == [c["name"] for c in example_rig()["cameras"]]
    assert all((c["width"], c["height"], c["model"]) == (800, 450, "pinhole") for c in info["cameras"])
    assert info["model"]["name"] == MODEL_NAME and info["model"]["version"]
    assert info["gaussians"] > 1000 and info["background"] is True
    assert info["counts"] and all(isinstance(v, int) and v >= 0 for v in info["counts"].values())
    assert info["counts"]["total"] == info["gaussians"]
    lo, hi = np.array(info["bbox"]["min"]), np.array(info["bbox"]["max"])
    assert lo.shape == hi.shape == (3,) and np.all(lo < hi)
    assert info["timings"] and info["bytes"] > 0
    assert info["links"] == {"self": url(env), "gaussians": url(env, "/gaussians"), "render": url(env, "/render"),
                             "background": url(env, "/background")}
    assert env.client.get(url(env)).json() == info


def test_post_not_multipart_is_415(client, env):
    before = env.service.store.list()[1]
    e = err(client.post("/v1/scenes", json=example_rig()), 415, "content-type", "unsupported_media_type")
    assert "multipart/form-data" in e["message"]
    err(client.post("/v1/scenes"), 415, "content-type")
    assert env.service.store.list()[1] == before


def test_post_over_the_body_limit_by_content_length_is_413_before_reading(client, env):
    body, ctype = multipart_body(rig_files(images={"CAM_BACK": b"\x89PNG\r\n\x1a\n" + b"\0" * BODY_LIMIT}))
    assert len(body) > BODY_LIMIT
    pulled = []

    def chunks():
        for i in range(0, len(body), CHUNK):
            pulled.append(i)
            yield body[i:i + CHUNK]

    before = records(env)
    r = client.post("/v1/scenes", content=chunks(), headers={"content-type": ctype, "content-length": str(len(body))})
    e = err(r, 413, "body", "too_large")
    assert str(BODY_LIMIT) in e["message"]
    assert pulled == []                  # refused from the header: not one byte of the body was read
    assert records(env) == before and tmp_left(env) == []


def test_post_chunked_body_over_the_limit_is_413_while_streaming(client, env):
    """No Content-Length (Transfer-Encoding: chunked): refused once the body read so far passes the limit.
    TestClient reads a streamed request body whole before the app sees it, so this request goes through httpx's
    ASGITransport (chunk by chunk, more_body=True) on the app's own event loop."""
    body, ctype = multipart_body(rig_files(images={"CAM_BACK": b"\x89PNG\r\n\x1a\n" + b"\0" * (2 * BODY_LIMIT)}))
    pulled = []

    async def chunks():
        for i in range(0, len(body), CHUNK):
            pulled.append(CHUNK)
            yield body[i:i + CHUNK]

    async def post():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=env.app), base_url="http://test") as ac:
            return await ac.post("/v1/scenes", content=chunks(), headers={"content-type": ctype})

    before = records(env)
    counted = metric(env, "xyzcyl_http_requests_total", route="/v1/scenes", method="POST", status="413")
    r = client.portal.call(post)
    assert "content-length" not in r.request.headers and r.request.headers["transfer-encoding"] == "chunked"
    err(r, 413, "body", "too_large")
    assert "server" not in r.headers
    assert BODY_LIMIT < sum(pulled) <= BODY_LIMIT + 2 * CHUNK < len(body)   # stopped at the limit, not at the end
    assert records(env) == before and tmp_left(env) == []
    assert metric(env, "xyzcyl_http_requests_total", route="/v1/scenes", method="POST", status="413") == counted + 1


def _rig_with(change) -> dict:
    rig = json.loads(json.dumps(example_rig()))
    change(rig)
    return rig


def _bad_fx(rig):
    rig["cameras"][1]["K"][0][0] = -633.0


def _skewed_pose(rig):
    rig["cameras"][2]["cam_to_ego"][0][0] *= 1.5


def _many(rig):
    rig["cameras"] = [dict(rig["cameras"][0], name=f"CAM_{i:02d}") for i in range(17)]


def _no_cameras(rig):
    rig["cameras"] = []


def jpeg_of(name: str) -> bytes:
    """The example camera's image as a JPEG (the rig declares it 800x450, whatever the file type)."""
    ok, buf = cv2.imencode(".jpg", decode(example_images()[name], cv2.IMREAD_COLOR))
    assert ok
    return buf.tobytes()


def jpeg_with_ff_run(name: str) -> bytes:
    """A JPEG whose header and end marker are whole, with a run of FF bytes in its scan data (corrupt data)."""
    b = jpeg_of(name)
    return b[:len(b) // 2] + b"\xff" * 100 + b[len(b) // 2 + 100:]


# issue 27 (defects 1 and 5): cut or corrupt image parts were accepted (a cut JPEG decodes with the rest grey: the
# scene had a grey wall) or named the part twice with the store's temporary path
CUT_IMAGES = {
    "image JPEG cut short": ("b.jpg", lambda: jpeg_of("CAM_BACK")[:-5000], "image/jpeg"),
    "image JPEG without its end marker": ("b.jpg", lambda: jpeg_of("CAM_BACK")[:-2], "image/jpeg"),
    "image JPEG with corrupt data": ("b.jpg", lambda: jpeg_with_ff_run("CAM_BACK"), "image/jpeg"),
    "image PNG cut short": ("b.png", lambda: example_images()["CAM_BACK"][:100_000], "image/png"),
    "image PNG with a garbage header": ("b.png", lambda: b"\x89PNG\r\n\x1a\n" + b"garbage " * 40, "image/png"),
}


UPLOAD_ERRORS = {
    # case: (files, status, field, code)
    "missing rig part": (lambda: rig_files(drop=("rig",)), 422, "rig", "invalid"),
    "rig not JSON": (lambda: rig_files(rig_bytes=b"{cameras: ["), 422, "rig", "invalid"),
    "rig not a rig": (lambda: rig_files(rig_bytes=b"[1, 2]"), 422, "rig", "invalid"),
    "K with fx < 0": (lambda: rig_files(_rig_with(_bad_fx)), 422, "rig", "invalid"),
    "non-orthonormal cam_to_ego": (lambda: rig_files(_rig_with(_skewed_pose)), 422, "rig", "invalid"),
    "more cameras than max_cameras": (lambda: rig_files(_rig_with(_many))[:1], 422, "rig.cameras", "invalid"),
    "rig with no cameras": (lambda: rig_files(_rig_with(_no_cameras)), 422, "rig", "invalid"),
    "missing image part": (lambda: rig_files(drop=("CAM_BACK",)), 422, "CAM_BACK", "invalid"),
    "unknown part": (lambda: rig_files(extra=[("CAM_TOP", ("t.png", png_bytes(8, 8), "image/png"))]), 422,
                     "CAM_TOP", "invalid"),
    "part twice": (lambda: rig_files(extra=[("CAM_FRONT", ("f.png", example_images()["CAM_FRONT"], "image/png"))]),
                   422, "CAM_FRONT", "invalid"),
    "image part as a text field": (lambda: [p for p in rig_files() if p[0] != "CAM_BACK"]
                                   + [("CAM_BACK", (None, "hello"))], 422, "CAM_BACK", "invalid"),
    "image size not the rig's": (lambda: rig_files(images={"CAM_BACK": png_bytes(400, 225)}), 422, "CAM_BACK",
                                 "invalid"),
    "image pixels over the limit": (lambda: rig_files(images={"CAM_BACK": png_header_only(5000, 4000)}), 422,
                                    "CAM_BACK", "invalid"),
    "image not an image": (lambda: rig_files(images={"CAM_BACK": b"hello, not an image at all"}), 415,
                           "CAM_BACK", "unsupported_media_type"),
    "image with a text media type": (lambda: rig_files(images={"CAM_BACK": ("b.txt", b"hello", "text/plain")}),
                                     415, "CAM_BACK", "unsupported_media_type"),
    **{case: ((lambda f=f, make=make, t=t: rig_files(images={"CAM_BACK": (f, make(), t)})), 422, "CAM_BACK",
              "invalid") for case, (f, make, t) in CUT_IMAGES.items()},
    "depth part cut short": (lambda: rig_files(extra=[("depth:CAM_FRONT", (
        "d.png", png_bytes(800, 450, 1, np.uint16)[:-3000], "image/png"))]), 422, "depth:CAM_FRONT", "invalid"),
    "depth part of the wrong size": (lambda: rig_files(extra=[("depth:CAM_FRONT", (
        "d.png", png_bytes(80, 45, 1, np.uint16), "image/png"))]), 422, "depth:CAM_FRONT", "invalid"),
    "depth part as JPEG": (lambda: rig_files(extra=[("depth:CAM_FRONT", (
        "d.jpg", cv2.imencode(".jpg", np.zeros((450, 800), np.uint8))[1].tobytes(), "image/jpeg"))]), 415,
        "depth:CAM_FRONT", "unsupported_media_type"),
    "lidar part not whole float32 rows": (lambda: rig_files(extra=[("lidar", (
        "s.bin", b"\x00" * 10, "application/octet-stream"))]), 422, "lidar", "invalid"),
    "lidar part with an image media type": (lambda: rig_files(extra=[("lidar", ("s.npy", wall_npy(), "image/png"))]),
                                            415, "lidar", "unsupported_media_type"),
    "lidar part as a text field": (lambda: rig_files(extra=[("lidar", (None, "1 2 3"))]), 422, "lidar", "invalid"),
    "lidar_to_ego not 4x4": (lambda: rig_files(_rig_with(_lidar_to_ego_2x2), extra=[("lidar", (
        "s.npy", wall_npy(), "application/octet-stream"))]), 422, "lidar", "invalid"),
    "ego mask part of the wrong size": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (
        "m.png", png_bytes(80, 45, 1), "image/png"))]), 422, "ego_mask:CAM_FRONT", "invalid"),
    "ego mask part cut short": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (
        "m.png", mask_png()[:-200], "image/png"))]), 422, "ego_mask:CAM_FRONT", "invalid"),
    "ego mask JPEG cut short": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (
        "m.jpg", cv2.imencode(".jpg", mask_array())[1].tobytes()[:-300], "image/jpeg"))]), 422,
        "ego_mask:CAM_FRONT", "invalid"),
    "ego mask part as TIFF": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (
        "m.tif", b"II*\x00" + b"\x00" * 64, "image/tiff"))]), 415, "ego_mask:CAM_FRONT", "unsupported_media_type"),
    "ego mask part with a text media type": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (
        "m.txt", mask_png(), "text/plain"))]), 415, "ego_mask:CAM_FRONT", "unsupported_media_type"),
    "ego mask part as a text field": (lambda: rig_files(extra=[("ego_mask:CAM_FRONT", (None, "1"))]), 422,
                                      "ego_mask:CAM_FRONT", "invalid"),
    "ego mask part of no camera": (lambda: rig_files(extra=[("ego_mask:CAM_TOP", ("m.png", mask_png(),
                                                                                  "image/png"))]), 422,
                                   "ego_mask:CAM_TOP", "invalid"),
}


@pytest.mark.parametrize("case", list(UPLOAD_ERRORS))
def test_post_bad_upload(client, env, case):
    make, status, field_name, code = UPLOAD_ERRORS[case]
    records = env.service.store.list()[1]
    e = err(client.post("/v1/scenes?wait=5", files=make()), status, field_name, code)
    if case == "image pixels over the limit":
        assert "20000000 pixels" in e["message"]
    if case == "K with fx < 0":
        assert "CAM_FRONT_RIGHT" in e["message"]
    assert env.service.store.list()[1] == records          # no scene was created
    assert tmp_left(env) == []                             # and the upload was removed


@pytest.mark.parametrize("case", list(CUT_IMAGES))
def test_post_cut_or_corrupt_image_names_the_part_once(client, env, case):
    """Regression (issue 27, defects 1 and 5): one line that names the part once and says what is wrong with the
    file, without the store's temporary path (nor the '()' of an empty decoder message)."""
    name, make, ctype = CUT_IMAGES[case]
    e = err(client.post("/v1/scenes?wait=5", files=rig_files(images={"CAM_BACK": (name, make(), ctype)})), 422,
            "CAM_BACK", "invalid")
    msg = e["message"]
    assert msg.startswith("part 'CAM_BACK': ") and msg.count("CAM_BACK") == 1, msg
    assert "cut short or corrupt" in msg or "cannot read the image" in msg, msg
    assert str(env.store_root) not in msg and "image_0" not in msg and "/" not in msg, msg
    assert "\n" not in msg and "()" not in msg, msg


def test_post_rig_errors_name_the_rig_once_with_plain_numbers(client, env):
    """Regression (issue 27, defect 5): 'rig: rig: cameras must have 1..16 entries' and 'K[0][0] (fx) must be > 0
    (got np.float64(-633.0))'."""
    e = err(client.post("/v1/scenes?wait=5", files=rig_files(_rig_with(_no_cameras))), 422, "rig", "invalid")
    assert e["message"] == "rig: cameras must have 1..16 entries (got 0)", e
    e = err(client.post("/v1/scenes?wait=5", files=rig_files(_rig_with(_bad_fx))), 422, "rig", "invalid")
    assert e["message"] == "camera 'CAM_FRONT_RIGHT': K[0][0] (fx) must be > 0 (got -633.0)", e


def test_post_with_a_lidar_part(client, env):
    """A 'lidar' part becomes the depth input of every camera (counts.lidar_cameras); without it a rig's lidar block
    (a file name of the client's) is not used."""
    r = client.post("/v1/scenes?wait=60", files=rig_files(extra=[("lidar", ("sweep.npy", wall_npy(),
                                                                            "application/octet-stream"))]))
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["counts"]["lidar_cameras"] == 6 and info["timings"]["encode_lidar"] > 0
    plain = env.created.json()
    assert "lidar_cameras" not in plain["counts"]
    r = client.post("/v1/scenes?wait=60", files=rig_files(_rig_with(
        lambda rig: rig.update(lidar={"file": "sweep.npy"}))))
    assert r.status_code == 201, r.text
    assert "lidar_cameras" not in r.json()["counts"]
    for sid in (info["id"], r.json()["id"]):
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204


def test_post_a_rotation_the_rig_accepts_with_lidar(client, env):
    """CAM_FRONT's rotation off by |R^T R - I| = 8e-4 (within the rig's tolerance) with a LiDAR part: the renderer's
    camera once refused it (tolerance 1e-4), and the job failed with code `error` (a 500 with ?wait); now one
    tolerance (runtime.rotations.ORTHO_TOL) and the scene is made. Issue 27 defect 8."""
    def tilt(rig):
        T = np.array(rig["cameras"][0]["cam_to_ego"], dtype=np.float64)
        u, _, vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = u @ vt * np.sqrt(1 + 8e-4)
        rig["cameras"][0]["cam_to_ego"] = T.tolist()

    r = client.post("/v1/scenes?wait=60&detail=false", files=rig_files(_rig_with(tilt), extra=[(
        "lidar", ("sweep.npy", wall_npy(), "application/octet-stream"))]))
    assert r.status_code == 201, r.text
    assert r.json()["counts"]["lidar_cameras"] == 6
    assert client.delete(f"/v1/scenes/{r.json()['id']}").status_code == 204


def test_post_with_ego_mask_parts(client, env):
    """An 'ego_mask:<camera>' part (non-zero = the ego's own body) keeps detail Gaussians off those pixels: a mask
    over the bottom third of CAM_FRONT lowers counts.detail. 16-bit RGB masks are read too (CAM_BACK's, all zero,
    changes nothing), and like depth, an ego_mask that the rig names without a part is not used (the file is the
    client's): CAM_FRONT_LEFT's name does not fail the scene."""
    rig = _rig_with(lambda rig: rig["cameras"][5].update(ego_mask="masks/front_left.png"))
    assert rig["cameras"][5]["name"] == "CAM_FRONT_LEFT"
    r = client.post("/v1/scenes?wait=60", files=rig_files(rig, extra=[
        ("ego_mask:CAM_FRONT", ("front.png", mask_png(), "image/png")),
        ("ego_mask:CAM_BACK", ("back.png", cv2.imencode(".png", np.zeros((450, 800, 3), np.uint16))[1].tobytes(),
                                "application/octet-stream"))]))
    assert r.status_code == 201, r.text
    masked, plain = r.json()["counts"], env.created.json()["counts"]
    assert 0 < masked["detail"] < plain["detail"], (masked, plain)
    assert client.delete(f"/v1/scenes/{r.json()['id']}").status_code == 204


DETAIL_QUERY_ERRORS = {
    "stride 0": ("detail_stride=0", "detail_stride"),
    "stride 17": ("detail_stride=17", "detail_stride"),
    "stride not an integer": ("detail_stride=2.5", "detail_stride"),
    "stride empty": ("detail_stride=", "detail_stride"),
    "stride twice": ("detail_stride=4&detail_stride=8", "detail_stride"),
    "detail not a boolean": ("detail=maybe", "detail"),
    "detail=false with a stride": ("detail=false&detail_stride=4", "detail_stride"),
}


@pytest.mark.parametrize("case", list(DETAIL_QUERY_ERRORS))
def test_post_bad_detail_query_is_422(client, env, case):
    query, field_name = DETAIL_QUERY_ERRORS[case]
    before = records(env)
    e = err(client.post(f"/v1/scenes?wait=5&{query}", files=rig_files()), 422, field_name, "invalid")
    assert e["message"].startswith(f"{field_name}: ")
    if case == "detail=false with a stride":
        assert "detail=false" in e["message"]
    assert records(env) == before and tmp_left(env) == []


def test_post_detail_stride_and_detail_false(client, env):
    """?detail_stride=8: at most one detail Gaussian per 8x8 block of each 800x450 camera; ?detail=false: the
    model's Gaussians only; the default is the runtime's stride (2). The choice is in the scene's metadata."""
    from xyzcyl.runtime.inference import DEFAULT_DETAIL

    plain = env.created.json()
    assert plain["detail"] == {"enabled": True, "stride": DEFAULT_DETAIL.stride}
    assert plain["counts"]["detail"] > 0 and plain["timings"]["detail"] > 0
    r = client.post("/v1/scenes?wait=60&detail_stride=8", files=rig_files())
    assert r.status_code == 201, r.text
    s8 = r.json()
    c = s8["counts"]
    assert s8["detail"] == {"enabled": True, "stride": 8} and client.get(f"/v1/scenes/{s8['id']}").json() == s8
    assert 0 < c["detail"] <= 6 * 100 * 57 < plain["counts"]["detail"] and c["total"] == c["coarse"] + c["detail"]
    r = client.post("/v1/scenes?wait=60&detail=false", files=rig_files())
    assert r.status_code == 201, r.text
    off = r.json()
    assert off["detail"] == {"enabled": False, "stride": None}
    assert not {"detail", "coarse", "culled"} & set(off["counts"]) and "detail" not in off["timings"]
    for sid in (s8["id"], off["id"]):
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204


def test_post_store_full_is_507(client, env, monkeypatch):
    store = env.service.store
    monkeypatch.setattr(store, "when_full", "reject")
    live = sum(n for state, n in store.usage()["scenes"].items() if state != "failed")
    before = records(env)
    monkeypatch.setattr(store, "max_scenes", live)
    err(client.post("/v1/scenes", files=rig_files()), 507, None, "storage_full")
    assert records(env) == before and store.get(env.sid)["state"] == "ready" and tmp_left(env) == []


# ----------------------------------------------------------------------------------------------- GET / DELETE


@pytest.mark.parametrize("bad", ["AAAAAAAAAAAAAAAAAAAAAA", "..%2F..%2Fetc", "..%2F..%2Fetc%2Fpasswd", "A" * 21,
                                 "A" * 23, "%2e%2e", "nope"])
def test_unknown_or_malformed_scene_is_404(client, bad):
    for tail in ("", "/gaussians", "/background", "/render?camera=CAM_FRONT"):
        err(client.get(f"/v1/scenes/{bad}{tail}"), 404, code="not_found")
    err(client.delete(f"/v1/scenes/{bad}"), 404, code="not_found")
    err(client.post(f"/v1/scenes/{bad}/render", json={"cameras": [{"camera": "CAM_FRONT"}]}), 404,
        code="not_found")
    if bad == "AAAAAAAAAAAAAAAAAAAAAA":              # well-formed but unknown: the field is named
        err(client.get(f"/v1/scenes/{bad}"), 404, "id", "not_found")


def test_list_scenes_paging_and_delete(client, env):
    from xyzcyl.server.store import new_scene_id

    store = env.service.store
    before = {r["id"] for r in store.list(0, 1000)[0]}
    extra = []
    for _ in range(4):
        sid = new_scene_id()
        store.create(sid, {"cameras": []})
        extra.append(sid)
        time.sleep(0.002)
    total = store.list()[1]
    assert total == len(before) + 4
    seen, pages, nxt = [], 0, "/v1/scenes?limit=2"
    while nxt:
        r = client.get(nxt)
        assert r.status_code == 200
        page = r.json()
        assert page["total"] == total and page["limit"] == 2 and len(page["scenes"]) <= 2
        seen += [s["id"] for s in page["scenes"]]
        nxt = page["next"]
        pages += 1
    assert pages == (total + 1) // 2 and len(seen) == total              # each once
    assert seen[:4] == extra[::-1] and set(seen) == before | set(extra)  # newest first
    assert client.get(f"/v1/scenes?offset={total - 2}&limit=2").json()["next"] is None
    assert client.get(f"/v1/scenes?offset={total - 3}&limit=2").json()["next"] == (
        f"/v1/scenes?offset={total - 1}&limit=2")
    last = client.get(f"/v1/scenes?offset={total}").json()
    assert last["scenes"] == [] and last["total"] == total and last["next"] is None
    err(client.get("/v1/scenes?limit=0"), 422, "limit", "invalid")
    err(client.get("/v1/scenes?offset=-1"), 422, "offset", "invalid")
    queued = client.get(f"/v1/scenes/{extra[0]}").json()
    assert queued["state"] == "queued" and set(queued["links"]) == {"self"}

    for sid in extra:
        r = client.delete(f"/v1/scenes/{sid}")
        assert r.status_code == 204 and r.content == b""
        err(client.get(f"/v1/scenes/{sid}"), 404, "id", "not_found")
        err(client.delete(f"/v1/scenes/{sid}"), 404, "id", "not_found")
    assert client.get("/v1/scenes").json()["total"] == len(before)


# ----------------------------------------------------------------------------------------------- 409, 503


def test_scene_not_ready_is_409_and_a_full_reconstruction_queue_is_503(client, env, tmp_path):
    before = records(env)
    rejected = metric(env, "xyzcyl_rejected_total", queue="reconstruct")
    with worker_held(env, tmp_path) as (blocker, release):   # the next job stays queued/running meanwhile
        sid = _not_ready_and_503(client, env, before, rejected)
        release()
        assert blocker.result(timeout=30) == 0
    ready = wait_state(client, sid, ("ready", "failed"))
    assert ready["state"] == "ready", ready
    assert client.get(f"/v1/scenes/{sid}/render?camera=CAM_FRONT&width=80").status_code == 200
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    err(client.get(f"/v1/scenes/{sid}/render?camera=CAM_FRONT&width=80"), 404, "id")


def _not_ready_and_503(client, env, before, rejected) -> str:
    r = client.post("/v1/scenes", files=rig_files())
    assert r.status_code == 202, r.text
    info = r.json()
    sid = info["id"]
    assert r.headers["location"] == f"/v1/scenes/{sid}" and info["state"] in ("queued", "running")
    assert set(info["links"]) == {"self"}
    for path in ("/render?camera=CAM_FRONT", "/gaussians", "/background"):
        r = client.get(f"/v1/scenes/{sid}{path}")
        err(r, 409, "id", "not_ready")
        assert r.headers["retry-after"] == "1"
    err(client.post(f"/v1/scenes/{sid}/render", json={"cameras": [{"camera": "CAM_FRONT"}]}), 409, "id",
        "not_ready")

    # reconstruct_queue=0 and one job in the worker: the next upload is refused at once
    t0 = time.monotonic()
    r = client.post("/v1/scenes", files=rig_files())
    err(r, 503, None, "busy")
    assert r.headers["retry-after"] == "1" and time.monotonic() - t0 < 5.0
    assert client.get("/v2/health/live").status_code == 200
    m = client.get("/metrics")
    assert m.status_code == 200 and 'xyzcyl_queue_depth{queue="reconstruct"} 1.0' in m.text
    assert metric(env, "xyzcyl_rejected_total", queue="reconstruct") == rejected + 1
    assert records(env) == before + 1
    return sid


def test_failed_scene_is_409_scene_failed(client, env):
    from xyzcyl.server.store import new_scene_id

    store = env.service.store
    sid = new_scene_id()
    store.create(sid, {"cameras": []})
    store.fail(sid, "invalid_input", "camera 'CAM_FRONT': K: fx must be > 0")
    info = client.get(f"/v1/scenes/{sid}").json()
    assert info["state"] == "failed" and info["error"]["code"] == "invalid_input"
    for path in ("/render?camera=CAM_FRONT", "/gaussians", "/background"):
        e = err(client.get(f"/v1/scenes/{sid}{path}"), 409, "id", "scene_failed")
        assert "fx must be > 0" in e["message"]
    err(client.post(f"/v1/scenes/{sid}/render", json={"cameras": [{"camera": "CAM_FRONT"}]}), 409, "id",
        "scene_failed")
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204


def test_killed_worker_fails_its_job_only(client, env, tmp_path):
    rec = env.service.reconstructions
    worker = rec.workers[0]
    pids = worker.pids()
    crashed = metric(env, "xyzcyl_reconstructions_total", outcome="worker_crashed")
    assert len(pids) == 1
    with worker_held(env, tmp_path) as (blocker, _):          # the job is in the worker when it dies
        r = client.post("/v1/scenes", files=rig_files())
        assert r.status_code == 202, r.text
        sid = r.json()["id"]
        wait_state(client, sid, ("running",), timeout=10)
        os.kill(pids[0], signal.SIGKILL)
        info = wait_state(client, sid, ("failed", "ready"), timeout=30)
        assert info["state"] == "failed" and info["error"]["code"] == "worker_crashed", info
        with pytest.raises(BrokenProcessPool):
            blocker.result(timeout=10)
    assert client.get("/v2/health/live").status_code == 200
    assert client.get("/v2/health/ready").status_code == 200
    assert client.get(url(env, "/render?camera=CAM_FRONT&width=80")).status_code == 200

    r = client.post("/v1/scenes?wait=60", files=rig_files())         # a fresh worker takes the next job
    assert r.status_code == 201, r.text
    assert rec.workers[0].pids() and rec.workers[0].pids() != pids
    assert metric(env, "xyzcyl_reconstructions_total", outcome="worker_crashed") == crashed + 1
    for s in (sid, r.json()["id"]):
        assert client.delete(f"/v1/scenes/{s}").status_code == 204


# ----------------------------------------------------------------------------------------------- downloads


def test_gaussians_ply(client, env, tmp_path):
    from plyfile import PlyData

    r = client.get(url(env, "/gaussians"))
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-ply"
    assert int(r.headers["content-length"]) == len(r.content)
    assert r.headers["cache-control"] and env.sid in r.headers["content-disposition"]
    path = tmp_path / "scene.ply"          # plyfile reads a real file at once (a BytesIO row by row, ~7 s)
    path.write_bytes(r.content)
    ply = PlyData.read(path)
    v = ply["vertex"]
    assert v.count == env.created.json()["gaussians"]
    names = {p.name for p in v.properties}
    assert {"x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
            "f_dc_0", "f_dc_1", "f_dc_2"} <= names
    assert np.all(np.isfinite(v["x"]))
    etag = r.headers["etag"]
    r2 = client.get(url(env, "/gaussians"), headers={"If-None-Match": etag})
    assert r2.status_code == 304 and r2.content == b"" and r2.headers["etag"] == etag
    assert client.get(url(env, "/gaussians"), headers={"If-None-Match": '"other"'}).status_code == 200


def test_gaussians_splat_by_query_and_accept(client, env):
    n = env.created.json()["gaussians"]
    r = client.get(url(env, "/gaussians?format=splat"))
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-splat"
    assert len(r.content) == 32 * n
    r2 = client.get(url(env, "/gaussians"), headers={"Accept": "application/x-splat"})
    assert r2.status_code == 200 and r2.content == r.content
    assert r.headers["etag"] != client.get(url(env, "/gaussians"), headers={"Accept": "*/*"}).headers["etag"]
    assert client.get(url(env, "/gaussians?format=splat"),
                      headers={"If-None-Match": r.headers["etag"]}).status_code == 304
    err(client.get(url(env, "/gaussians?format=obj")), 422, "format", "invalid")


def test_background_png_and_exr(client, env, tmp_path):
    r = client.get(url(env, "/background"))
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    png = decode(r.content, cv2.IMREAD_COLOR)
    assert png.ndim == 3 and png.shape[2] == 3 and png.std() > 0
    r = client.get(url(env, "/background?format=exr"))
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-exr"
    exr = read_exr_bytes(r.content, tmp_path)
    assert exr.shape == png.shape and exr.dtype == np.float32 and np.isfinite(exr).all()
    err(client.get(url(env, "/background?format=gif")), 422, "format", "invalid")


def test_scene_without_background_is_404_no_background(client, env):
    """A ready scene whose model made no background (a copy of the module's scene committed without one)."""
    import shutil

    from xyzcyl.server.store import new_scene_id

    store = env.service.store
    sid = new_scene_id()
    store.create(sid, {"cameras": env.created.json()["cameras"]})
    work = store.work_dir()
    shutil.copytree(store.scene_dir(env.sid), work / "scene")
    store.commit(sid, work / "scene", background=False, gaussians=env.created.json()["gaussians"])
    work.rmdir()
    try:
        info = client.get(f"/v1/scenes/{sid}").json()
        assert info["state"] == "ready" and "background" not in info["links"]
        err(client.get(f"/v1/scenes/{sid}/background"), 404, "id", "no_background")
        r = client.get(f"/v1/scenes/{sid}/render?camera=CAM_FRONT&width=80")
        assert r.status_code == 200 and decode(r.content).shape == (45, 80, 3)
    finally:
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204


# ----------------------------------------------------------------------------------------------- GET render


def test_render_input_camera(client, env):
    r = client.get(url(env, "/render?camera=CAM_FRONT"))
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = decode(r.content)
    assert img.shape == (450, 800, 3) and img.dtype == np.uint8 and img.std() > 5
    assert r.headers["etag"].startswith('"') and "max-age" in r.headers["cache-control"]
    small = decode(client.get(url(env, "/render?camera=CAM_BACK&width=400")).content)
    assert small.shape == (225, 400, 3)
    small = decode(client.get(url(env, "/render?camera=CAM_BACK&height=90")).content)
    assert small.shape == (90, 160, 3)


def test_render_pose_equals_the_input_camera(client, env):
    """cam_to_ego + fx, fy, cx, cy of CAM_FRONT from rig.json is the same request as camera=CAM_FRONT."""
    cam = front()
    K = cam["K"]
    by_name = client.get(url(env, "/render?camera=CAM_FRONT"))
    q = (f"/render?cam_to_ego={flat(cam['cam_to_ego'])}&fx={K[0][0]}&fy={K[1][1]}&cx={K[0][2]}&cy={K[1][2]}"
         f"&width={cam['width']}&height={cam['height']}")
    by_pose = client.get(url(env, q))
    assert by_pose.status_code == 200
    assert by_pose.headers["etag"] == by_name.headers["etag"]
    assert by_pose.content == by_name.content
    # rendered from the scene (not the render cache): identical bytes again
    env.service.views.drop_owner(env.sid)
    again = client.get(url(env, q))
    assert again.content == by_name.content


def test_render_pose_with_fov_and_carla(client, env):
    c2e = "0,0,1,1.5,-1,0,0,0,0,-1,0,1.6,0,0,0,1"          # looking forward from 1.5 m ahead, 1.6 m up
    r = client.get(url(env, f"/render?cam_to_ego={c2e}&fov=90&width=320&height=240"))
    assert r.status_code == 200
    assert decode(r.content).shape == (240, 320, 3)
    carla = client.get(url(env, "/render?x=1.5&y=0&z=1.6&pitch=0&yaw=0&roll=0&fov=90&width=320&height=240"))
    assert carla.status_code == 200 and decode(carla.content).shape == (240, 320, 3)
    assert carla.headers["etag"] == r.headers["etag"] and carla.content == r.content      # the same camera
    left = client.get(url(env, "/render?x=1.5&y=0&z=1.6&pitch=0&yaw=-90&roll=0&fov=90&width=320&height=240"))
    assert left.status_code == 200 and left.headers["etag"] != r.headers["etag"]
    err(client.get(url(env, "/render?x=1.5&y=0&z=1.6&pitch=0&yaw=0&roll=0&width=320&height=240")), 422, "fov")
    err(client.get(url(env, "/render?x=1.5&y=0&z=1.6&fov=90&width=320&height=240")), 422, "pitch")


def test_render_outputs_and_formats(client, env, tmp_path):
    base = url(env, "/render?camera=CAM_FRONT&width=320")
    r = client.get(base + "&output=depth")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    depth = decode(r.content)
    assert depth.shape == (180, 320) and depth.dtype == np.uint16
    assert (depth > 0).mean() > 0.5 and 1000 < np.median(depth[depth > 0]) < 65535     # millimetres
    r = client.get(base + "&output=depth&format=exr")
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-exr"
    z = read_exr_bytes(r.content, tmp_path)[..., 0]
    assert z.shape == (180, 320)
    near = (depth > 0) & (depth < 65535)
    assert np.allclose(z[near] * 1000.0, depth[near], atol=0.51)
    r = client.get(base + "&output=alpha")
    alpha = decode(r.content)
    assert r.status_code == 200 and alpha.shape == (180, 320) and alpha.dtype == np.uint8 and alpha.max() > 200
    r = client.get(base + "&format=jpeg&quality=80")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg" and r.content[:3] == b"\xff\xd8\xff"
    assert decode(r.content).shape == (180, 320, 3)
    low = client.get(base + "&format=jpeg&quality=10")
    assert len(low.content) < len(r.content) and low.headers["etag"] != r.headers["etag"]
    r = client.get(base + "&format=exr")
    assert r.status_code == 200 and read_exr_bytes(r.content, tmp_path).shape == (180, 320, 3)


def test_render_etag_and_304(client, env):
    q = url(env, "/render?camera=CAM_FRONT_LEFT&width=200")
    a, b = client.get(q), client.get(q)
    assert a.status_code == b.status_code == 200 and a.headers["etag"] == b.headers["etag"]
    etag = a.headers["etag"]
    r = client.get(q, headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    assert client.get(q, headers={"If-None-Match": f'"x", {etag}'}).status_code == 304
    assert client.get(q, headers={"If-None-Match": '"x"'}).status_code == 200
    for other in ("&output=alpha", "&format=jpeg", "&height=100"):
        assert client.get(q + other).headers["etag"] != etag
    assert client.get(q.replace("CAM_FRONT_LEFT", "CAM_BACK_LEFT")).headers["etag"] != etag


_C2E = "0,0,1,1.5,-1,0,0,0,0,-1,0,1.6,0,0,0,1"
RENDER_ERRORS = {
    "two poses": (f"camera=CAM_FRONT&cam_to_ego={_C2E}&fov=60&width=64&height=64", "cam_to_ego"),
    "camera and CARLA": ("camera=CAM_FRONT&yaw=1", "yaw"),
    "no pose": ("width=64&height=64", "camera"),
    "15 numbers": (f"cam_to_ego={_C2E.rsplit(',', 1)[0]}&fov=60&width=64&height=64", "cam_to_ego"),
    "not numbers": ("cam_to_ego=a,b,c&fov=60&width=64&height=64", "cam_to_ego"),
    "non-orthonormal": ("cam_to_ego=0,0,2,1.5,-1,0,0,0,0,-1,0,1.6,0,0,0,1&fov=60&width=64&height=64", "cam_to_ego"),
    "bad bottom row": ("cam_to_ego=0,0,1,1.5,-1,0,0,0,0,-1,0,1.6,0,0,1,1&fov=60&width=64&height=64", "cam_to_ego"),
    "no size": (f"cam_to_ego={_C2E}&fov=60", "width"),
    "fx and fov": (f"cam_to_ego={_C2E}&fov=60&fx=100&width=64&height=64", "fov"),
    "no intrinsics": (f"cam_to_ego={_C2E}&width=64&height=64", "fov"),
    "fov and cy": (f"cam_to_ego={_C2E}&fov=60&cy=3&width=64&height=64", "cy"),
    "negative fx": (f"cam_to_ego={_C2E}&fx=-100&width=64&height=64", "fx"),
    "fov 180": (f"cam_to_ego={_C2E}&fov=180&width=64&height=64", "fov"),
    "side over max_render_side": (f"cam_to_ego={_C2E}&fov=60&width=9000&height=100", "width"),
    "height over max_render_side": (f"cam_to_ego={_C2E}&fov=60&width=100&height=9000", "height"),
    "pixels over max_render_pixels": (f"cam_to_ego={_C2E}&fov=60&width=5000&height=5000", "width"),
    "input camera too big": ("camera=CAM_FRONT&width=8000", "width"),
    "jpeg depth": ("camera=CAM_FRONT&output=depth&format=jpeg", "format"),
    "unknown camera": ("camera=CAM_NOPE", "camera"),
    "unknown format": ("camera=CAM_FRONT&format=gif", "format"),
    "unknown output": ("camera=CAM_FRONT&output=normals", "output"),
    "quality 0": ("camera=CAM_FRONT&format=jpeg&quality=0", "quality"),
}


@pytest.mark.parametrize("case", list(RENDER_ERRORS))
def test_render_bad_request_is_422(client, env, case):
    query, field_name = RENDER_ERRORS[case]
    lookups = metric(env, "xyzcyl_render_cache_total", result="miss") + metric(
        env, "xyzcyl_render_cache_total", result="hit")
    e = err(client.get(url(env, f"/render?{query}")), 422, code="invalid")
    assert metric(env, "xyzcyl_render_cache_total", result="miss") + metric(
        env, "xyzcyl_render_cache_total", result="hit") == lookups            # refused before rendering
    assert e["field"] == field_name, e


# ----------------------------------------------------------------------------------------------- POST render


def test_render_batch_zip(client, env):
    cam = front()
    batch = {"cameras": [
        {"K": cam["K"], "cam_to_ego": cam["cam_to_ego"], "width": 800, "height": 450, "name": "front"},
        {"fov": 70, "cam_to_ego": [float(v) for v in _C2E.split(",")], "width": 160, "height": 120},
        {"transform": {"location": {"x": 1.5, "y": 0, "z": 1.6}, "rotation": {"pitch": 0, "yaw": 0, "roll": 0}},
         "fov": 90, "image_size_x": 320, "image_size_y": 240, "sensor_tick": 0.05},
        {"camera": "CAM_BACK", "width": 160},
    ]}
    r = client.post(url(env, "/render"), json=batch)
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    assert zf.testzip() is None
    assert zf.namelist() == [f"frame_{i:05d}.png" for i in range(4)] + ["index.json"]
    sizes = [(450, 800), (120, 160), (240, 320), (90, 160)]
    for i, (h, w) in enumerate(sizes):
        assert decode(zf.read(f"frame_{i:05d}.png")).shape == (h, w, 3)
    index = json.loads(zf.read("index.json"))
    assert index["scene"] == env.sid and index["output"] == "rgb" and index["format"] == "png"
    assert [(f["file"], f["height"], f["width"]) for f in index["frames"]] == [
        (f"frame_{i:05d}.png", h, w) for i, (h, w) in enumerate(sizes)]
    assert np.allclose(index["frames"][0]["K"], cam["K"]) and np.allclose(index["frames"][0]["cam_to_ego"],
                                                                          cam["cam_to_ego"])
    # the same views as GET .../render
    assert zf.read("frame_00000.png") == client.get(url(env, "/render?camera=CAM_FRONT")).content
    assert zf.read("frame_00002.png") == client.get(
        url(env, "/render?x=1.5&y=0&z=1.6&pitch=0&yaw=0&roll=0&fov=90&width=320&height=240")).content

    r = client.post(url(env, "/render?output=depth&format=exr"), json={"cameras": batch["cameras"][1:2]})
    assert r.status_code == 200
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    assert zf.namelist() == ["frame_00000.exr", "index.json"]
    r = client.post(url(env, "/render"), json={"cameras": batch["cameras"][3:], "output": "alpha",
                                                "format": "jpeg", "quality": 50})
    assert zipfile.ZipFile(io.BytesIO(r.content)).namelist() == ["frame_00000.jpg", "index.json"]


def test_render_batch_nerfstudio_camera_path(client, env):
    gl = [0, 0, -1, 1.5, -1, 0, 0, 0, 0, 1, 0, 1.6, 0, 0, 0, 1]       # OpenGL camera looking along ego +x
    doc = {"camera_type": "perspective", "render_width": 128, "render_height": 72, "seconds": 1, "fps": 3,
           "camera_path": [{"camera_to_world": gl, "fov": 50, "aspect": 16 / 9} for _ in range(3)]}
    r = client.post(url(env, "/render"), json=doc)
    assert r.status_code == 200, r.text
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    assert zf.namelist() == ["frame_00000.png", "frame_00001.png", "frame_00002.png", "index.json"]
    frames = [zf.read(n) for n in zf.namelist()[:3]]
    assert decode(frames[0]).shape == (72, 128, 3) and frames[0] == frames[1] == frames[2]
    e = err(client.post(url(env, "/render"), json={**doc, "camera_path": [{"camera_to_world": gl}]}), 422)
    assert e["field"] == "camera_path[0].fov"


BATCH_ERRORS = {
    "bad K": ({"cameras": [{"camera": "CAM_FRONT"}, {"K": [1, 2], "cam_to_ego": [0] * 16, "width": 8,
                                                       "height": 8}]}, "cameras[1].K"),
    "non-orthonormal": ({"cameras": [{"fov": 60, "cam_to_ego": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
                                      "width": 8, "height": 8}]}, "cameras[0].cam_to_ego"),
    "unknown field": ({"cameras": [{"camera": "CAM_FRONT", "fx": 3}]}, "cameras[0].fx"),
    "unknown camera": ({"cameras": [{"camera": "CAM_NOPE"}]}, "cameras[0].camera"),
    "CARLA without fov": ({"cameras": [{"transform": {"location": {"x": 0, "y": 0, "z": 0},
                                                      "rotation": {"pitch": 0, "yaw": 0, "roll": 0}},
                                        "image_size_x": 8, "image_size_y": 8}]}, "cameras[0].fov"),
    "empty": ({"cameras": []}, "cameras"),
    "no cameras": ({"frames": []}, "cameras"),
    "not an object": ([1, 2], "body"),
    "too big": ({"cameras": [{"camera": "CAM_FRONT"}, {"camera": "CAM_FRONT", "width": 9000}]}, "cameras[1]"),
    "jpeg depth": ({"cameras": [{"camera": "CAM_FRONT"}], "output": "depth", "format": "jpeg"}, "format"),
    "bad output": ({"cameras": [{"camera": "CAM_FRONT"}], "output": "normals"}, "output"),
    "bad quality": ({"cameras": [{"camera": "CAM_FRONT"}], "quality": "high"}, "quality"),
}


@pytest.mark.parametrize("case", list(BATCH_ERRORS))
def test_render_batch_bad_item_is_422(client, env, case):
    doc, field_name = BATCH_ERRORS[case]
    err(client.post(url(env, "/render"), json=doc), 422, field_name, "invalid")


def test_render_batch_media_type_and_json(client, env):
    body = json.dumps({"cameras": [{"camera": "CAM_FRONT"}]})
    err(client.post(url(env, "/render"), content=body, headers={"content-type": "text/plain"}), 415,
        "content-type", "unsupported_media_type")
    err(client.post(url(env, "/render"), files={"cameras": ("c.json", body.encode())}), 415, "content-type")
    err(client.post(url(env, "/render"), content=b"{nope", headers={"content-type": "application/json"}), 422,
        "body", "invalid")


# ----------------------------------------------------------------------------------------------- render backpressure


def test_full_render_pool_is_503_and_health_still_answers(client, env):
    renders = env.service.renders
    assert renders.limit == 1
    rejected = metric(env, "xyzcyl_rejected_total", queue="render_queue")
    release = threading.Event()
    done: list = []

    def occupy():            # a render slot held through the real admission path (Renders.run)
        done.append(client.portal.call(renders.run, release.wait, 30))

    t = threading.Thread(target=occupy, daemon=True)
    t.start()
    try:
        t0 = time.monotonic()
        while renders.inflight < 1:
            assert time.monotonic() - t0 < 10
            time.sleep(0.01)
        for r in (client.get(url(env, "/render?camera=CAM_FRONT&width=96")),
                  client.get(url(env, f"/render?cam_to_ego={_C2E}&fov=60&width=90&height=60")),
                  client.get(url(env, "/gaussians?format=splat")),
                  client.post(url(env, "/render"), json={"cameras": [{"camera": "CAM_FRONT", "width": 96}]})):
            err(r, 503, None, "busy")
            assert r.headers["retry-after"] == "1"
        assert client.get("/v2/health/live").status_code == 200
        assert client.get("/v2/health/ready").status_code == 200
        assert client.get(url(env)).status_code == 200
        assert client.get(url(env, "/gaussians")).status_code == 200        # a file stream: no render slot
        m = client.get("/metrics")
        assert m.status_code == 200 and 'xyzcyl_queue_depth{queue="render"} 1.0' in m.text
        assert metric(env, "xyzcyl_rejected_total", queue="render_queue") == rejected + 4
    finally:
        release.set()
        t.join(30)
    assert done == [True] and renders.inflight == 0
    assert client.get(url(env, "/render?camera=CAM_FRONT&width=96")).status_code == 200


# ----------------------------------------------------------------------------------------------- health, metadata


def test_health_and_model_metadata(client, env):
    assert client.get("/v2/health/live").json() == {"live": True}
    assert client.get("/v2/health/ready").json()["ready"] is True
    from xyzcyl.server import __version__

    assert client.get("/v2").json() == {"name": "xyzcyl", "version": __version__, "extensions": []}
    meta = client.get(f"/v2/models/{MODEL_NAME}").json()
    assert meta["name"] == MODEL_NAME and meta["versions"] == [env.service.info.version]
    assert meta["platform"] == "onnxruntime_onnx" and meta["inputs"] and meta["outputs"]
    assert all({"name", "datatype", "shape"} <= set(t) for t in meta["inputs"] + meta["outputs"])
    assert client.get(f"/v2/models/{MODEL_NAME}/ready").json() == {"name": MODEL_NAME, "ready": True}
    err(client.get("/v2/models/resnet50"), 404, "name", "not_found")
    err(client.get("/v2/models/resnet50/ready"), 404, "name", "not_found")
    err(client.get("/v3/nothing"), 404, None, "not_found")
    err(client.put("/v2/health/live"), 405, None, "method_not_allowed")
    doc = client.get("/openapi.json").json()
    assert {"/v1/scenes", "/v1/scenes/{scene_id}", "/v1/scenes/{scene_id}/gaussians",
            "/v1/scenes/{scene_id}/background", "/v1/scenes/{scene_id}/render", "/v2/health/live",
            "/v2/health/ready", "/v2", "/v2/models/{name}", "/metrics"} <= set(doc["paths"])


def _scrape(client: TestClient):
    """GET /metrics parsed: value(name, **labels) sums the samples whose labels match."""
    from prometheus_client.parser import text_string_to_metric_families

    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    samples: dict = {}
    for fam in text_string_to_metric_families(r.text):
        for s in fam.samples:
            samples.setdefault(s.name, []).append((s.labels, s.value))

    def value(name: str, **labels) -> float:
        return sum(v for lab, v in samples.get(name, []) if all(lab.get(k) == x for k, x in labels.items()))

    return value, r.text


def test_metrics(client, env):
    route = "/v1/scenes/{scene_id}/render"
    req = "xyzcyl_http_requests_total"
    before, _ = _scrape(client)
    assert client.get(url(env, "/render?camera=CAM_BACK_RIGHT&width=72")).status_code == 200
    assert client.get(url(env, "/render?camera=CAM_BACK_RIGHT&width=72")).status_code == 200     # cached
    assert client.get(url(env, "/render?camera=NOPE")).status_code == 422
    assert client.get("/no/such/route").status_code == 404
    assert client.post("/v1/scenes", content=b"x" * (BODY_LIMIT + 1),
                       headers={"content-type": "multipart/form-data; boundary=x"}).status_code == 413
    after, text = _scrape(client)

    def delta(name, **labels):
        return after(name, **labels) - before(name, **labels)

    assert delta(req, route=route, method="GET", status="200") == 2
    assert delta(req, route=route, method="GET", status="422") == 1
    assert delta(req, route="unmatched", method="GET", status="404") == 1
    # a 413 from Content-Length is answered before routing, so it counts under "unmatched"
    assert delta(req, method="POST", status="413") == 1
    assert delta("xyzcyl_http_request_duration_seconds_count", route=route, method="GET") == 3
    assert delta("xyzcyl_render_duration_seconds_count") == 1
    assert delta("xyzcyl_render_cache_total", result="miss") == 1
    assert delta("xyzcyl_render_cache_total", result="hit") == 1
    assert after(req, route="/v1/scenes", method="POST", status="201") >= 1        # the module's scene
    assert after("xyzcyl_reconstructions_total", outcome="ready") >= 1
    assert after("xyzcyl_reconstruction_duration_seconds_count") >= 1
    assert env.sid not in text                                   # route templates, never ids
    usage = env.service.store.usage()
    for state in ("queued", "running", "ready", "failed"):
        assert after("xyzcyl_scenes", state=state) == usage["scenes"][state]
    assert usage["scenes"]["ready"] >= 1
    assert after("xyzcyl_store_bytes") == usage["bytes"] > 0
    assert after("xyzcyl_queue_depth", queue="render") == 0 and after("xyzcyl_queue_depth", queue="reconstruct") == 0


# ----------------------------------------------------------------------------------------------- API keys, CORS


def _v1_routes(client: TestClient) -> list[tuple[str, str]]:
    paths = client.app.openapi()["paths"]          # from the app: with API keys /openapi.json is not served
    return [(m.upper(), p.replace("{scene_id}", "AAAAAAAAAAAAAAAAAAAAAA"))
            for p, ops in paths.items() if p.startswith("/v1") for m in ops]


def test_api_keys(tmp_path):
    key = "secret-key-1"
    client = cold_client(tmp_path, api_keys=(key, "another-key-2"))
    routes = _v1_routes(client)
    assert len(routes) == 8
    for method, path in routes:
        for headers in ({}, {"Authorization": "Bearer wrong-key-99"}, {"X-API-Key": "secret-key-"},
                        {"Authorization": f"Basic {key}"}, {"Authorization": "Bearer "},
                        {"X-API-Key": key + "x"}):
            r = client.request(method, path, headers=headers)
            err(r, 401, None, "unauthorized")
            assert r.headers["www-authenticate"] == "Bearer"
            assert key not in r.text
    for headers in ({"Authorization": f"Bearer {key}"}, {"authorization": f"bearer {key}"},
                    {"X-API-Key": key}, {"X-API-Key": "another-key-2"}):
        r = client.get("/v1/scenes", headers=headers)
        assert r.status_code == 200 and r.json()["total"] == 0
        err(client.get("/v1/scenes/AAAAAAAAAAAAAAAAAAAAAA", headers=headers), 404, "id")
        err(client.delete("/v1/scenes/AAAAAAAAAAAAAAAAAAAAAA", headers=headers), 404, "id")
    for path in ("/v2/health/live", "/v2", f"/v2/models/{MODEL_NAME}", "/metrics"):
        assert client.get(path).status_code == 200, path
    assert client.get("/v2/health/ready").status_code == 503          # open (not 401); the model is not loaded


def test_api_keys_are_off_by_default(client):
    assert client.get("/v1/scenes").status_code == 200


def test_cors_off_by_default(client, env):
    r = client.get("/v2/health/live", headers={"Origin": "https://example.org"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
    r = client.options("/v1/scenes", headers={"Origin": "https://example.org", "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in r.headers


def test_cors_when_configured(tmp_path):
    client = cold_client(tmp_path, cors_origins=("https://example.org",))
    r = client.get("/v1/scenes", headers={"Origin": "https://example.org"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://example.org"
    assert "etag" in r.headers["access-control-expose-headers"].lower()
    r = client.options("/v1/scenes", headers={"Origin": "https://example.org", "Access-Control-Request-Method": "POST",
                                              "Access-Control-Request-Headers": "x-api-key"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://example.org"
    r = client.get("/v1/scenes", headers={"Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in r.headers
    r = client.options("/v1/scenes", headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"})
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers


# ----------------------------------------------------------------------------------------------- server header


def test_no_server_header(env, tmp_path):
    for path in ("/v2/health/live", "/metrics", url(env), url(env, "/render?camera=CAM_FRONT&width=64"),
                 "/nowhere", url(env, "/render?camera=NOPE")):
        env.client.get(path)
    assert len(env.responses) > 8
    leaks = [(str(r.request.url), r.headers["server"]) for r in env.responses if "server" in r.headers]
    assert leaks == []
    # a response that does carry one (as a framework or a handler might add it) loses it in the middleware
    from fastapi.responses import Response

    cold = cold_client(tmp_path)
    cold.app.add_api_route("/leaky", lambda: Response(b"x", headers={"Server": "leaky/1.0"}))
    r = cold.get("/leaky")
    assert r.status_code == 200 and r.content == b"x" and "server" not in r.headers
