"""The render router (server/routes/render.py) in process: GET .../render by input camera, OpenCV pose, FOV or CARLA
pose, its outputs and formats, ETag and 304, every 422; the POST batch (zip, nerfstudio camera path); a full render
pool answers 503 while health still answers. The app and its scene are tests/server/conftest.py's ``env``."""

from __future__ import annotations

import io
import json
import threading
import time
import zipfile
from urllib.parse import quote

import numpy as np
import pytest
from api_helpers import decode, err, metric, read_exr_bytes, url
from xyzcyl.testing.rigs import example_rig

# ----------------------------------------------------------------------------------------------- helpers


def front() -> dict:
    return example_rig()["cameras"][0]


def flat(m) -> str:
    return ",".join(repr(float(v)) for row in m for v in row)


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


def test_render_fisheye_equals_the_runtime_render(client, env):
    """A lens in the GET query (issue 28): the answer is the runtime's render of the same lens camera, byte for
    byte, and its ETag differs from the ideal pinhole's at the same pose."""
    from xyzcyl.common.wire import validated
    from xyzcyl.runtime.views import ViewRequest, render_request, resolve

    c2e = "0,0,1,1.5,-1,0,0,0,0,-1,0,1.6,0,0,0,1"
    lens = {"model": "opencv_fisheye", "k1": 0.02, "k2": -0.005, "k3": 0.0, "k4": 0.0, "max_angle_deg": 95.0}
    q = f"/render?cam_to_ego={c2e}&fx=60&width=240&height=180&distortion={quote(json.dumps(lens))}"
    r = client.get(url(env, q))
    assert r.status_code == 200, r.text
    pinhole = client.get(url(env, f"/render?cam_to_ego={c2e}&fx=60&width=240&height=180"))
    assert pinhole.status_code == 200 and pinhole.headers["etag"] != r.headers["etag"]
    cam = resolve(validated(dict(cam_to_ego=[float(v) for v in c2e.split(",")], fx=60, width=240, height=180,
                                 distortion=lens)))
    assert r.content == render_request(env.service.load_scene(env.sid), ViewRequest(cam))
    img = decode(r.content)
    assert img.shape == (180, 240, 3) and img[0, 0].max() == 0          # outside the 190-degree image circle: black


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
    "camera and CARLA": ("camera=CAM_FRONT&pitch=1", "pitch"),     # (with camera, yaw is the move's: issue 35)
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
    "side over max_render_side": (f"cam_to_ego={_C2E}&fov=60&width=17000&height=100", "width"),
    "height over max_render_side": (f"cam_to_ego={_C2E}&fov=60&width=100&height=17000", "height"),
    "pixels over max_render_pixels": (f"cam_to_ego={_C2E}&fov=60&width=5000&height=5000", "width"),
    "input camera too big": ("camera=CAM_FRONT&width=8000", "width"),
    "jpeg depth": ("camera=CAM_FRONT&output=depth&format=jpeg", "format"),
    "unknown camera": ("camera=CAM_NOPE", "camera"),
    "unknown format": ("camera=CAM_FRONT&format=gif", "format"),
    "unknown output": ("camera=CAM_FRONT&output=normals", "output"),
    "quality 0": ("camera=CAM_FRONT&format=jpeg&quality=0", "quality"),
    "lens not JSON": (f"cam_to_ego={_C2E}&fov=60&width=64&height=64&distortion=%7Bnope", "distortion"),
    "lens field": (f"cam_to_ego={_C2E}&fov=60&width=64&height=64&distortion="
                   + quote('{"model": "opencv_fisheye", "k1": "x", "max_angle_deg": 95}'), "distortion.k1"),
    "lens max angle": (f"cam_to_ego={_C2E}&fov=60&width=64&height=64&distortion="
                       + quote('{"model": "ftheta", "pixeldist_to_angle_poly": [0, 0.02], "max_angle_deg": 181}'),
                       "distortion.max_angle_deg"),
    "bad lens on an input camera": ("camera=CAM_FRONT&distortion=" + quote("[0.1, 0, 0]"), "distortion"),
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
    "too big": ({"cameras": [{"camera": "CAM_FRONT"}, {"camera": "CAM_FRONT", "width": 9000}]}, "cameras[1].width"),
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
