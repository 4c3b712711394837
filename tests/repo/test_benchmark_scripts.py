"""The benchmark scripts that reproduce figures the documentation quotes run, with small arguments, as a user runs
them (a subprocess from the repository root), and print JSON lines: benchmarks/eval_compare.py (paired intervals
and rig gaps of `xyzcyl eval` reports), anchor_parallax.py, synth_lidar.py, compile_time.py and exposure_probe.py;
drive_eval.py reaches `xyzcyl eval-real --drive`. The records the documentation cites lie in benchmarks/records and parse."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from xyzcyl.testing import EXAMPLE_RIG, REPO

BENCH = REPO / "benchmarks"


def _run(script: str, *args: str, timeout: float = 120) -> list[dict]:
    r = subprocess.run([sys.executable, str(BENCH / script), *args], cwd=REPO, capture_output=True, text=True,
                       timeout=timeout, env={**os.environ, "PYTHONWARNINGS": "ignore"}, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    return [json.loads(line) for line in r.stdout.splitlines() if line.strip()]


def _report(path: Path, rig: str, scenes: int, psnr, settings=("ego-forward", "ego-inward"), views: int = 3) -> Path:
    """A report JSON shaped as `xyzcyl eval --out` writes it: per-view rows of data, rig, setting, scene, view."""
    rows = [{"data": f"data/{rig}", "rig": rig, "setting": s, "scene": f"scene_{i:06d}", "view": v,
             "psnr": psnr(s, i, v)}
            for s in settings for i in range(scenes) for v in range(views)]
    path.mkdir(parents=True)
    (path / "model_ego-forward+ego-inward.json").write_text(json.dumps({"views": rows}))
    return path


def test_eval_compare_paired(tmp_path):
    a = _report(tmp_path / "a", "nuscenes", 6, lambda s, i, v: 20.0 + 0.1 * i + (1.0 if s == "ego-forward" else 0))
    b = _report(tmp_path / "b", "nuscenes", 6, lambda s, i, v: None if (s, i, v) == ("ego-inward", 0, 0) else 19.5)
    rows = _run("eval_compare.py", "paired", str(a), str(b), "--resamples", "200")
    by = {r["setting"]: r for r in rows}
    assert set(by) == {"ego-forward", "ego-inward"}
    fwd, inw = by["ego-forward"], by["ego-inward"]
    assert fwd["mean_diff"] == pytest.approx(1.75) and fwd["scenes"] == 6 and fwd["views"] == 18
    assert fwd["ci95"][0] <= fwd["mean_diff"] <= fwd["ci95"][1] and fwd["scenes_a_better"] == 6
    assert inw["undefined"] == 1 and inw["views"] == 17


def test_eval_compare_rig_gap(tmp_path):
    six = _report(tmp_path / "six", "nuscenes", 8, lambda s, i, v: 22.0 if i < 3 else 30.0)
    five = _report(tmp_path / "five", "waymo", 3, lambda s, i, v: 20.5)
    (row,) = _run("eval_compare.py", "rig-gap", f"m={six},{five}")
    assert row["rig"] == "waymo" and row["scenes"] == 3
    assert row["ego-forward"] == {"six_cameras": 22.0, "rig": 20.5, "difference": -1.5}


@pytest.fixture
def depth_scene(tmp_path) -> Path:
    """A data set of one scene: the example rig's geometry and images with a depth file per camera (a plane 10 m
    along each optical axis), as `xyzcyl data synth` lays a scene out (docs/data.md)."""
    from xyzcyl.common.media import write_exr

    scene = tmp_path / "data" / "scene_000000"
    scene.mkdir(parents=True)
    rig = json.loads(EXAMPLE_RIG.read_text())
    for cam in rig["cameras"]:
        shutil.copy(EXAMPLE_RIG.parent / cam["image"], scene / Path(cam["image"]).name)
        cam["image"] = Path(cam["image"]).name
        cam["depth"] = f"{cam['name']}_depth.exr"
        write_exr(scene / cam["depth"], np.full((cam["height"], cam["width"], 1), 10.0, np.float32), ("Z",))
    (scene / "rig.json").write_text(json.dumps(rig))
    return scene


def test_anchor_parallax(depth_scene):
    (row,) = _run("anchor_parallax.py", "--data", str(depth_scene.parent), "--scenes", "1")
    assert row["scenes"] == 1 and row["pixels"] > 1000
    assert 0 < row["reprojection_px_at_400"]["median"] <= row["reprojection_px_at_400"]["p90"]
    assert 0 < row["distance_m"]["median"] < 10


def test_synth_lidar(depth_scene):
    from xyzcyl.runtime.lidar import load_lidar
    from xyzcyl.runtime.rig import load_rig

    (row,) = _run("synth_lidar.py", str(depth_scene.parent), "--step", "16")
    rig = load_rig(depth_scene / "rig_lidar.json")
    points = load_lidar(rig).points
    assert row["points"] == len(points) == 6 * 29 * 50
    # every point lies 10 m along the optical axis of the camera it came from
    cam = rig.cameras[0]
    z = (np.c_[points, np.ones(len(points))] @ np.linalg.inv(cam.cam_to_ego).T)[:, 2]
    assert np.isclose(z, 10.0, atol=1e-3).sum() >= 29 * 50


def test_compile_time_pinhole():
    """With numba's cache as the test run has it (filled: the kernels load; empty: they compile, ~20 s)."""
    rows = _run("compile_time.py", "pinhole", timeout=300)
    assert list(rows[0]) == ["pinhole"] and rows[0]["pinhole"]["rgb_sum"] > 0
    assert rows[-1]["total_wall_s"] >= 0


def test_exposure_probe(depth_scene):
    """On the pseudo-LiDAR of synth_lidar.py (the real rigs of docs/results.md need real data): the flat depth
    planes the model cannot know, so only the figures' form is checked."""
    _run("synth_lidar.py", str(depth_scene.parent), "--step", "16")
    (row,) = _run("exposure_probe.py", str(depth_scene / "rig_lidar.json"), "--kinds", "exposure_1.5",
                  "--width", "160", "--threads", "2", timeout=300)
    assert row["inputs"] == "exposure_1.5" and row["detail"] is False and row["model"].startswith("xyzcyl-cpu-v1")
    assert row["abs_rel"] > 0 and 0 <= row["delta1"] <= 1


def test_drive_eval_is_eval_real_drive(tmp_path):
    """benchmarks/drive_eval.py (docs/results.md "Drives") passes its flags to `xyzcyl eval-real --drive`: a bad one
    comes back as the command's error, naming the flag (the evaluation itself: tests/runtime/test_drive_eval.py)."""
    r = subprocess.run([sys.executable, str(BENCH / "drive_eval.py"), str(tmp_path / "drive.json"), "--every", "0",
                        "--out", str(tmp_path / "out")], cwd=REPO, capture_output=True, text=True, timeout=120,
                       check=False)
    assert r.returncode == 2 and r.stderr.startswith("xyzcyl eval-real: --every"), r.stderr[-2000:]


@pytest.mark.parametrize("name", sorted(p.name for p in (BENCH / "records").rglob("*.json*")))
def test_the_records_parse(name):
    (path,) = (BENCH / "records").rglob(name)
    text = path.read_text()
    if path.suffix == ".jsonl":
        assert [json.loads(line) for line in text.splitlines() if line.strip()]
    else:
        assert json.loads(text)


def test_the_eight_camera_rig_loads():
    from xyzcyl.runtime.rig import load_rig

    assert len(load_rig(BENCH / "rigs" / "ring8.json", check_images=False)) == 8


def test_drive_under_ego_camera_looks_down_and_refuses_a_frame_outside_the_drive(real_data):
    """benchmarks/drive_under_ego.py (docs/results.md "Drives: the ground under the ego"): its camera looks straight
    down with the ego's forward up in the image, and a --frame the drive lacks exits 2 naming the flag, before any
    reconstruction."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("drive_under_ego", BENCH / "drive_under_ego.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    T = np.eye(4)
    T[:3, 3] = (5.0, 2.0, 0.0)
    cam = mod.down_camera(T, 2.0)
    uv, z, front = cam.project(np.array([[5.0, 2.0, 0.0], [6.0, 2.0, 0.0], [5.0, 3.0, 0.0]]))
    assert front.all() and np.allclose(z, 2.0)                       # the ground 2 m below, straight down
    assert np.allclose(uv[0], [(cam.width - 1) / 2, (cam.height - 1) / 2])
    assert uv[1][1] < uv[0][1] and abs(uv[1][0] - uv[0][0]) < 1e-9      # forward is up
    assert uv[2][0] < uv[0][0]                                         # left is left
    drive = real_data / "pandaset_002_drive" / "drive.json"
    r = subprocess.run([sys.executable, str(BENCH / "drive_under_ego.py"), str(drive), "--frame", "99"], cwd=REPO,
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 2 and "--frame" in r.stderr, r.stderr[-2000:]


def test_actors_bench_times_thirty_moved_actors(tmp_path):
    """benchmarks/actors_bench.py (docs/results.md "Actors"): a drive with one moving car gives 30 edits a view
    (the car moved, 29 copies inserted beside it) and the ratio of the render times; a drive without tracks exits
    2 saying so."""
    from xyzcyl.testing.drives import moving_car, pose, write_drive

    E = pose(0)
    drive = write_drive(tmp_path / "d", [E, E], [0.0, 0.5], tracks=moving_car(E, 12.0, 1.0))
    (doc,) = _run("actors_bench.py", str(drive), "--every", "1", "--frames", "0,1", "--repeats", "1",
                  "--scene", str(tmp_path / "scene"), timeout=300)
    assert doc["moved_actors"] == [30, 30] and doc["actors"] == 1 and doc["views"] == 2 * 6
    assert doc["seconds_30_moved"] > 0 and doc["ratio"] == pytest.approx(doc["seconds_30_moved"] /
                                                                         doc["seconds_no_edits"], rel=0.01)
    plain = write_drive(tmp_path / "p", [E, E], [0.0, 0.5])
    r = subprocess.run([sys.executable, str(BENCH / "actors_bench.py"), str(plain)], cwd=REPO, capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 2 and "no tracks" in r.stderr, r.stderr[-2000:]


def test_actors_boxes_scores_inside_the_moving_boxes(tmp_path):
    """benchmarks/actors_boxes.py (docs/results.md "Actors"): a drive with a moving car, reconstructed with and
    without its tracks, scored inside its boxes, outside and whole at the frame between the keyframes; the scenes
    are reused from --work; a drive without tracks exits 2."""
    from xyzcyl.testing.drives import moving_car, pose, write_drive

    E = pose(0)
    tracks = moving_car(E, 12.0, 1.0)
    tracks["tracks"][0]["poses"].append({"frame": 2, "object_to_world": tracks["tracks"][0]["poses"][1]
                                         ["object_to_world"]})
    drive = write_drive(tmp_path / "d", [E, E, E], [0.0, 0.5, 1.0], tracks=tracks)
    (doc,) = _run("actors_boxes.py", str(drive), "--every", "2", "--work", str(tmp_path / "w"), "--no-lidar",
                  timeout=300)
    assert doc["keyframes"] == [0, 2] and doc["scored_frames"] == [1] and not doc["lidar"]
    for name in ("tracks", "untracked", "still"):
        assert all(np.isfinite(doc["psnr"][name][k]) for k in ("outside", "all")), doc
    assert (tmp_path / "w" / "tracks" / "scene.json").is_file() and (tmp_path / "w" / "untracked").is_dir()
    plain = write_drive(tmp_path / "p", [E, E], [0.0, 0.5])
    r = subprocess.run([sys.executable, str(BENCH / "actors_boxes.py"), str(plain), "--work", str(tmp_path / "x")],
                       cwd=REPO, capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 2 and "no tracks" in r.stderr, r.stderr[-2000:]


def test_lidar_bench_times_a_sweep_and_refuses_bad_arguments(tmp_path):
    """benchmarks/lidar_bench.py on a cylinder of Gaussians 10 m around the LiDAR (testing.lidarscene): one AT128
    sweep at a given sensor origin, timed, every ray of the forward 120 degrees returning; bad flags exit 2."""
    from xyzcyl.testing.lidarscene import cylinder_scene

    scene = cylinder_scene(tmp_path / "cyl", n_around=360, n_up=30)
    (doc,) = _run("lidar_bench.py", "--scene", str(scene), "--models", "at128", "--repeat", "1",
                  "--sensor-origin", "0,0,0.5")
    assert doc["sensor_origin_m"] == {"ego_frame": [0.0, 0.0, 0.5], "given": [0.0, 0.0, 0.5]}
    (m,) = doc["models"]
    assert m["name"] == "at128" and m["seconds_per_sweep"] > 0 and m["returns"] > 0.9 * m["rays"]
    for args, says in ((["--sensor-origin", "1,2"], "--sensor-origin"), ([], "--sensor-origin auto: needs --drive"),
                       (["--sensor-origin", "0,0,0", "--compare"], "--compare: needs --drive")):
        r = subprocess.run([sys.executable, str(BENCH / "lidar_bench.py"), "--scene", str(scene), *args], cwd=REPO,
                           capture_output=True, text=True, timeout=60, check=False)
        assert r.returncode == 2 and says in r.stderr, r.stderr[-500:]


def test_usdz_bench_exports_and_draws_the_artifact(tmp_path):
    """benchmarks/usdz_bench.py on a one-rig scene of a flat road: the export's report with its members, and the
    picture of the artifact read back."""
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import Scene

    x, y = np.meshgrid(np.arange(-20, 20, 0.5), np.arange(-10, 10, 0.5), indexing="ij")
    n = x.size
    means = np.stack([x.ravel(), y.ravel(), np.full(n, -0.3)], 1).astype(np.float32)
    g = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), -2.5, np.float32),
                  np.full(n, 4.0, np.float32), np.zeros((n, 1, 3), np.float32))
    Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG)).save(tmp_path / "scene")
    (doc,) = _run("usdz_bench.py", str(tmp_path / "scene"), "--out", str(tmp_path / "s.usdz"),
                  "--picture", str(tmp_path / "top.jpg"))
    assert doc["gaussians"] == n and doc["frames"] == 1 and "scene.nurec" in doc["members"]
    assert (tmp_path / "top.jpg").stat().st_size > 1000
