"""`xyzcyl data synth-drive`: a synthetic drive at speed with exact ground truth (model_export/data/drive.py).

A tiny drive (3 frames, 64 px wide, one mover) loads with runtime.drive.load_drive, its mover's box moves by
speed / hz per frame and its pixels move in the images, parked cars stay, the truth depth and the LiDAR sweep are
exact in each frame's ego frame, and a rerun resumes."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest
from xyzcyl.cli import main
from xyzcyl.model_export.data import classes as C
from xyzcyl.model_export.data.drive import DriveConfig, drive_scene, synth_drive
from xyzcyl.model_export.data.synth import read_exr
from xyzcyl.runtime.drive import load_drive
from xyzcyl.runtime.lidar import has_lidar, load_lidar

CFG = DriveConfig(seed=7, frames=3, hz=10.0, speed=5.0, width=64, movers=1)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    out = tmp_path_factory.mktemp("drive")
    assert synth_drive(out, CFG, progress=False) == 3
    return out


def _world_points(frame, cam, folder):
    """World points [N, 3] and classes [N] of a camera's pixels with depth (truth depth unprojected)."""
    depth = read_exr(folder / cam.extra["truth_depth"])
    sem = cv2.imread(str(folder / cam.extra["semantic"]), cv2.IMREAD_UNCHANGED)
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=1) @ np.linalg.inv(cam.K).T
    T = frame.ego_to_world @ cam.cam_to_ego
    return (z[:, None] * rays) @ T[:3, :3].T + T[:3, 3], sem[v, u], (v, u)


def _in_box(points, pose, size, grow=0.05):
    q = (points - pose[:3, 3]) @ pose[:3, :3]
    return np.all(np.abs(q) <= np.asarray(size) / 2 + grow, axis=1)


def test_drive_loads_with_load_drive(drive):
    d = load_drive(drive / "drive.json")      # every rig and image checked
    assert len(d) == 3 and list(d.frames[0].rig.names) == [
        "front_camera", "front_right_camera", "right_camera", "back_camera", "left_camera", "front_left_camera"]
    cam = d.frames[0].rig.cameras[0]
    assert (cam.width, cam.height) == (64, 36) and cam.depth is None   # the truth is no input depth
    times = np.array([f.timestamp_s for f in d.frames])
    assert np.allclose(np.diff(times), 0.1)
    traj = d.trajectory()
    assert np.allclose(traj[0], np.eye(4))
    assert np.allclose(np.diff(traj[:, 0, 3]), 0.5, atol=1e-9)          # speed / hz along the road
    moving = [t for t in d.tracks if not t.stationary]
    assert len(moving) == 1 and len(d.tracks) > 5
    doc = json.loads((drive / "drive.json").read_text())
    assert doc["config"]["speed"] == 5.0 and doc["frames"][2]["rig"] == "frame_02/rig.json"
    for f in d.frames:                          # LiDAR: in the ego frame, the ground at z = 0 there
        assert has_lidar(f.rig)
        pts = load_lidar(f.rig).points
        cls = np.load(f.rig_path.parent / "lidar.npy")[:, 3]
        assert len(pts) > 50_000
        road = pts[cls == C.ROAD]
        assert np.abs(road[:, 2]).max() < 1e-3
        # each frame's sweep starts at the mount: the nearest road points lie all around the ego
        assert np.ptp(np.arctan2(road[:, 1], road[:, 0])) > 6.0


def test_truth_depth_and_lidar_agree_across_frames(drive):
    """Frame 2's LiDAR ground points, moved to frame 0's ego frame, are still road at z = 0 (the poses are
    consistent with the geometry); every camera's truth depth is 0 exactly on sky pixels."""
    d = load_drive(drive / "drive.json")
    for f in d.frames:
        folder = f.rig_path.parent
        for cam in f.rig.cameras:
            depth = read_exr(folder / cam.extra["truth_depth"])
            sky = cv2.imread(str(folder / cam.extra["sky"]), 0)
            assert depth.shape == (36, 64) and np.array_equal(sky > 0, depth == 0)
    pts = load_lidar(d.frames[2].rig).points
    world = pts @ d.relative(2)[:3, :3].T + d.relative(2)[:3, 3]
    cls = np.load(d.frames[2].rig_path.parent / "lidar.npy")[:, 3]
    assert np.abs(world[cls == C.ROAD, 2]).max() < 1e-3


def test_mover_moves_by_speed_over_hz_and_parked_cars_stay(drive):
    d = load_drive(drive / "drive.json")
    tracks = json.loads((drive / "tracks.json").read_text())["tracks"]
    mover = next(t for t in d.tracks if not t.stationary)
    speed = next(t["speed_mps"] for t in tracks if t["id"] == mover.id)
    steps = [mover.poses[k + 1][:3, 3] - mover.poses[k][:3, 3] for k in range(2)]
    for s in steps:
        assert abs(np.linalg.norm(s) - speed / CFG.hz) < 1e-9 and abs(s[1]) < 1e-12 and abs(s[2]) < 1e-12
    # its pixels: the truth depth of vehicle pixels lands in its box at each frame, and they move in the image
    seen = {}
    parked_hits = {}
    parked = [t for t in d.tracks if t.stationary]
    for k, f in enumerate(d.frames):
        for cam in f.rig.cameras:
            pts, cls, (v, u) = _world_points(f, cam, f.rig_path.parent)
            veh = cls == C.VEHICLE
            inside = veh & _in_box(pts, mover.poses[k], mover.size)
            if inside.any():
                seen.setdefault(cam.name, {})[k] = np.stack([u[inside], v[inside]], axis=1)
            for t in parked:
                hit = veh & _in_box(pts, t.poses[k], t.size)
                if hit.any():
                    parked_hits.setdefault((t.id, cam.name), {})[k] = pts[hit]
            # no vehicle pixel lies where the mover was at frame 0 once it has moved on (it left no copy)
            if k == 2:
                others = [t for t in parked if _in_box(mover.poses[0][:3, 3][None], t.poses[0], t.size)[0]]
                if not others:
                    assert not (veh & _in_box(pts, mover.poses[0], mover.size, grow=-0.3)
                                & ~_in_box(pts, mover.poses[2], mover.size)).any()
    name, frames = max(seen.items(), key=lambda kv: len(kv[1]))
    assert set(frames) == {0, 1, 2}, f"the mover is not in every frame of one camera: {seen.keys()}"
    c0, c2 = frames[0].mean(axis=0), frames[2].mean(axis=0)
    assert np.linalg.norm(c2 - c0) > 1.0, (name, c0, c2)
    # parked cars: the same box every frame, and the ones seen at frames 0 and 2 are still there
    assert all(np.allclose(t.poses[0], t.poses[2]) for t in parked)
    both = [h for h in parked_hits.values() if 0 in h and 2 in h]
    assert both, "no parked car seen by one camera at frames 0 and 2"
    ds = drive_scene(CFG)
    static = np.ones(ds.scene.n, bool)
    for m in ds.movers:
        static[m.rows] = False
    static &= ~ds.scene.ego
    assert np.array_equal(ds.at(CFG, 0.2).geo[static], ds.scene.geo[static])


def test_rerun_resumes_and_is_deterministic(drive, tmp_path, capsys):
    assert synth_drive(drive, CFG, progress=False) == 0
    copy = tmp_path / "copy"
    shutil.copytree(drive, copy)
    before = (copy / "frame_01" / "left_camera.png").read_bytes()
    lidar = (copy / "frame_01" / "lidar.npy").read_bytes()
    shutil.rmtree(copy / "frame_01")
    (copy / "drive.json").unlink()
    assert synth_drive(copy, CFG, progress=False) == 1
    assert (copy / "frame_01" / "left_camera.png").read_bytes() == before
    assert (copy / "frame_01" / "lidar.npy").read_bytes() == lidar
    assert not (copy / ".tmp").exists() and len(load_drive(copy / "drive.json")) == 3
    with pytest.raises(ValueError, match="^speed"):
        synth_drive(copy, replace(CFG, speed=6.0), progress=False)
    out = tmp_path / "cli"
    assert main(["data", "synth-drive", str(out), "--frames", "2", "--width", "16", "--movers", "0",
                 "--no-shadows", "--supersample", "1", "--quiet"]) == 0
    assert len(load_drive(out / "drive.json")) == 2
    assert main(["data", "synth-drive", str(out), "--speed", "-1"]) == 2
    assert "speed" in capsys.readouterr().err
