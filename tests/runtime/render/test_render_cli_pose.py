"""`xyzcyl render` poses (issue 27): negative numbers in scientific notation and the other forms of
--cam-to-world (defect 2), and the camera moves --forward/--left/--up/--yaw on an explicit pose and on an input
camera of a scene (defect 7). Each form renders the same image as the plain decimal pose."""

from __future__ import annotations

import json

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl import cli

K = ["40", "40", "23.5", "15.5"]
# identity rotation, a -1e-05 m shift (how numpy prints a tiny number): the Gaussians lie ahead along +z
POSE = np.eye(4)
POSE[0, 3] = -1e-05
SCI = [repr(float(v)) if v else "0" for v in POSE.ravel()]         # "-1e-05" among them
PLAIN = [f"{v:.5f}" for v in POSE.ravel()]                     # "-0.00001"


@pytest.fixture(scope="module")
def ply(tmp_path_factory):
    path = tmp_path_factory.mktemp("ply") / "g.ply"
    random_gaussians(np.random.default_rng(0), 150, degree=1).save_ply(path)
    return path


def _exr(path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    img = inp.read_image(oiio.FLOAT)
    inp.close()
    return img


def _render(tmp_path, name, *argv) -> np.ndarray:
    out = tmp_path / f"{name}.exr"
    assert cli.main(["render", *argv, "--out", str(out)]) == 0
    return _exr(out)


def test_scientific_notation_and_matrix_forms(ply, tmp_path, capsys):
    assert "-1e-05" in SCI
    size = ["--width", "48", "--height", "32", "--K", *K]
    ref = _render(tmp_path, "ref", str(ply), *size, "--cam-to-world", *PLAIN)
    assert ref[..., 3].mean() > 0.05                                     # the view sees the Gaussians
    np.save(tmp_path / "pose.npy", POSE)
    (tmp_path / "pose.json").write_text(json.dumps({"cam_to_ego": POSE.tolist()}))
    forms = {
        "tokens": [str(ply), *size, "--cam-to-world", *SCI],
        "equals": [str(ply), *size, "--cam-to-world=" + SCI[0], *SCI[1:]],
        "positional last": [*size, "--cam-to-world", *SCI, str(ply)],
        "json": [str(ply), *size, "--cam-to-world", json.dumps(POSE.tolist())],
        "numpy printed": [str(ply), *size, "--cam-to-world", str(POSE)],
        "npy": [*size, "--cam-to-world", str(tmp_path / "pose.npy"), str(ply)],
        "json file": [str(ply), *size, "--cam-to-world=" + str(tmp_path / "pose.json")],
        "negative K": [str(ply), "--width", "48", "--height", "32", "--K", "4e1", "40", "23.5", "15.5",
                       "--cam-to-world", *SCI, "--forward", "-0e0"],
    }
    for name, argv in forms.items():
        assert np.array_equal(_render(tmp_path, name, *argv), ref), name


@pytest.mark.parametrize("value, message", [
    (["1", "2", "3"], "expected 16 numbers, got 3 values"),
    (["pose.npy"], "no such file 'pose.npy'"),
    (["[[1, 0], [0, 1]]"], "must be 16 numbers (row-major) or a [4, 4] array"),
])
def test_matrix_errors_exit_2_naming_the_flag(ply, tmp_path, capsys, value, message):
    argv = ["render", str(ply), "--width", "48", "--height", "32", "--K", *K, "--cam-to-world", *value,
            "--out", str(tmp_path / "a.png")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("xyzcyl render: --cam-to-world: ") and message in err[0], err


def test_moves_on_an_explicit_pose(ply, tmp_path):
    size = ["--width", "48", "--height", "32", "--K", *K]
    base = np.eye(4)
    base[:3, 3] = (0.2, -0.1, -1.0)
    # by hand: turn 12 degrees about ego z, then shift (0.3, -0.2, 0.5)
    a = np.radians(12.0)
    expected = base.copy()
    expected[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ base[:3, :3]
    expected[:3, 3] += (0.3, -0.2, 0.5)
    ref = _render(tmp_path, "ref", str(ply), *size, "--cam-to-world", *map(str, expected.ravel().tolist()))
    moved = _render(tmp_path, "moved", str(ply), *size, "--cam-to-world", *map(str, base.ravel().tolist()),
                    "--forward", "0.3", "--left", "-2e-1", "--up", "0.5", "--yaw", "12")
    assert ref[..., 3].mean() > 0.05 and np.abs(moved - ref).max() < 1e-4
    still = _render(tmp_path, "still", str(ply), *size, "--cam-to-world", *map(str, base.ravel().tolist()))
    assert np.abs(still - ref).max() > 0.05                              # the moves did move the camera


def test_moves_on_an_input_camera(tmp_path):
    from xyzcyl.runtime.rig import Camera, Rig, look_rotation
    from xyzcyl.runtime.scene import Scene

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = look_rotation(0.0), (0.0, 0.0, 1.5)
    cam = Camera(name="front", width=96, height=54, K=np.array([[60, 0, 47.5], [0, 60, 26.5], [0, 0, 1.0]]),
                 cam_to_ego=T)
    g = random_gaussians(np.random.default_rng(1), 200, lo=(3, -4, 0), hi=(12, 4, 3), degree=1)
    scene = tmp_path / "scene"
    Scene(gaussians=g, background=None, rig=Rig(cameras=(cam,))).save(scene)
    moves = ["--forward", "1", "--left", "0.5", "--up", "-0.25", "--yaw", "-20"]
    moved = _render(tmp_path, "moved", str(scene), "--camera", "front", "--width", "48", "--height", "27", *moves)
    a = np.radians(-20.0)
    expected = T.copy()
    expected[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ T[:3, :3]
    expected[:3, 3] += (1.0, 0.5, -0.25)
    r = cam.resized(48, 27).K
    ref = _render(tmp_path, "ref", str(scene), "--width", "48", "--height", "27",
                  "--K", *(str(float(v)) for v in (r[0, 0], r[1, 1], r[0, 2], r[1, 2])),
                  "--cam-to-world", *map(str, expected.ravel().tolist()))
    assert ref[..., 3].mean() > 0.05 and np.abs(moved - ref).max() < 1e-4
