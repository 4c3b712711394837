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
