"""runtime/commands/pose_flags.py: the matrix flag's forms (issue 27, defect 2) and the camera moves shared by
`xyzcyl render` and `xyzcyl client render` (defect 7), checked by hand and against runtime.convert's CARLA
conversion."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from xyzcyl.common.poses import CameraMove, PoseArgError, parse_matrix

# the pose: 5 m ahead, 1.6 m up, looking forward, as numpy prints it (one entry -1e-05)
POSE = np.array([[0, 0, 1, 5], [-1, 0, 0, -1e-05], [0, -1, 0, 1.6], [0, 0, 0, 1.0]])
TOKENS = ["0", "0", "1", "5", "-1", "0", "0", "-1e-05", "0", "-1", "0", "1.6", "0", "0", "0", "1"]


@pytest.mark.parametrize("form", ["tokens", "one string", "commas", "json flat", "json 4x4", "numpy printed"])
def test_parse_matrix_inline_forms(form):
    value = {"tokens": TOKENS, "one string": " ".join(TOKENS), "commas": ",".join(TOKENS),
             "json flat": json.dumps(POSE.ravel().tolist()), "json 4x4": json.dumps(POSE.tolist()),
             "numpy printed": str(POSE)}[form]
    assert np.array_equal(parse_matrix(value), POSE)


def test_parse_matrix_files(tmp_path):
    np.save(tmp_path / "p.npy", POSE)
    np.save(tmp_path / "flat.npy", POSE.ravel())
    (tmp_path / "list.json").write_text(json.dumps(POSE.tolist()))
    (tmp_path / "obj.json").write_text(json.dumps({"name": "x", "cam_to_ego": POSE.ravel().tolist()}))
    (tmp_path / "world.json").write_text(json.dumps({"cam_to_world": POSE.tolist()}))
    (tmp_path / "p.txt").write_text(str(POSE))
    for name in ("p.npy", "flat.npy", "list.json", "obj.json", "world.json", "p.txt"):
        assert np.array_equal(parse_matrix([str(tmp_path / name)]), POSE), name


@pytest.mark.parametrize("values, message", [
    (["1", "2", "3"], "expected 16 numbers, got 3 values"),
    ([*TOKENS, "1"], "expected 16 numbers, got 17 values"),
    (["[1, 2, 3]"], "got [1, 2, 3]"),
    (["[[1, 2, 3, 4]] * 4"], "'*' is not a number"),
    (["nope.npy"], "no such file 'nope.npy'"),
    (["nope.json"], "no such file 'nope.json'"),
    ([*TOKENS[:-1], "nan"], "entry [3][3] is not finite"),
    (['{"K": [1]}'], "must hold one of cam_to_ego, cam_to_world"),
])
def test_parse_matrix_errors_name_the_flag(values, message):
    with pytest.raises(PoseArgError) as e:
        parse_matrix(values, "--cam-to-world")
    assert e.value.field == "--cam-to-world" and str(e.value).startswith("--cam-to-world: ")
    assert message in str(e.value)


def test_parse_matrix_bad_files(tmp_path):
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    np.save(tmp_path / "3x4.npy", POSE[:3])
    (tmp_path / "bad.json").write_text("{")
    for name, message in (("bad.npy", "is not a .npy array"), ("3x4.npy", "got shape [3, 4]"),
                          ("bad.json", "'{' is not a number")):
        with pytest.raises(PoseArgError, match="^--cam-to-world: "):
            try:
                parse_matrix([str(tmp_path / name)])
            except PoseArgError as e:
                assert message in str(e), str(e)
                raise


def test_move_by_hand():
    T = POSE.copy()
    assert not CameraMove() and np.array_equal(CameraMove().apply(T), T)
    moved = CameraMove(forward=1.0, left=2.0, up=-0.5).apply(T)
    assert np.array_equal(moved[:3, :3], T[:3, :3]) and np.allclose(moved[:3, 3], [6.0, 2.0 - 1e-05, 1.1])
    # turning 90 degrees left: the camera that looked along ego +x looks along +y (its z column), stays upright
    # (y column down) and stays where it was
    turned = CameraMove(yaw=90.0).apply(T)
    assert np.allclose(turned[:3, 2], [0, 1, 0]) and np.allclose(turned[:3, 1], [0, 0, -1])
    assert np.array_equal(turned[:3, 3], T[:3, 3]) and np.array_equal(T, POSE)       # the input is not changed
    # the turn comes first: it does not turn the shift
    both = CameraMove(forward=1.0, yaw=90.0).apply(T)
    assert np.allclose(both[:3, 3], [6.0, -1e-05, 1.6]) and np.allclose(both[:3, :3], turned[:3, :3])
    assert CameraMove(forward=1.0, yaw=-5.0).flags() == ["--forward", "--yaw"]


@pytest.mark.parametrize("move", [CameraMove(yaw=30.0), CameraMove(1.5, -2.0, 0.25, -40.0), CameraMove(left=3.0)])
def test_carla_move_is_the_same_move(move):
    """Moving a CARLA transform (apply_carla) and converting it gives the converted pose moved (apply)."""
    from xyzcyl.runtime.convert import camera_from_carla

    def cam(x, y, z, pitch, yaw, roll):
        return camera_from_carla({"transform": {"location": {"x": x, "y": y, "z": z},
                                                "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
                                  "fov": 90, "image_size_x": 64, "image_size_y": 48})

    carla = (1.0, 0.5, 1.6, -10.0, 20.0, 3.0)
    expected = move.apply(cam(*carla).cam_to_ego)
    assert np.allclose(cam(*move.apply_carla(*carla)).cam_to_ego, expected, atol=1e-12)


def test_module_is_light():
    """The HTTP client imports pose_flags: it must not bring the renderer, numba, OpenCV or onnxruntime."""
    code = ("import sys; from xyzcyl.common import poses as pose_flags; pose_flags.parse_matrix(" + repr(TOKENS)
            + "); heavy = [m for m in sys.modules if m.split('.')[0] in ('numba', 'cv2', 'onnxruntime', 'torch') "
            "or (m.startswith('xyzcyl.runtime.') and m not in ('xyzcyl.runtime.commands', "
            "'xyzcyl.runtime.commands.pose_flags'))]; assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_move_flags_must_be_finite():
    import argparse

    from xyzcyl.common.poses import add_move_arguments, move_from_args

    p = argparse.ArgumentParser()
    add_move_arguments(p)
    assert move_from_args(p.parse_args(["--up", "2", "--yaw", "90"])) == CameraMove(up=2.0, yaw=90.0)
    with pytest.raises(PoseArgError, match="^--left: must be finite"):
        move_from_args(p.parse_args(["--left", "inf"]))
    assert math.isclose(move_from_args(p.parse_args(["--forward=-2e0"])).forward, -2.0)
