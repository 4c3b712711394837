"""Every answer of the render front ends is pinned: a corpus of GET .../render queries, POST .../render bodies and
gRPC RGBRenderRequests (good ones and every kind of bad one) is sent, and each answer is compared with the one
recorded in wire_answers.json: the status and the whole error body (code, message, field), and for a rendered view
the canonical description of what was rendered (runtime.views.ViewRequest.description: camera model, K, cam_to_ego
to 1e-9, lens, size, output, format, quality; the ETag hashes exactly this), the media type and, for a batch, its
index.json. The description pins the pixels without depending on this machine's floating point: the renderer is a
function of it (tests/runtime/render covers that function).

The corpus was recorded from the code before the render query became one typed ViewQuery (common.wire), then
re-recorded once, deliberately, by that change: every rendered view (its description, media type, batch index),
every status and every error's code and field stayed as they were; 15 error messages read differently because one
type now states each refusal once (a batch item's value errors read as the GET query's, pydantic's wording; a
non-finite pose entry is named by its [row][column]; a nerfstudio pose's errors read as every other pose's), and a
gRPC image_format outside the protocol's enum is now refused naming the field (it raised a ValueError: INTERNAL).
A refactoring of the view path that changes any answer fails here. Re-record deliberately with
XYZCYL_RECORD_WIRE=1 (and say why in the commit).

The app and its scene are conftest.py's ``env`` (the example rig, cameras 800x450); the gRPC requests go through
the servicer's conversion (frames) with the example scene's ego pose, no gRPC server needed."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest

RECORD = Path(__file__).with_name("wire_answers.json")
REC = os.environ.get("XYZCYL_RECORD_WIRE") == "1"

C2E = "0,0,1,0.5, -1,0,0,0.1, 0,-1,0,1.6, 0,0,0,1"          # looking along ego +x from 1.6 m up
C2E_LIST = [[0, 0, 1, 0.5], [-1, 0, 0, 0.1], [0, -1, 0, 1.6], [0, 0, 0, 1]]
FISHEYE = json.dumps({"model": "opencv_fisheye", "k1": 0.02, "k2": -0.005, "k3": 0.0, "k4": 0.0,
                      "max_angle_deg": 95.0})
FTHETA = json.dumps({"model": "ftheta", "reference": "angle", "poly": [0.0, 0.0025, 0.0, 0.0, 0.0],
                     "max_angle_deg": 100.0})
CARLA = "x=1.5&y=0.2&z=2.4&pitch=-5&yaw=15&roll=0.5&fov=90&width=64&height=36"

GET = [
    # good: every pose, output and format
    "camera=CAM_FRONT&width=64",
    "camera=CAM_FRONT&height=20",
    "camera=CAM_FRONT&width=64&height=40",
    "camera=CAM_BACK_LEFT&width=64&output=depth",
    "camera=CAM_FRONT&width=64&output=alpha&format=jpeg&quality=70",
    "camera=CAM_FRONT&width=64&format=exr",
    "camera=CAM_FRONT&width=64&output=depth&format=exr",
    "camera=CAM_FRONT&width=64&format=jpeg",
    "camera=CAM_FRONT&width=64&forward=1&left=-0.5&up=0.25&yaw=10",
    "camera=CAM_FRONT&width=64&yaw=-30",
    "camera=CAM_FRONT&width=64&distortion=" + quote("[0,0,0,0]"),
    "camera=CAM_FRONT&width=64&distortion=" + quote("[-0.1,0.01,0.001,0.0005,0.0]"),
    "camera=CAM_FRONT&width=64&distortion=" + quote(FISHEYE),
    "camera=CAM_FRONT&width=64&distortion=" + quote(FTHETA),
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fx=50",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fx=50&fy=55&cx=30.5&cy=17",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=120&distortion=" + quote(FISHEYE),
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&forward=2&yaw=5",
    f"cam_to_ego={quote(C2E.replace(' ', ''))},&width=64&height=36&fov=70",     # a trailing comma
    f"cam_to_ego={quote('0,0,1,0.5,-1,0,0,0.1,0,-1,0,1.6,0,0,0,1e0')}&width=64&height=36&fov=70",
    CARLA,
    CARLA.replace("yaw=15", "yaw=-170"),
    # bad: the pose
    "width=64",
    "camera=CAM_FRONT&cam_to_ego=" + quote(C2E) + "&width=64",
    "camera=CAM_FRONT&x=1&width=64",
    f"cam_to_ego={quote(C2E)}&{CARLA}",
    "camera=NOPE&width=64",
    "camera=" + "A" * 300,
    f"cam_to_ego={quote('1,2,3')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote('0,0,1,0.5,-1,0,0,0.1,0,-1,0,1.6,0,0,0,x')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote('0,0,1,0.5,-1,0,0,0.1,0,-1,0,1.6,0,0,0,nan')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote('1,0,0,0,0,1,0,0,0,0,2,0,0,0,0,1')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote('1,0,0,0,0,1,0,0,0,0,1,0,0,0,1,1')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote('1,0,0,0,0,1,0,0,0,0,-1,0,0,0,0,1')}&width=64&height=36&fov=70",
    f"cam_to_ego={quote(C2E)}&height=36&fov=70",
    f"cam_to_ego={quote(C2E)}&width=64&fov=70",
    f"cam_to_ego={quote(C2E)}&width=64&height=36",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&fx=50",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&cy=3",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fx=-1",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fx=0",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fx=inf",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&cx=nan&fx=5",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=180",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=0",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=abc",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&distortion=notjson",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&distortion=3",
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&distortion=" + quote('{"model":"bogus"}'),
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&distortion=" + quote("[1,2,3]"),
    f"cam_to_ego={quote(C2E)}&width=64&height=36&fov=70&distortion=" + quote('{"model":"opencv_fisheye","k1":"a"}'),
    f"{CARLA}&distortion=" + quote("[0,0,0,0]"),
    f"{CARLA}&forward=1",
    CARLA.replace("&roll=0.5", ""),
    CARLA.replace("&fov=90", ""),
    CARLA.replace("&width=64", ""),
    CARLA.replace("x=1.5", "x=nan"),
    CARLA.replace("pitch=-5", "pitch=inf"),
    "camera=CAM_FRONT&width=64&forward=nan",
    "camera=CAM_FRONT&width=64&forward=2000",
    "camera=CAM_FRONT&width=64&yaw=1000",
    "camera=CAM_FRONT&width=64&left=abc",
    # bad: size, output, format
    "camera=CAM_FRONT&width=0",
    "camera=CAM_FRONT&width=-3",
    "camera=CAM_FRONT&width=2.5",
    "camera=CAM_FRONT&width=99999",
    "camera=CAM_FRONT&width=16384",
    f"cam_to_ego={quote(C2E)}&width=5000&height=5000&fov=70",
    "camera=CAM_FRONT&width=64&output=rgba",
    "camera=CAM_FRONT&width=64&output=all",
    "camera=CAM_FRONT&width=64&format=gif",
    "camera=CAM_FRONT&width=64&quality=0",
    "camera=CAM_FRONT&width=64&quality=101",
    "camera=CAM_FRONT&width=64&quality=5.5",
    "camera=CAM_FRONT&width=64&output=depth&format=jpeg",
    "camera=CAM_FRONT&widht=64",
]

ITEM_K = {"K": [[50, 0, 31.5], [0, 50, 17.5], [0, 0, 1]], "cam_to_ego": C2E_LIST, "width": 64, "height": 36}
ITEM_FOV = {"fov": 70, "cam_to_ego": [v for r in C2E_LIST for v in r], "width": 64, "height": 36}
ITEM_CARLA = {"transform": {"location": {"x": 1.5, "y": 0.2, "z": 2.4},
                            "rotation": {"pitch": -5, "yaw": 15, "roll": 0.5}},
              "fov": 90, "image_size_x": 64, "image_size_y": 36, "sensor_tick": 0.1}
ITEM_RIG = {"camera": "CAM_FRONT", "width": 64}
NS_PATH = {"render_width": 64, "render_height": 36, "camera_type": "perspective",
           "camera_path": [{"camera_to_world": [0, 0, 1, 0.5, -1, 0, 0, 0.1, 0, -1, 0, 1.6, 0, 0, 0, 1],
                            "fov": 50, "aspect": 1.7}]}


def _with(item: dict, **kw) -> dict:
    out = {k: v for k, v in item.items() if k not in kw}
    out.update({k: v for k, v in kw.items() if v is not None})
    return out


def _without(item: dict, key: str) -> dict:
    return {k: v for k, v in item.items() if k != key}


BATCH: list[tuple[str, object]] = [
    # (query, body); good
    ("", {"cameras": [ITEM_K, ITEM_FOV, ITEM_CARLA, ITEM_RIG]}),
    ("", {"cameras": [ITEM_RIG, _with(ITEM_RIG, distortion=json.loads(FISHEYE), forward=1, yaw=5, name="a")],
          "output": "depth"}),
    ("output=alpha&format=jpeg&quality=60", {"cameras": [ITEM_FOV], "output": "depth"}),
    ("", {"cameras": [_with(ITEM_K, distortion=[-0.1, 0.01, 0, 0, 0], left=0.5)], "format": "exr"}),
    ("", {"cameras": [ITEM_FOV], "format": "jpeg", "quality": 50}),
    ("", NS_PATH),
    ("", _with(NS_PATH, camera_type="fisheye")),
    ("", _with(NS_PATH, camera_type="equirectangular")),
    # bad: the document
    ("", []),
    ("", {}),
    ("", {"cameras": []}),
    ("", {"cameras": "x"}),
    ("", {"cameras": [ITEM_FOV], "camera_path": []}),
    ("", {"cameras": [3]}),
    ("", {"cameras": [{"width": 3}]}),
    ("", {"cameras": [ITEM_FOV], "output": "all"}),
    ("", {"cameras": [ITEM_FOV], "format": "gif"}),
    ("", {"cameras": [ITEM_FOV], "quality": 0}),
    ("", {"cameras": [ITEM_FOV], "quality": True}),
    ("", {"cameras": [ITEM_FOV], "output": "depth", "format": "jpeg"}),
    ("format=jpeg", {"cameras": [ITEM_FOV], "output": "depth"}),
    # bad: an item
    ("", {"cameras": [_with(ITEM_K, widht=3)]}),
    ("", {"cameras": [_without(ITEM_K, "width")]}),
    ("", {"cameras": [_without(ITEM_K, "cam_to_ego")]}),
    ("", {"cameras": [_with(ITEM_K, K=[[50, 1, 31.5], [0, 50, 17.5], [0, 0, 1]])]}),
    ("", {"cameras": [_with(ITEM_K, K=[1, 2, 3])]}),
    ("", {"cameras": [_with(ITEM_K, K=[[-50, 0, 31.5], [0, 50, 17.5], [0, 0, 1]])]}),
    ("", {"cameras": [_with(ITEM_K, cam_to_ego=[1, 2])]}),
    ("", {"cameras": [_with(ITEM_K, cam_to_ego="0,0,1,0")]}),
    ("", {"cameras": [_with(ITEM_K, cam_to_ego=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]])]}),
    ("", {"cameras": [_with(ITEM_FOV, fov=200)]}),
    ("", {"cameras": [_with(ITEM_FOV, fov="70")]}),
    ("", {"cameras": [_with(ITEM_FOV, width=2.5)]}),
    ("", {"cameras": [_with(ITEM_FOV, width=True)]}),
    ("", {"cameras": [_with(ITEM_FOV, width=20000)]}),
    ("", {"cameras": [_with(ITEM_FOV, width=5000, height=5000)]}),
    ("", {"cameras": [_with(ITEM_FOV, distortion={"model": "bogus"})]}),
    ("", {"cameras": [_with(ITEM_FOV, distortion=5)]}),
    ("", {"cameras": [_with(ITEM_FOV, forward="a")]}),
    ("", {"cameras": [_with(ITEM_FOV, yaw=720)]}),
    ("", {"cameras": [_with(ITEM_RIG, camera="NOPE")]}),
    ("", {"cameras": [_with(ITEM_RIG, camera=3)]}),
    ("", {"cameras": [_with(ITEM_RIG, fov=3)]}),
    ("", {"cameras": [_with(ITEM_RIG, width=0)]}),
    ("", {"cameras": [_with(ITEM_RIG, height=-1, width=None)]}),
    ("", {"cameras": [_with(ITEM_CARLA, transform=3)]}),
    ("", {"cameras": [_with(ITEM_CARLA, transform={"location": {"x": 1, "y": 2, "z": 3}})]}),
    ("", {"cameras": [_with(ITEM_CARLA, transform={"location": 3, "rotation": {}})]}),
    ("", {"cameras": [_with(ITEM_CARLA, transform={"location": {"x": 1, "y": 2, "z": 3},
                                                   "rotation": {"pitch": 0, "yaw": "a", "roll": 0}})]}),
    ("", {"cameras": [_without(ITEM_CARLA, "fov")]}),
    ("", {"cameras": [_with(ITEM_CARLA, image_size_x=0)]}),
    ("", {"cameras": [_with(ITEM_CARLA, forward=1)]}),
    ("", {"cameras": [ITEM_FOV, ITEM_FOV, _with(ITEM_FOV, fov=0)]}),
    ("", _with(NS_PATH, render_width=0)),
    ("", _with(NS_PATH, camera_type="omnidirectional")),
    ("", _with(NS_PATH, camera_path=[{"camera_to_world": [1, 2], "fov": 50}])),
    ("", _with(NS_PATH, camera_path=[{"camera_to_world": [0] * 15 + [float("nan")], "fov": 50}])),
    ("", _with(NS_PATH, camera_path=[{"camera_to_world": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1],
                                      "fov": 50}])),
    ("", _with(NS_PATH, camera_path=[{"camera_to_world": NS_PATH["camera_path"][0]["camera_to_world"],
                                      "fov": 190}])),
    ("", _with(NS_PATH, camera_path=[3])),
]


def _jsonable(v):
    return json.loads(json.dumps(v, allow_nan=True))


def _answer(r, captured: list) -> dict:
    ctype = r.headers.get("content-type", "")
    out: dict = {"status": r.status_code, "type": ctype.split(";")[0]}
    if r.status_code != 200:
        out["body"] = r.json()
    elif ctype.startswith("application/zip"):
        zf = zipfile.ZipFile(io.BytesIO(r.content))
        index = json.loads(zf.read("index.json"))
        index["scene"] = "<sid>"
        out["files"] = zf.namelist()
        out["index"] = index
        out["views"] = [_jsonable(d) for d in captured]
    else:
        out["views"] = [_jsonable(d) for d in captured]
    captured.clear()
    return out


@pytest.fixture(scope="module")
def answers(env):
    """Every case's answer, sent once: {"get": {query: answer}, "batch": [...], "grpc": [...]}."""
    svc = env.service
    captured: list = []
    key = svc.view_key

    def view_key(sid, req):             # the description of each view the service renders (its ETag's input)
        captured.append(req.description())
        return key(sid, req)

    svc.view_key = view_key
    try:
        base = f"/v1/scenes/{env.sid}/render"
        got = {"get": {q: _answer(env.client.get(f"{base}?{q}"), captured) for q in GET}}
        batch = []
        for query, body in BATCH:
            r = env.client.post(f"{base}?{query}" if query else base,
                                content=json.dumps(body, allow_nan=True).encode(),
                                headers={"content-type": "application/json"})
            batch.append(_answer(r, captured))
        got["batch"] = batch
    finally:
        del svc.view_key
    got["grpc"] = _grpc_answers()
    if REC:
        RECORD.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    elif os.environ.get("XYZCYL_WIRE_OUT"):     # the answers of this run, to compare by hand
        Path(os.environ["XYZCYL_WIRE_OUT"]).write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    return got


def _grpc_cases():
    """(label, RGBRenderRequest) pairs: the example scene's cameras as AlpaSim asks for them, and bad fields."""
    from xyzcyl.runtime.rig import Rig
    from xyzcyl.server.sensorsim import frames
    from xyzcyl.server.sensorsim import sensorsim_pb2 as pb
    from xyzcyl.testing.rigs import example_rig
    from xyzcyl.testing.sensorsim import ego_pose, rgb_request

    rig = Rig.from_dict(example_rig())
    E = ego_pose()
    cams = list(frames.available_cameras(rig))
    c0 = cams[0]
    cases = [(f"{c.logical_id} {w}x{h}", rgb_request(c, E, width=w, height=h))
             for c in cams[:3] for w, h in ((64, 36), (64, 0), (0, 20))]
    cases.append(("jpeg q 0.9", rgb_request(c0, E, width=64, height=36, image_format=pb.JPEG)))
    moved = E.copy()
    moved[:3, 3] += [0.5, 0.1, 0.0]
    cases.append(("moving", rgb_request(c0, E, moved, width=64, height=36)))

    def bad(label, edit):
        r = rgb_request(c0, E, width=64, height=36)
        edit(r)
        cases.append((label, r))

    bad("no intrinsics", lambda r: r.ClearField("camera_intrinsics"))
    bad("no pose", lambda r: r.ClearField("sensor_pose"))
    bad("quality 200", lambda r: setattr(r, "image_quality", 200.0))
    bad("quality nan", lambda r: setattr(r, "image_quality", float("nan")))
    bad("format", lambda r: setattr(r, "image_format", 99))
    bad("ego mask", lambda r: setattr(r, "insert_ego_mask", True))
    bad("huge", lambda r: (setattr(r, "resolution_w", 20000), setattr(r, "resolution_h", 20000)))
    bad("over the pixel limit", lambda r: (setattr(r, "resolution_w", 8000), setattr(r, "resolution_h", 8000)))
    bad("nan pose", lambda r: setattr(r.sensor_pose.start_pose.vec, "x", float("nan")))
    bad("zero quaternion", lambda r: (setattr(r.sensor_pose.start_pose.quat, "w", 0.0),
                                      setattr(r.sensor_pose.start_pose.quat, "x", 0.0),
                                      setattr(r.sensor_pose.start_pose.quat, "y", 0.0),
                                      setattr(r.sensor_pose.start_pose.quat, "z", 0.0)))

    def intrinsics(r, name, value):
        which = r.camera_intrinsics.WhichOneof("camera_param")
        setattr(getattr(r.camera_intrinsics, which), name, value)

    bad("exposure ends before it starts", lambda r: setattr(r, "frame_end_us", r.frame_start_us - 1))
    bad("fx 0", lambda r: intrinsics(r, "focal_length_x", 0.0))
    bad("cx nan", lambda r: intrinsics(r, "principal_point_x", float("nan")))
    bad("camera size 0", lambda r: (setattr(r, "resolution_w", 0), setattr(r, "resolution_h", 0),
                                    setattr(r.camera_intrinsics, "resolution_w", 0),
                                    setattr(r.camera_intrinsics, "resolution_h", 0)))
    return E, cases


def _grpc_view(req, E, prefix: str):
    from xyzcyl.server.sensorsim import frames

    return frames.view_request(req, E, prefix)


def _grpc_answers() -> list:
    from xyzcyl.common.errors import FieldError

    E, cases = _grpc_cases()
    out = []
    for label, req in cases:
        try:
            view = _grpc_view(req, E, "items[1].request.")
            out.append({"case": label, "view": _jsonable(view.description())})
        except FieldError as e:
            out.append({"case": label, "error": [e.field, e.message]})
        except Exception as e:      # noqa: BLE001 - recorded as the answer it is (the servicer's INTERNAL)
            out.append({"case": label, "exception": type(e).__name__})
    return out


@pytest.mark.skipif(REC, reason="recording wire_answers.json")
def test_every_get_answer_is_unchanged(answers):
    want = json.loads(RECORD.read_text())["get"]
    assert list(answers["get"]) == list(want) or set(answers["get"]) == set(want)
    diff = {q: (answers["get"][q], want[q]) for q in want if answers["get"][q] != want[q]}
    assert not diff, json.dumps(diff, indent=1)[:6000]


@pytest.mark.skipif(REC, reason="recording wire_answers.json")
def test_every_batch_answer_is_unchanged(answers):
    want = json.loads(RECORD.read_text())["batch"]
    assert len(answers["batch"]) == len(want)
    diff = [(i, BATCH[i], a, w) for i, (a, w) in enumerate(zip(answers["batch"], want, strict=True)) if a != w]
    assert not diff, json.dumps(diff, indent=1, default=str)[:6000]


@pytest.mark.skipif(REC, reason="recording wire_answers.json")
def test_every_grpc_answer_is_unchanged(answers):
    want = json.loads(RECORD.read_text())["grpc"]
    diff = [(a, w) for a, w in zip(answers["grpc"], want, strict=True) if a != w]
    assert not diff, json.dumps(diff, indent=1)[:6000]


def test_the_corpus_covers_every_outcome(answers):
    """The corpus is not all errors or all successes: each front end has both, and the errors name many fields."""
    statuses = {a["status"] for a in answers["get"].values()} | {a["status"] for a in answers["batch"]}
    assert {200, 422} <= statuses
    fields = {a["body"]["error"]["field"] for a in [*answers["get"].values(), *answers["batch"]] if "body" in a}
    assert len(fields) >= 25, sorted(map(str, fields))
    grpc = answers["grpc"]
    assert sum("view" in a for a in grpc) >= 8 and sum("error" in a for a in grpc) >= 8
    assert np.isfinite([v for a in grpc if "view" in a for v in a["view"]["cam_to_ego"]]).all()
