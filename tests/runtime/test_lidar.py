"""runtime.lidar: reading LiDAR files, the per-pixel nearest-point map and the occlusion filter against their slow
references, the depth errors by hand, and the whole check on a scene whose surface is known (a wall of Gaussians);
`xyzcyl lidar-eval` on the real rigs (skipped without ../shared/data/real) and its errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.runtime.lidar import (
    LidarError,
    camera_depths,
    depth_errors,
    eval_camera,
    fuse_depth,
    lidar_depth_map,
    lidar_depth_map_reference,
    load_lidar,
    occlusion_filter,
    occlusion_filter_reference,
    read_points,
    summarise,
)
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.rig import Camera, Rig, look_rotation
from xyzcyl.runtime.scene import Scene


def _camera(name="front", yaw=0.0, width=64, height=48, f=40.0, pos=(1.0, 0.0, 1.5)) -> Camera:
    T = np.eye(4)
    T[:3, :3] = look_rotation(yaw)
    T[:3, 3] = pos
    K = [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]
    return Camera(name=name, image=None, width=width, height=height, K=K, cam_to_ego=T)


def _wall(x: float, n: int = 80, half: float = 12.0) -> Gaussians:
    """Opaque Gaussians tiling the plane x = const (ego metres), y and z in [-half, half] + 1.5 m."""
    ys, zs = np.meshgrid(np.linspace(-half, half, n), np.linspace(-half, half, n) + 1.5, indexing="ij")
    means = np.stack([np.full(ys.size, x), ys.ravel(), zs.ravel()], axis=1).astype(np.float32)
    step = 2 * half / (n - 1)
    log_scales = np.log(np.tile([[0.01, step, step]], (means.shape[0], 1))).astype(np.float32)
    quats = np.tile([[1.0, 0, 0, 0]], (means.shape[0], 1)).astype(np.float32)
    sh = np.full((means.shape[0], 1, 3), 0.5, np.float32)
    return Gaussians(means, quats, log_scales, np.full(means.shape[0], 8.0, np.float32), sh)


# -- files -------------------------------------------------------------------------------------------------------

def test_read_points_formats_and_nonfinite(tmp_path):
    a = np.array([[1, 2, 3, 9, 0], [4, 5, 6, 9, 1], [np.nan, 0, 0, 9, 2]], np.float32)
    a.tofile(tmp_path / "s.pcd.bin")                 # nuScenes: 5 columns by its name
    xyz, bad = read_points(tmp_path / "s.pcd.bin")
    assert xyz.tolist() == [[1, 2, 3], [4, 5, 6]] and bad == 1
    a[:, :4].copy().tofile(tmp_path / "k.bin")       # KITTI: 4 columns
    assert read_points(tmp_path / "k.bin")[0].shape == (2, 3)
    np.save(tmp_path / "p.npy", a[:2, :3].astype(np.float64))
    assert read_points(tmp_path / "p.npy")[0].tolist() == [[1, 2, 3], [4, 5, 6]]
    a[:, :3].copy().tofile(tmp_path / "odd.bin")     # 9 floats: not whole 4-column rows
    with pytest.raises(LidarError, match="whole number of 4-column"):
        read_points(tmp_path / "odd.bin")
    with pytest.raises(LidarError, match="columns: must be an integer >= 3"):
        read_points(tmp_path / "k.bin", columns=2)
    with pytest.raises(LidarError, match="columns: applies to .bin"):
        read_points(tmp_path / "p.npy", columns=4)
    np.save(tmp_path / "flat.npy", np.zeros(5))
    with pytest.raises(LidarError, match=r"shape \[N, C >= 3\]"):
        read_points(tmp_path / "flat.npy")
    (tmp_path / "x.las").write_bytes(b"")
    with pytest.raises(LidarError, match="unknown format"):
        read_points(tmp_path / "x.las")
    with pytest.raises(LidarError, match="does not exist"):
        read_points(tmp_path / "missing.npy")


def test_load_lidar_applies_lidar_to_ego(tmp_path):
    np.save(tmp_path / "p.npy", np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]))
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]     # LiDAR x -> ego y (a 90 degree yaw)
    T[:3, 3] = [0.5, 0.0, 1.8]
    rig = Rig(cameras=(_camera(),), root=tmp_path, extra={"lidar": {"file": "p.npy", "lidar_to_ego": T.tolist()}})
    got = load_lidar(rig)
    want = np.array([[0.5, 1.0, 1.8], [-1.5, 0.0, 1.8]])      # by hand: R p + t
    np.testing.assert_allclose(got.points, want, atol=1e-12)
    assert got.nonfinite == 0 and got.source.endswith("p.npy")
    # an explicit file is read in the ego frame unless the block gives lidar_to_ego: here it does
    np.testing.assert_allclose(load_lidar(rig, tmp_path / "p.npy").points, want, atol=1e-12)
    bare = Rig(cameras=(_camera(),), root=tmp_path)
    np.testing.assert_allclose(load_lidar(bare, tmp_path / "p.npy").points, [[1, 0, 0], [0, 2, 0]])
    with pytest.raises(LidarError, match="no lidar.file"):
        load_lidar(bare)
    bad = Rig(cameras=(_camera(),), root=tmp_path, extra={"lidar": {"file": "p.npy", "lidar_to_ego": [[1, 0], [0, 1]]}})
    with pytest.raises(LidarError, match="lidar_to_ego: must be 16 numbers"):
        load_lidar(bad)
    with pytest.raises(LidarError, match="lidar: must be an object"):
        load_lidar(Rig(cameras=(_camera(),), root=tmp_path, extra={"lidar": "p.npy"}))


def test_real_rigs_load(real_data):
    from xyzcyl.runtime.rig import load_rig

    for name, n in (("nuscenes_ca9a282c", 34688), ("pandaset_002_00", 106169)):
        rig = load_rig(real_data / name / "rig.json")
        pts = load_lidar(rig)
        assert pts.points.shape == (n, 3) and pts.nonfinite == 0
        # the sweep surrounds the ego car: every camera sees hundreds of points (the dataset READMEs' overlays)
        for cam in rig.cameras:
            assert (lidar_depth_map(pts.points, eval_camera(cam, 200)) > 0).sum() > 300


# -- kernels against their references ----------------------------------------------------------------------------

def test_depth_map_matches_reference_and_keeps_the_nearest():
    rng = np.random.default_rng(0)
    cam = _camera(width=32, height=24, f=20.0)
    pts = rng.uniform([-5, -20, -10], [60, 20, 12], size=(3000, 3))
    pts[:50] = pts[50:100] * 1.0001     # near-duplicates land in the same pixels: the nearer one must win
    fast, slow = lidar_depth_map(pts, cam), lidar_depth_map_reference(pts, cam)
    np.testing.assert_array_equal(fast, slow)    # same float32 values, same pixels: no tolerance needed
    assert (fast > 0).sum() > 100
    # by hand: a point straight ahead at 10 m lands on the principal point with camera z 10
    one = lidar_depth_map(np.array([[11.0, 0.0, 1.5], [21.0, 0.0, 1.5]]), _camera(width=65, height=49))
    assert one[24, 32] == 10.0 and (one > 0).sum() == 1
    # limits: behind, too near, too far
    assert not lidar_depth_map(np.array([[-5.0, 0, 1.5], [1.5, 0, 1.5], [90.0, 0, 1.5]]), cam).any()


def test_occlusion_filter_matches_reference():
    rng = np.random.default_rng(1)
    d = np.where(rng.random((30, 40)) < 0.3, rng.uniform(2, 60, (30, 40)), 0).astype(np.float32)
    for r in (1, 2, 3):
        np.testing.assert_array_equal(occlusion_filter(d, r), occlusion_filter_reference(d, r))
    # by hand: a 10 m point beside a 5 m point is hidden (10 > 1.25 * 5); an 6 m one is not (6 < 6.25)
    d = np.zeros((5, 5), np.float32)
    d[2, 2], d[2, 3], d[0, 0] = 5.0, 10.0, 6.0
    keep = occlusion_filter(d, 2)
    assert keep[2, 2] and not keep[2, 3] and keep[0, 0] and keep.sum() == 2


def test_depth_errors_by_hand():
    e = depth_errors(np.array([10.0, 12.0, 30.0]), np.array([10.0, 10.0, 20.0]))
    assert e["points"] == 3
    assert e["abs_rel"] == pytest.approx((0 + 0.2 + 0.5) / 3)
    assert e["rmse"] == pytest.approx(math.sqrt((0 + 4 + 100) / 3))
    assert e["delta1"] == pytest.approx(2 / 3)          # ratios 1, 1.2, 1.5
    assert e["median_ratio"] == pytest.approx(1.2)
    assert math.isnan(depth_errors(np.array([]), np.array([]))["abs_rel"])


# -- the whole check on a known surface -------------------------------------------------------------------------

def test_check_on_a_wall_of_gaussians():
    """A wall at x = 12 m seen by a forward camera at x = 1: LiDAR points on the wall give AbsRel ~ 0 and ratio 1;
    the same points 10 % further give ratio 1/1.1; a camera looking away sees no LiDAR point."""
    cams = (_camera("front"), _camera("back", yaw=math.pi))
    scene = Scene(gaussians=_wall(12.0), background=None, rig=Rig(cameras=cams))
    ys, zs = np.meshgrid(np.linspace(-6, 6, 60), np.linspace(-3, 5, 40), indexing="ij")
    pts = np.stack([np.full(ys.size, 12.0), ys.ravel(), zs.ravel()], axis=1)
    views = camera_depths(scene, pts, width=64)
    s = summarise(views)
    front, back = s["cameras"]
    assert back["lidar_pixels"] == 0 and math.isnan(back["abs_rel"])
    assert front["lidar_pixels"] > 500 and front["covered"] == 1.0
    # tolerance: the wall's Gaussians are 1 cm thick and opaque, so the expected depth sits within ~1 mm of 11 m
    assert front["abs_rel"] < 1e-3 and front["median_ratio"] == pytest.approx(1.0, abs=1e-3)
    assert s["ranges"][1]["points"] == front["points"]          # 11 m falls in the 10-20 m bin
    far = pts.copy()
    far[:, 0] = 1.0 + 11.0 * 1.1                                  # 12.1 m camera z: 10 % further than the wall
    s2 = summarise(camera_depths(scene, far, width=64))
    assert s2["all"]["median_ratio"] == pytest.approx(1 / 1.1, abs=1e-3)
    assert s2["all"]["delta1"] == 1.0 and s2["all"]["abs_rel"] == pytest.approx(1 - 1 / 1.1, abs=1e-3)


# -- the command ------------------------------------------------------------------------------------------------

def test_lidar_eval_cli_errors(tmp_path, capsys):
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"cameras": [{"name": "a", "image": None, "width": 64, "height": 48,
                                            "K": [[40, 0, 32], [0, 40, 24], [0, 0, 1]],
                                            "cam_to_ego": np.eye(4).tolist()}]}))
    assert cli.main(["lidar-eval", str(rig), "--width", "2"]) == 2
    assert "--width" in capsys.readouterr().err
    assert cli.main(["lidar-eval", str(rig), "--min-depth", "5", "--max-depth", "1"]) == 2
    assert "--min-depth" in capsys.readouterr().err
    assert cli.main(["lidar-eval", str(rig), "--picture", str(tmp_path / "x.gif")]) == 2
    assert "--picture: extension" in capsys.readouterr().err
    assert cli.main(["lidar-eval", str(rig), "--quiet"]) == 2
    assert "no lidar.file" in capsys.readouterr().err
    assert cli.main(["lidar-eval", str(rig), "--quiet", "--lidar-file", str(tmp_path / "none.npy")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.slow
def test_lidar_eval_cli_on_a_real_rig(real_data, tmp_path, capsys):
    """The shipped model on the PandaSet rig: the table, the JSON and the picture come out; every figure is a
    number (the values themselves are reported in docs/results.md, not asserted)."""
    out, pic = tmp_path / "d.json", tmp_path / "d.jpg"
    assert cli.main(["lidar-eval", str(real_data / "pandaset_002_00" / "rig.json"), "--width", "160",
                     "--json", str(out), "--picture", str(pic), "--threads", "2", "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "front_camera" in table and "LiDAR 40-80 m" in table
    r = json.loads(out.read_text())
    assert r["cameras"][0]["camera"] == "front_camera" and r["all"]["points"] > 1000
    assert 0 < r["all"]["abs_rel"] and 0 <= r["all"]["delta1"] <= 1 and r["all"]["covered"] > 0.5
    import cv2

    assert cv2.imread(str(pic)).shape[1] == 3 * 160


def test_fuse_depth_by_hand():
    """LiDAR cells are kept as they are; the others take the model's depth times the median LiDAR / model ratio;
    no surface (alpha < 0.5) and no LiDAR gives 0; too few shared cells keep scale 1."""
    lidar = np.array([[10.0, 0, 0], [20.0, 0, 0]], np.float32)
    head = np.array([[5.0, 6.0, 7.0], [10.0, 8.0, 9.0]], np.float32)
    alpha = np.array([[1.0, 1.0, 0.2], [1.0, 1.0, 1.0]], np.float32)
    out, s = fuse_depth(lidar, head, alpha, min_cells=2)
    assert s == 2.0                                       # median of 10/5 and 20/10
    np.testing.assert_array_equal(out, [[10.0, 12.0, 0.0], [20.0, 16.0, 18.0]])
    out1, s1 = fuse_depth(lidar, head, alpha, min_cells=3)
    assert s1 == 1.0 and out1[0, 1] == 6.0 and out1[1, 0] == 20.0
