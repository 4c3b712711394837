"""`xyzcyl client render` poses (issue 27): --cam-to-world and --carla take negative numbers in scientific notation
and the other matrix forms (defect 2), and the camera moves of `xyzcyl render` (--forward/--left/--up/--yaw, one
definition: common/poses.py; defect 7), sent to the server as the query's move (issue 35). The request the client sends is captured with
httpx.MockTransport (no server)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from client_helpers import PNG

httpx = pytest.importorskip("httpx")

POSE = np.array([[0, 0, 1, 5], [-1, 0, 0, -1e-05], [0, -1, 0, 1.6], [0, 0, 0, 1.0]])
SCI = ["0", "0", "1", "5", "-1", "0", "0", "-1e-05", "0", "-1", "0", "1.6", "0", "0", "0", "1"]


def _client(capsys, *args):
    from xyzcyl import cli

    capsys.readouterr()
    rc = cli.main(["client", "render", "SID", "--server", "http://test", "--quiet", *args])
    return rc, capsys.readouterr().err


def _pose(params) -> np.ndarray:
    return np.array([float(v) for v in params["cam_to_ego"].split(",")]).reshape(4, 4)


def test_matrix_forms(sent, tmp_path, capsys):
    np.save(tmp_path / "pose.npy", POSE)
    (tmp_path / "pose.json").write_text(json.dumps({"cam_to_ego": POSE.tolist()}))
    size = ["--width", "80", "--height", "45", "--K", "57", "57", "39.5", "22", "--out", str(tmp_path / "v.png")]
    forms = {"tokens": ["--cam-to-world", *SCI], "equals": ["--cam-to-world=" + SCI[0], *SCI[1:]],
             "json": ["--cam-to-world", json.dumps(POSE.tolist())], "numpy printed": ["--cam-to-world", str(POSE)],
             "npy": ["--cam-to-world", str(tmp_path / "pose.npy")],
             "json file": ["--cam-to-world", str(tmp_path / "pose.json")]}
    for name, argv in forms.items():
        rc, err = _client(capsys, *argv, *size)
        assert rc == 0, (name, err)
        assert np.array_equal(_pose(sent[-1]), POSE), name
        assert (tmp_path / "v.png").read_bytes() == PNG
    assert sent[-1]["fx"] == "57.0" and sent[-1]["width"] == "80"


def test_moves_on_cam_to_world_are_the_render_commands(sent, tmp_path, capsys):
    """The pose and the move go to the server as they are (issue 35: the server moves a pose with
    runtime.views.move_camera, as `xyzcyl render` does); the moved pose is CameraMove.apply's."""
    from xyzcyl.common.poses import CameraMove

    rc, err = _client(capsys, "--cam-to-world", *SCI, "--fov", "90", "--width", "80", "--height", "45",
                      "--forward", "-2e0", "--left", "0.5", "--up", "1e-1", "--yaw", "-1.5e1",
                      "--out", str(tmp_path / "v.png"))
    assert rc == 0, err
    assert np.array_equal(_pose(sent[-1]), POSE)
    move = {k: float(sent[-1][k]) for k in ("forward", "left", "up", "yaw")}
    assert move == {"forward": -2.0, "left": 0.5, "up": 0.1, "yaw": -15.0}
    moved = CameraMove(**move).apply(POSE)
    # by hand: 15 degrees to the right, the camera that looked along ego +x looks right of it (-y)
    assert np.allclose(moved[:3, 2], [np.cos(np.radians(15)), -np.sin(np.radians(15)), 0])
    assert np.allclose(moved[:3, 3], [3.0, 0.5 - 1e-05, 1.7])


def test_moves_on_a_carla_pose(sent, tmp_path, capsys):
    rc, err = _client(capsys, "--carla", "5", "-1e-05", "1.6", "-2.5e0", "0", "0", "--fov", "90", "--width", "80",
                      "--height", "45", "--forward", "1", "--left", "2", "--up", "-0.5", "--yaw", "30",
                      "--out", str(tmp_path / "v.png"))
    assert rc == 0, err
    p = {k: float(sent[-1][k]) for k in ("x", "y", "z", "pitch", "yaw", "roll")}
    # CARLA is left-handed (y right, yaw turns right): 2 m left is y - 2, 30 degrees left is yaw - 30
    assert p == pytest.approx({"x": 6.0, "y": -2.00001, "z": 1.1, "pitch": -2.5, "yaw": -30.0, "roll": 0.0})


def test_moves_with_an_input_camera_go_to_the_server(sent, tmp_path, capsys):
    """Issue 35: the server moves the input camera's pose (it was refused here, the client not knowing it)."""
    rc, err = _client(capsys, "--camera", "CAM_FRONT", "--up", "1", "--out", str(tmp_path / "v.png"))
    assert rc == 0, err
    assert sent[-1]["camera"] == "CAM_FRONT" and float(sent[-1]["up"]) == 1.0 and "forward" not in sent[-1]


@pytest.mark.parametrize("value, message", [
    (["1", "2", "3"], "expected 16 numbers, got 3 values"),
    (["nope.npy"], "no such file 'nope.npy'"),
])
def test_matrix_errors(sent, tmp_path, capsys, value, message):
    rc, err = _client(capsys, "--cam-to-world", *value, "--fov", "90", "--width", "80", "--height", "45",
                      "--out", str(tmp_path / "v.png"))
    assert rc == 2 and not sent
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("xyzcyl client: --cam-to-world: ") and message in lines[0], err


@pytest.mark.parametrize("sid", ["-" + "Ab3_" * 5 + "x", "--" + "Zq9" * 6 + "zz", "-h" + "Ab3_" * 5,
                                 "-q" + "Ab3_" * 5, "-1" + "Ab3_" * 5])
def test_a_scene_id_that_starts_with_a_dash_is_the_scene(monkeypatch, tmp_path, capsys, sid):
    """1 scene id in 64 started with "-" (URL-safe base64): `xyzcyl client render -Ab3...` took it for an unknown
    option and refused with "the following arguments are required: SCENE_ID", "-hAb3..." for -h with an argument
    (common.command.SCENE_ID_LIKE)."""
    from xyzcyl import cli

    paths = []
    real = httpx.Client

    def handler(request):
        paths.append(request.url.path)
        return httpx.Response(200, content=PNG, headers={"content-type": "image/png"})

    monkeypatch.setattr(httpx, "Client", lambda **kw: real(transport=httpx.MockTransport(handler), **kw))
    monkeypatch.delenv("XYZCYL_API_KEY", raising=False)
    assert len(sid) == 22
    rc = cli.main(["client", "render", sid, "--server", "http://test", "--quiet", "--camera", "CAM_FRONT",
                   "--width", "80", "--out", str(tmp_path / "v.png")])
    assert rc == 0, capsys.readouterr().err
    assert paths and f"/{sid}/" in paths[-1]


def test_no_option_of_a_command_looks_like_a_scene_id():
    """A scene id that starts with "-" is a value wherever it stands (common.command.SCENE_ID_LIKE): an option of that
    form would be one a user could not abbreviate, and a negative-number-like option would make argparse take every
    negative number for an option in its parser."""
    import argparse

    from xyzcyl.cli import COMMANDS
    from xyzcyl.common.command import NEGATIVE_NUMBER, SCENE_ID_LIKE, command_parser

    seen = []

    def walk(parser):
        for a in parser._actions:
            seen.extend(a.option_strings)
            if isinstance(a, argparse._SubParsersAction):
                for sub in a.choices.values():
                    walk(sub)

    for cmd in COMMANDS:
        try:
            walk(command_parser(cmd)[0])
        except ModuleNotFoundError:      # an extra not installed here: its options are not checked
            continue
    assert len(seen) > 300
    assert [o for o in seen if SCENE_ID_LIKE.match(o) or NEGATIVE_NUMBER.match(o)] == []
