"""The scenes router (server/routes/scenes.py) in process (fastapi TestClient = httpx over ASGI, the lifespan runs):
POST /v1/scenes and every status of issue 12 item 5 it answers (docs/api.md's error table: 413, 415, 422, 503,
507), the list, a scene's record, DELETE, 409 for scenes not ready or failed, a reconstruction worker that dies, and
the downloads (Gaussians, background). The app and its scene are tests/server/conftest.py's ``env``; tests run in
file order and each leaves no job running behind it."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import time
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from api_helpers import BODY_LIMIT, MODEL_NAME, Env, decode, err, metric, read_exr_bytes, url
from fastapi.testclient import TestClient
from xyzcyl.testing.rigs import example_images, example_rig, multipart_body, png_header_only, rig_files

# ----------------------------------------------------------------------------------------------- helpers


CHUNK = 64 << 10


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


def records(env: Env) -> int:
    return env.service.store.list()[1]


def tmp_left(env: Env) -> list[str]:
    return [p.name for p in (env.store_root / "tmp").iterdir() if not p.name.startswith("deleted-")]


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
    """Regression (issue 27, defect 5): 'rig: rig: cameras: must have 1..16 entries' and 'K[0][0]: fx must be > 0
    (got np.float64(-633.0))'."""
    e = err(client.post("/v1/scenes?wait=5", files=rig_files(_rig_with(_no_cameras))), 422, "rig", "invalid")
    assert e["message"] == "rig: cameras: must have 1..16 entries (got 0)", e
    e = err(client.post("/v1/scenes?wait=5", files=rig_files(_rig_with(_bad_fx))), 422, "rig", "invalid")
    assert e["message"] == "camera 'CAM_FRONT_RIGHT': K[0][0]: fx must be > 0 (got -633.0)", e


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
    assert 0 < c["detail"] <= 6 * 100 * 57 < plain["counts"]["detail"] and c["total"] == c["coarse"] + c["detail"] + c["carved"] + 3 * c["split"]
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
    assert records(env) == before and store.get(env.sid).state == "ready" and tmp_left(env) == []


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
    before = {r.id for r in store.list(0, 1000)[0]}
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
