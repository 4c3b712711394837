"""One set of view options everywhere (issue 35, item 5): a camera move (forward / left / up metres along ego x / y
/ z, yaw degrees to the left; common.poses.CameraMove) and a lens on an input camera are taken alike by
`xyzcyl render` (local), `xyzcyl client render` and the Python Client (over HTTP), GET .../render's query and the
items of POST .../render, all resolved by runtime.views.move_camera. Each path's bytes are compared with the
others' and with a direct runtime render; a plain request (no move, no lens) still gives the bytes of a direct
runtime render of the unmoved camera. The app and its scene are tests/server/conftest.py's ``env``; the CLI
commands run in process, `xyzcyl client` through the app's TestClient."""

from __future__ import annotations

import io
import json
import zipfile
from urllib.parse import quote

import pytest
from api_helpers import err, url

FISHEYE = {"model": "opencv_fisheye", "k1": 0.02, "k2": -0.005, "k3": 0.0, "k4": 0.0, "max_angle_deg": 95.0}
MOVE = {"forward": 1.0, "left": 0.5, "up": -0.25, "yaw": 10.0}
WIDTH = 160                      # CAM_FRONT (800x450) at 160x90: fast renders


@pytest.fixture(scope="module")
def scene(env):
    """The loaded runtime Scene and its folder."""
    return env.service.load_scene(env.sid), env.service.store.scene_dir(env.sid)


def runtime_bytes(scene, camera, output="rgb", fmt="png") -> bytes:
    """The view rendered and encoded by the runtime directly (render_view + encode_view), no front end."""
    from xyzcyl.runtime.scene import render_view
    from xyzcyl.runtime.views import ViewRequest, encode_view

    rgb, depth, alpha = render_view(scene[0], camera)
    return encode_view(rgb, depth, alpha, ViewRequest(camera, output, fmt))


def front(scene, width=WIDTH, distortion=None):
    """CAM_FRONT at ``width`` (the input camera, resized; optionally through another lens), from the rig."""
    from xyzcyl.runtime.scene import rig_camera

    cam = scene[0].rig.camera("CAM_FRONT")
    c = rig_camera(cam, width=width, height=round(width * cam.height / cam.width))
    return c if distortion is None else c.replace(distortion=distortion)


def moved(camera):
    from xyzcyl.common.poses import CameraMove

    return camera.replace(cam_to_ego=CameraMove(**MOVE).apply(camera.cam_to_ego))


def batch_frames(client, env, cameras, **query) -> list[bytes]:
    r = client.post(url(env, "/render"), params=query, json={"cameras": cameras})
    assert r.status_code == 200, r.text
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    return [zf.read(n) for n in zf.namelist() if n != "index.json"]


def query(params: dict) -> str:
    return "&".join(f"{k}={quote(str(v))}" for k, v in params.items())


# ----------------------------------------------------------------------------------------------- unchanged


def test_plain_requests_are_the_runtime_render(client, env, scene):
    """No move, no lens: GET and a batch item give exactly the bytes of the runtime's render of the unmoved input
    camera (render_view + encode_view), as before the move options existed."""
    cam = front(scene)
    expected = runtime_bytes(scene, cam)
    env.service.views.drop_owner(env.sid)                      # rendered now, not from the render cache
    r = client.get(url(env, f"/render?camera=CAM_FRONT&width={WIDTH}"))
    assert r.status_code == 200 and r.content == expected
    assert batch_frames(client, env, [{"camera": "CAM_FRONT", "width": WIDTH}]) == [expected]
    # an explicit pose: the same camera pasted as cam_to_ego + fx, fy, cx, cy
    K = cam.K
    pasted = {"cam_to_ego": ",".join(repr(float(v)) for v in cam.cam_to_ego.ravel()), "fx": K[0, 0], "fy": K[1, 1],
              "cx": K[0, 2], "cy": K[1, 2], "width": cam.width, "height": cam.height}
    assert client.get(url(env, "/render?" + query(pasted))).content == expected
    # a move of zero is no move: the same ETag
    zero = client.get(url(env, f"/render?camera=CAM_FRONT&width={WIDTH}&forward=0&yaw=0"))
    assert zero.status_code == 200 and zero.headers["etag"] == r.headers["etag"] and zero.content == expected


# ----------------------------------------------------------------------------------------------- moves


def test_a_moved_input_camera_is_the_same_view_everywhere(client, env, scene, tmp_path, capsys, monkeypatch):
    """GET ?camera=CAM_FRONT&forward=..&left=..&up=..&yaw=.., a batch item with the same keys, `xyzcyl render
    SCENE_DIR --camera CAM_FRONT --forward ..`, `xyzcyl client render SID --camera CAM_FRONT --forward ..` and
    Client.render_bytes(sid, "CAM_FRONT", move=...) all give the runtime's render of the moved camera."""
    from xyzcyl import cli
    from xyzcyl.clients.client import Client

    expected = runtime_bytes(scene, moved(front(scene)))
    assert expected != runtime_bytes(scene, front(scene))
    r = client.get(url(env, f"/render?camera=CAM_FRONT&width={WIDTH}&" + query(MOVE)))
    assert r.status_code == 200, r.text
    assert r.content == expected
    assert batch_frames(client, env, [{"camera": "CAM_FRONT", "width": WIDTH, **MOVE}]) == [expected]

    flags = [f"--{k}={v}" for k, v in MOVE.items()]
    local = tmp_path / "local.png"
    assert cli.main(["render", str(scene[1]), "--camera", "CAM_FRONT", "--width", str(WIDTH), *flags,
                     "--out", str(local)]) == 0
    assert local.read_bytes() == expected

    _through_the_app(monkeypatch, client)
    over_http = tmp_path / "client.png"
    capsys.readouterr()
    rc = cli.main(["client", "render", env.sid, "--camera", "CAM_FRONT", "--width", str(WIDTH), *flags,
                   "--out", str(over_http), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    assert over_http.read_bytes() == local.read_bytes()

    c = Client(http_client=client)
    assert c.render_bytes(env.sid, "CAM_FRONT", width=WIDTH, move=MOVE) == expected


def test_a_moved_explicit_pose_is_the_moved_camera(client, env, scene):
    """A move on cam_to_ego applies to that pose (as `xyzcyl render --cam-to-world M --forward ..` always did):
    GET and a batch item with fov give the runtime's render of the moved pose."""
    from xyzcyl.runtime.views import camera_from_opencv

    c2e = [0, 0, 1, 1.5, -1, 0, 0, 0, 0, -1, 0, 1.6, 0, 0, 0, 1]
    expected = runtime_bytes(scene, moved(camera_from_opencv(c2e, 120, 90, fov=80)))
    r = client.get(url(env, "/render?" + query({"cam_to_ego": ",".join(map(str, c2e)), "fov": 80, "width": 120,
                                                 "height": 90, **MOVE})))
    assert r.status_code == 200 and r.content == expected
    item = {"fov": 80, "cam_to_ego": c2e, "width": 120, "height": 90, **MOVE}
    assert batch_frames(client, env, [item]) == [expected]


# ----------------------------------------------------------------------------------------------- a lens


def test_a_lens_on_an_input_camera_is_its_pose_pasted(client, env, scene, tmp_path, capsys, monkeypatch):
    """?camera=CAM_FRONT&distortion=FISHEYE: CAM_FRONT's pose and K through the fisheye, byte for byte the view
    with its 4x4 and K pasted (cam_to_ego + fx/fy/cx/cy + distortion), in GET, a batch item, `xyzcyl render` and
    `xyzcyl client render`; moved too."""
    from xyzcyl import cli

    cam = front(scene, distortion=FISHEYE)
    expected = runtime_bytes(scene, cam)
    lens = json.dumps(FISHEYE)
    by_name = client.get(url(env, "/render?" + query({"camera": "CAM_FRONT", "width": WIDTH, "distortion": lens})))
    assert by_name.status_code == 200, by_name.text
    K = cam.K
    pasted = client.get(url(env, "/render?" + query({
        "cam_to_ego": ",".join(repr(float(v)) for v in cam.cam_to_ego.ravel()), "fx": K[0, 0], "fy": K[1, 1],
        "cx": K[0, 2], "cy": K[1, 2], "width": cam.width, "height": cam.height, "distortion": lens})))
    assert pasted.status_code == 200, pasted.text
    assert by_name.content == pasted.content == expected
    assert by_name.headers["etag"] == pasted.headers["etag"]
    assert expected != runtime_bytes(scene, front(scene))            # the lens is drawn
    assert batch_frames(client, env, [{"camera": "CAM_FRONT", "width": WIDTH, "distortion": FISHEYE}]) == [expected]

    local = tmp_path / "fisheye.png"
    assert cli.main(["render", str(scene[1]), "--camera", "CAM_FRONT", "--width", str(WIDTH), "--distortion", lens,
                     "--out", str(local)]) == 0
    assert local.read_bytes() == expected
    _through_the_app(monkeypatch, client)
    capsys.readouterr()
    rc = cli.main(["client", "render", env.sid, "--camera", "CAM_FRONT", "--width", str(WIDTH), "--distortion",
                   lens, "--forward", "1", "--out", str(tmp_path / "c.png"), "-q"])
    assert rc == 0, capsys.readouterr().err
    from xyzcyl.common.poses import CameraMove

    assert (tmp_path / "c.png").read_bytes() == runtime_bytes(
        scene, cam.replace(cam_to_ego=CameraMove(forward=1).apply(cam.cam_to_ego)))


# ----------------------------------------------------------------------------------------------- refusals


MOVE_ERRORS = {
    "not finite": ("camera=CAM_FRONT&forward=nan", "forward"),
    "too far": ("camera=CAM_FRONT&left=1e6", "left"),
    "too much turn": ("camera=CAM_FRONT&yaw=1000", "yaw"),
    "not a number": ("camera=CAM_FRONT&up=high", "up"),
    "move on a CARLA pose": ("x=1.5&y=0&z=1.6&pitch=0&yaw=0&roll=0&fov=90&width=64&height=48&forward=1", "forward"),
    "a bad lens on an input camera":
        ("camera=CAM_FRONT&distortion=" + quote('{"model": "opencv_fisheye", "k1": "x", "max_angle_deg": 95}'),
         "distortion.k1"),
    "lens on a CARLA pose": ("x=1.5&y=0&z=1.6&pitch=0&yaw=0&roll=0&fov=90&width=64&height=48&distortion="
                             + quote("[0.1, 0, 0, 0]"), "distortion"),
}


@pytest.mark.parametrize("case", list(MOVE_ERRORS))
def test_bad_moves_and_lenses_are_422_naming_the_field(client, env, case):
    q, field_name = MOVE_ERRORS[case]
    e = err(client.get(url(env, f"/render?{q}")), 422, code="invalid")
    assert e["field"] == field_name, e
    assert e["message"].startswith(f"{field_name}: "), e


BATCH_MOVE_ERRORS = {
    "not a number": ({"camera": "CAM_FRONT", "forward": "far"}, "cameras[0].forward"),
    "bool": ({"camera": "CAM_FRONT", "left": True}, "cameras[0].left"),
    "too much turn": ({"fov": 60, "cam_to_ego": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], "width": 8,
                       "height": 8, "yaw": -400}, "cameras[0].yaw"),
    "CARLA item": ({"transform": {"location": {"x": 0, "y": 0, "z": 1}, "rotation": {"pitch": 0, "yaw": 0, "roll": 0}},
                    "fov": 90, "image_size_x": 8, "image_size_y": 8, "yaw": 5}, "cameras[0].yaw"),
    "a misspelt move": ({"camera": "CAM_FRONT", "foward": 1}, "cameras[0].foward"),
}


@pytest.mark.parametrize("case", list(BATCH_MOVE_ERRORS))
def test_bad_batch_moves_are_422_naming_the_json_path(client, env, case):
    item, field_name = BATCH_MOVE_ERRORS[case]
    e = err(client.post(url(env, "/render"), json={"cameras": [item]}), 422, field_name, "invalid")
    assert e["message"].startswith(f"{field_name}: "), e


def test_the_openapi_document_lists_the_move_parameters(client):
    from xyzcyl.common.poses import MOVE_NAMES

    params = {p["name"]: p for p in client.get("/openapi.json").json()["paths"]["/v1/scenes/{scene_id}/render"]
              ["get"]["parameters"]}
    for name in MOVE_NAMES:
        assert name in params and "camera move" in params[name].get("description", ""), params.get(name)
    assert "camera" in params["distortion"]["description"]


# ----------------------------------------------------------------------------------------------- helpers


def _through_the_app(monkeypatch, test_client) -> None:
    """`xyzcyl client` talks to the in-process app: its Client gets the TestClient as its httpx client."""
    from xyzcyl.clients import client as client_module

    real = client_module.Client
    monkeypatch.setattr(client_module, "Client", lambda *a, **kw: real(*a, **{**kw, "http_client": test_client}))
    monkeypatch.delenv("XYZCYL_API_KEY", raising=False)
