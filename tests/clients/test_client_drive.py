"""A recorded drive through the client (docs/client.md; issue 37 item 1): Client.reconstruct of a drive file sends the
'drive' part (each frame's rig and the tracks inline) and each frame's files as ``frames/<frame>/<name>`` parts, with
the keyframe query; what it refuses before sending, naming the argument, the drive file's field or the part; and
`xyzcyl client reconstruct DRIVE_JSON` with its progress lines. Against an httpx.MockTransport (no server: the
server's side is tests/server/test_drive_upload.py)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

httpx = pytest.importorskip("httpx")

from client_helpers import multipart_parts
from xyzcyl.clients import Client, InvalidArgumentError, InvalidRequestError
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import moving_car, pose, write_drive

T0 = 10.0
SCENE = {"id": "d" * 22, "state": "ready", "created": "2026-11-29T06:00:00+00:00",
         "updated": "2026-11-29T06:00:05+00:00", "gaussians": 1234, "timings": {"total": 4.2},
         "cameras": [{"name": "CAM_FRONT", "width": 800, "height": 450, "model": "pinhole"}], "links": {},
         "drive": {"frames": 3, "keyframes": [0, 2], "keyframe_spacing": 1.5, "keyframe_gap": 2.0, "timestamp_s": T0,
                   "duration_s": 1.0, "tracks": 1}}


@pytest.fixture
def drive(tmp_path):
    """Three frames of the example rig with a moving car; frame 1 names a LiDAR sweep, frame 2 a depth map of its
    first camera (files relative to their rig.json)."""
    def edit(i, rig):
        if i == 1:
            rig["lidar"] = {"file": "sweep.npy"}
        if i == 2:
            rig["cameras"][0]["depth"] = "depth.png"

    path = write_drive(tmp_path, [pose(0), pose(1), pose(2)], [T0, T0 + 0.5, T0 + 1.0], edit, moving_car(pose(0)))
    np.save(tmp_path / "frame_01" / "sweep.npy", np.zeros((10, 4), np.float32))
    cv2.imwrite(str(tmp_path / "frame_02" / "depth.png"), np.full((450, 800), 5000, np.uint16))
    return path


def _mock(handler) -> Client:
    return Client(http_client=httpx.Client(transport=httpx.MockTransport(handler), base_url="http://mock"))


def _recorder():
    sent = []

    def handler(request):
        sent.append((dict(request.url.params), multipart_parts(request)))
        return httpx.Response(201, json=SCENE)

    return sent, handler


def test_a_drive_file_goes_up_as_its_parts(drive):
    sent, handler = _recorder()
    c = _mock(handler)
    info = c.reconstruct(drive, keyframe_spacing=2, keyframe_gap=0.5)
    assert info.drive.keyframes == [0, 2]
    params, parts = sent[0]
    assert params == {"wait": "600", "keyframe_spacing": "2.0", "keyframe_gap": "0.5"}
    cams = [c["name"] for c in json.loads(EXAMPLE_RIG.read_text())["cameras"]]
    want = {"drive"} | {f"frames/{i}/{c}" for i in range(3) for c in cams} | {"frames/1/lidar",
                                                                                 "frames/2/depth:CAM_FRONT"}
    assert set(parts) == want
    doc = json.loads(parts["drive"][1])
    assert parts["drive"][0] == "application/json"
    assert [f["timestamp_s"] for f in doc["frames"]] == [T0, T0 + 0.5, T0 + 1.0]
    assert [f["rig"]["ego_to_world"] for f in doc["frames"]] == [pose(0), pose(1), pose(2)]     # rigs inline
    assert doc["tracks"] == moving_car(pose(0))                                                  # the tracks too
    assert parts["frames/0/CAM_BACK"][1] == (EXAMPLE_RIG.parent / "images" / "CAM_BACK.png").read_bytes()
    assert parts["frames/1/lidar"] == ("application/octet-stream", (drive.parent / "frame_01" / "sweep.npy")
                                       .read_bytes())
    # depths={} and lidar=False leave those files out (reconstruct_drive: depths=False, lidar=False)
    c.reconstruct(drive, depths={}, lidar=False, wait=False, detail=False)
    params, parts = sent[1]
    assert params == {"detail": "false"} and not any(p.endswith(("/lidar", "depth:CAM_FRONT")) for p in parts)


@pytest.mark.parametrize("call, field", [
    (lambda c, d, r: c.reconstruct(r, keyframe_gap=1.0), "keyframe_gap"),            # a rig is one timestamp
    (lambda c, d, r: c.reconstruct(d, keyframe_spacing=0), "keyframe_spacing"),
    (lambda c, d, r: c.reconstruct_drive(d, keyframe_gap=float("inf")), "keyframe_gap"),
    (lambda c, d, r: c.reconstruct_drive(d, keyframe_gap=True), "keyframe_gap"),
    (lambda c, d, r: c.reconstruct(d, images={}), "images"),
    (lambda c, d, r: c.reconstruct(d, lidar=b"\0" * 16), "lidar"),
])
def test_bad_arguments_are_refused_before_sending(drive, call, field):
    def handler(request):
        raise AssertionError("nothing may be sent")

    with pytest.raises(InvalidArgumentError) as e:
        call(_mock(handler), drive, EXAMPLE_RIG)
    assert e.value.status is None and e.value.field == field, e.value


@pytest.mark.parametrize("change, field, code", [
    (lambda d: (d / "frame_01" / "sweep.npy").unlink(), "frames/1/lidar", "file_missing"),
    (lambda d: (d / "frame_02" / "rig.json").unlink(), "frames[2].rig", "file_missing"),
    (lambda d: (d / "tracks.json").write_text("{"), "tracks", "invalid"),
    (lambda d: (d / "drive.json").write_text('{"frames": []}'), "frames", "invalid"),
    (lambda d: (d / "drive.json").write_text('{"frames": [{"rig": 3}]}'), "frames[0].rig", "invalid"),
])
def test_a_bad_drive_file_is_refused_naming_its_field(drive, change, field, code):
    def handler(request):
        raise AssertionError("nothing may be sent")

    change(drive.parent)
    with pytest.raises(InvalidRequestError) as e:
        _mock(handler).reconstruct_drive(drive)
    assert (e.value.status, e.value.field, e.value.code) == (None, field, code), e.value


def _cli(args, capsys) -> tuple[int, str, str]:
    from xyzcyl import cli

    capsys.readouterr()
    rc = cli.main(list(args))
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_reconstructs_a_drive_with_a_line_per_stage(drive, monkeypatch, capsys):
    sent, handler = _recorder()
    real = httpx.Client
    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(handler), **kw))
    rc, out, err = _cli(["client", "reconstruct", str(drive), "--wait", "--keyframe-gap", "0.5", "--no-lidar",
                         "--stationary-actors"], capsys)
    assert rc == 0 and out.strip() == SCENE["id"], err
    lines = err.strip().splitlines()
    assert lines[0].startswith(f"drive {drive}: 3 frames of 6 cameras, ") and lines[0].endswith(" MB to upload")
    assert lines[1].startswith("uploaded ") and lines[1].endswith("waiting for the reconstruction ...")
    assert lines[2] == (f"scene {SCENE['id']} ready: 1234 Gaussians, 1 cameras, 3 frames (2 keyframes) in 4.2 s")
    params, parts = sent[0]
    assert params["keyframe_gap"] == "0.5" and "frames/1/lidar" not in parts
    assert params["stationary_actors"] == "true"
    # the keyframe flags go with a drive file: refused for a rig.json before anything is sent
    rc, out, err = _cli(["client", "reconstruct", str(EXAMPLE_RIG), "--keyframe-spacing", "3"], capsys)
    assert rc == 2 and "--keyframe-spacing: goes with a drive file" in err and len(sent) == 1, err
    rc, out, err = _cli(["client", "reconstruct", str(drive), "--keyframe-gap", "0"], capsys)
    assert rc == 2 and "--keyframe-gap: must be a finite number > 0" in err and len(sent) == 1, err
    rc, out, err = _cli(["client", "reconstruct", str(EXAMPLE_RIG), "--stationary-actors"], capsys)
    assert rc == 2 and "--stationary-actors: goes with a drive file" in err and len(sent) == 1, err


def test_a_render_at_a_time_sends_it_and_a_bad_time_is_refused_before(monkeypatch, capsys, tmp_path):
    png = cv2.imencode(".png", np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    sent = []

    def handler(request):
        sent.append(dict(request.url.params))
        return httpx.Response(200, content=png, headers={"content-type": "image/png"})

    with _mock(handler) as c:
        assert c.render("d" * 22, "CAM_FRONT", time=T0 + 0.25).shape == (4, 6, 3)
        assert float(sent[-1]["time"]) == T0 + 0.25
        c.render_bytes("d" * 22, "CAM_FRONT")
        assert "time" not in sent[-1]                        # no time: the drive's first frame (the server's rule)
        for bad in (float("nan"), "10", True):
            with pytest.raises(InvalidArgumentError, match="time: must be a finite number") as e:
                c.render_bytes("d" * 22, "CAM_FRONT", time=bad)
            assert e.value.field == "time"
    assert len(sent) == 2
    # `xyzcyl client render --time T` (once taken as an abbreviation of --timeout, silently)
    real = httpx.Client
    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(handler), **kw))
    out = str(tmp_path / "v.png")
    rc, _, err = _cli(["client", "render", "d" * 22, "--camera", "CAM_FRONT", "--time", "12.5", "--out", out], capsys)
    assert rc == 0 and float(sent[-1]["time"]) == 12.5, err


def test_actor_edits_are_sent_checked_first_and_listed(monkeypatch, capsys, tmp_path):
    """render(actors=...) sends the edits as the GET query's JSON text; malformed edits are refused before anything
    is sent, naming the edit's field; actors() reads GET .../actors; `xyzcyl client render --actors JSON|FILE` and
    `xyzcyl client actors SCENE_ID` do the same from the command line."""
    png = cv2.imencode(".png", np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    listed = {"time": T0, "actors": [{"id": "car-1", "label": "Car", "tracked": True, "size": [5.0, 6.0, 4.0],
                                      "span_s": [T0, T0 + 1.0], "copies": 2, "gaussians": 900,
                                      "pose": [1, 0, 0, 12, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}]}
    sent = []

    def handler(request):
        sent.append((request.url.path, dict(request.url.params)))
        if request.url.path.endswith("/actors"):
            return httpx.Response(200, json=listed)
        return httpx.Response(200, content=png, headers={"content-type": "image/png"})

    with _mock(handler) as c:
        c.render("d" * 22, "CAM_FRONT", time=T0, actors=[{"id": "car-1", "offset": [0, 1.5, 0]},
                                                          {"id": "car-1", "insert": "car-2", "offset": [0, -3, 0]}])
        assert json.loads(sent[-1][1]["actors"]) == [{"id": "car-1", "offset": [0.0, 1.5, 0.0]},
                                                     {"id": "car-1", "offset": [0.0, -3.0, 0.0], "insert": "car-2"}]
        for bad, field in (([{"id": "car-1"}], "actors[0]"), ([{"id": "car-1", "hide": 1}], "actors[0].hide"),
                           ("{", "actors")):
            with pytest.raises(InvalidArgumentError) as e:
                c.render_bytes("d" * 22, "CAM_FRONT", actors=bad)
            assert e.value.field == field
        got = c.actors("d" * 22, time=T0)
        assert sent[-1] == (f"/v1/scenes/{'d' * 22}/actors", {"time": repr(T0)})
        assert got.actors[0].id == "car-1" and got.actors[0].pose[3] == 12
    assert len(sent) == 2
    real = httpx.Client
    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(handler), **kw))
    edits = tmp_path / "edits.json"
    edits.write_text('[{"id": "car-1", "hide": true}]')
    rc, _, err = _cli(["client", "render", "d" * 22, "--camera", "CAM_FRONT", "--actors", str(edits),
                       "--out", str(tmp_path / "v.png")], capsys)
    assert rc == 0 and json.loads(sent[-1][1]["actors"]) == [{"id": "car-1", "hide": True}], err
    rc, _, err = _cli(["client", "render", "d" * 22, "--camera", "CAM_FRONT", "--actors", '[{"id": "car-1"}]',
                       "--out", str(tmp_path / "v.png")], capsys)
    assert rc == 2 and "--actors[0]: give exactly one of pose, offset and hide" in err and len(sent) == 3, err
    rc, out, err = _cli(["client", "actors", "d" * 22], capsys)
    assert rc == 0 and json.loads(out)["actors"][0]["id"] == "car-1", err
