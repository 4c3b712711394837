"""`xyzcyl render --lidar`: a sweep of a scene folder written as PLY or .npy (runtime.lidarsim), and its refusals
(exit 2, the flag named)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.testing.lidarscene import cylinder_scene

EYE = [str(v) for v in np.eye(4).ravel()]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return cylinder_scene(tmp_path_factory.mktemp("lidar") / "scene", n_around=360, n_up=30)


def test_ply_and_npy(scene, tmp_path, capsys):
    from plyfile import PlyData

    up = np.eye(4)
    up[2, 3] = 1.5
    out = tmp_path / "sweep.ply"
    argv = ["render", str(scene), "--lidar", "pandar64", "--azimuth-step", "2", "--out", str(out),
            "--lidar-pose", *[str(v) for v in up.ravel()]]
    assert cli.main(argv) == 0
    assert "LiDAR pandar64: 11520 points of 11520 rays" in capsys.readouterr().out
    v = PlyData.read(str(out))["vertex"]
    assert v.count == 64 * 180
    # the LiDAR frame is 1.5 m up: the cylinder (z -6..6 about the origin) at 10 m horizontally
    assert np.abs(np.hypot(v["x"], v["y"]) - 10.0).max() < 0.15        # tests/server/test_grpc_lidar.py RANGE_TOL
    npy = tmp_path / "sweep.npy"
    assert cli.main(["render", str(scene), "--lidar", "--lidar-beams", "[-10, 0, 10]", "--azimuth-step", "5",
                     "--max-range", "50", "--out", str(npy), "-q"]) == 0
    a = np.load(io.BytesIO(npy.read_bytes()))
    assert a.shape == (3 * 72, 4) and capsys.readouterr().out == ""


@pytest.mark.parametrize("extra, message", [
    (["--lidar", "velodyne"], "--lidar: unknown LiDAR model"),
    (["--lidar", "--azimuth-step", "0"], "--azimuth-step: must be in"),
    (["--lidar", "--max-range", "nan"], "--max-range: must be finite"),
    (["--lidar", "--lidar-beams", "[80]"], "--lidar-beams[0]: must be within"),
    (["--lidar", "--lidar-beams", "{\"a\": 1}"], "--lidar-beams: a JSON list"),
    (["--lidar", "--lidar-pose", *(["2"] * 16)], "--lidar-pose:"),
    (["--lidar", "--fov", "60"], "--fov: an image flag"),
    (["--azimuth-step", "1"], "need --lidar"),
])
def test_refusals_name_the_flag(scene, tmp_path, capsys, extra, message):
    assert cli.main(["render", str(scene), *extra, "--out", str(tmp_path / "s.ply")]) == 2
    assert message in capsys.readouterr().err


def test_out_must_be_ply_or_npy(scene, tmp_path, capsys):
    assert cli.main(["render", str(scene), "--lidar", "--out", str(tmp_path / "s.png")]) == 2
    assert "--out: a LiDAR sweep is written as .ply or .npy" in capsys.readouterr().err
