"""runtime.realeval (the metrics, frames, pairs and the pose of a camera of another frame) and `xyzcyl eval-real`:
end to end on a two-frame synthetic drive made from examples/synth_nuscenes, its errors, and the real PandaSet
drive (skipped without ../shared/data/real)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.runtime import realeval
from xyzcyl.runtime.commands.eval_real import parse_pairs, spread
from xyzcyl.runtime.realeval import Frame
from xyzcyl.runtime.rig import Camera, Rig, RigError, look_rotation

SYNTH = Path(__file__).resolve().parents[2] / "examples" / "synth_nuscenes"


def _texture(seed: int = 0, size: int = 96) -> np.ndarray:
    """[size, size, 3] 0..1: random blocks plus fine noise (edges at every scale)."""
    rng = np.random.default_rng(seed)
    coarse = cv2.resize(rng.random((size // 8, size // 8, 3)).astype(np.float32), (size, size),
                        interpolation=cv2.INTER_NEAREST)
    return np.clip(0.8 * coarse + 0.2 * rng.random((size, size, 3), dtype=np.float32), 0, 1)


def _pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = (x, y)
    return T


def _rig(pose: np.ndarray | None = None) -> Rig:
    T = np.eye(4)
    T[:3, :3] = look_rotation(0.0)
    T[:3, 3] = (0.5, 0.0, 1.5)
    cam = Camera(name="front", width=64, height=48, K=[[40, 0, 31.5], [0, 40, 23.5], [0, 0, 1]], cam_to_ego=T)
    return Rig(cameras=(cam,), extra={} if pose is None else {"ego_to_world": pose.tolist()})


# -- metrics -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_the_written_out_window(seed):
    """`ssim` (cv2.GaussianBlur, float64) against the per-pixel weighted sums of `ssim_reference`. Both are the
    same float64 arithmetic up to summation order (OpenCV filters separably with a normalised 1-D kernel, the
    reference with the normalised outer product, which is the same 2-D kernel): the local moments differ by a few
    ulps of values <= 1 (~1e-16), the variance terms are divided by at least C2 = 9e-4, so per-pixel SSIM agrees to
    ~1e-12 (measured: <= 2e-15). 1e-10 leaves room for that and still catches a wrong window size, sigma, border
    rule or constant: on these 16x16 images (the 5-pixel border is most of them) 9x9 instead of 11x11 moves SSIM
    by 9e-5, sigma 1.6 by 9e-4, BORDER_REFLECT_101 by 5e-3, C1 doubled by 8e-7."""
    rng = np.random.default_rng(seed)
    gt = rng.random((16, 16, 3))
    pred = np.clip(gt + 0.2 * rng.standard_normal(gt.shape), 0, 1)       # correlated, so SSIM is far from 0
    assert realeval.ssim(pred, gt) == pytest.approx(realeval.ssim_reference(pred, gt), abs=1e-10)
    other = rng.random((16, 16, 3))                                       # unrelated
    assert realeval.ssim(other, gt) == pytest.approx(realeval.ssim_reference(other, gt), abs=1e-10)


def test_identical_images_are_perfect():
    img = _texture()
    assert realeval.psnr(img, img) == math.inf
    assert realeval.ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    assert realeval.sharpness_ratio(img, img) == pytest.approx(1.0)
    m = realeval.image_metrics(img, img)
    assert set(m) == {"psnr", "ssim", "sharpness"}


def test_psnr_by_hand_and_flat_ground_truth():
    gt = np.full((8, 8, 3), 0.5)
    assert realeval.psnr(gt + 0.1, gt) == pytest.approx(20.0)            # mse 0.01
    assert realeval.psnr(gt + 0.01, gt) == pytest.approx(40.0)
    assert math.isnan(realeval.sharpness_ratio(_texture(size=8), gt))   # flat ground truth: no gradient


def test_blur_lowers_sharpness_and_ssim():
    gt = _texture()
    soft = cv2.GaussianBlur(gt, (0, 0), 1.0)
    softer = cv2.GaussianBlur(gt, (0, 0), 3.0)
    assert realeval.sharpness_ratio(softer, gt) < realeval.sharpness_ratio(soft, gt) < 1.0
    assert realeval.ssim(softer, gt) < realeval.ssim(soft, gt) < 1.0
    assert realeval.psnr(soft, gt) > realeval.psnr(softer, gt)
    noisy = np.clip(gt + 0.1 * np.random.default_rng(0).standard_normal(gt.shape), 0, 1)
    assert realeval.sharpness_ratio(noisy, gt) > 1.0                    # noise adds gradient energy


def test_summary_means_and_gain():
    rows = [{"camera": "a", "render_psnr": 20.0, "still_psnr": 18.0, "render_ssim": 0.6, "still_ssim": 0.5},
            {"camera": "b", "render_psnr": math.inf, "still_psnr": 16.0, "render_ssim": 0.8, "still_ssim": 0.7}]
    s = realeval.summary(rows)
    assert s["views"] == 2 and s["render_psnr"] == 20.0                 # non-finite values are left out
    assert s["still_psnr"] == 17.0 and s["gain_psnr"] == 3.0
    assert s["gain_ssim"] == pytest.approx(0.1)


# -- frames, pairs, poses ----------------------------------------------------------------------------------------

def test_camera_in_by_hand():
    """Frame A at (2, 3) facing ego x; frame B at (1, 0) turned 90 degrees left. B's camera, 0.5 m ahead of B's
    origin and 1.5 m up looking ahead, is in the world at (1, 0.5, 1.5) looking along world +y, so in A's frame
    at (-1, -2.5, 1.5), looking along +y."""
    a = Frame("a", _rig(), _pose(2.0, 3.0))
    b = Frame("b", _rig(), _pose(1.0, 0.0, 90.0))
    cam = realeval.camera_in(a, b, "front")
    assert np.allclose(cam.cam_to_ego[:3, 3], (-1.0, -2.5, 1.5))
    assert np.allclose(cam.cam_to_ego[:3, :3], look_rotation(math.pi / 2))
    assert np.allclose(cam.rotation[:, 2], (0.0, 1.0, 0.0))             # optical axis
    assert cam.cam_to_ego[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert cam.name == "front" and (cam.width, cam.height) == (64, 48) and np.array_equal(cam.K, b.rig.cameras[0].K)
    same = realeval.camera_in(b, b, "front")                             # a frame in itself: unchanged
    assert np.allclose(same.cam_to_ego, b.rig.cameras[0].cam_to_ego)


def test_pairs_within():
    f = [Frame(f"f{i}", _rig(), _pose(x)) for i, x in enumerate((0.0, 1.0, 2.5))]
    got = [(a.name, b.name) for a, b in realeval.pairs_within(f, 0.8, 2.1)]
    assert got == [("f0", "f1"), ("f1", "f0"), ("f1", "f2"), ("f2", "f1")]    # 2.5 m apart: out
    assert [(a.name, b.name) for a, b in realeval.pairs_within(f, 1.0, 1.0)] == [("f0", "f1"), ("f1", "f0")]
    assert realeval.pairs_within(f, 3.0, 4.0) == []
    assert realeval.frame_distance(f[0], f[2]) == pytest.approx(2.5)


def test_load_frames(tmp_path):
    for name, pose, key in (("b", _pose(1.0), "ego_to_world"), ("a", _pose(), "ego_to_global")):
        (tmp_path / name).mkdir()
        d = _rig().to_dict()
        d[key] = pose.tolist()
        (tmp_path / name / "rig.json").write_text(json.dumps(d))
    (tmp_path / "notes").mkdir()                                          # no rig.json: not a frame
    frames = realeval.load_frames(tmp_path)
    assert [f.name for f in frames] == ["a", "b"] and frames[1].pose[0, 3] == 1.0
    shutil.rmtree(tmp_path / "b")
    with pytest.raises(RigError, match="at least two"):
        realeval.load_frames(tmp_path)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "rig.json").write_text(json.dumps(_rig().to_dict()))
    with pytest.raises(RigError, match="ego_to_world"):
        realeval.load_frames(tmp_path)


def test_spread_and_parse_pairs():
    items = list(range(10))
    assert spread(items, None) == items and spread(items, 20) == items
    assert spread(items, 1) == [5] and spread(items, 2) == [2, 7] and spread(items, 5) == [1, 3, 5, 7, 9]
    assert len(set(spread(items, 9))) == 9
    assert parse_pairs(" x:y , y:x,x:y", ["x", "y"]) == [("x", "y"), ("y", "x")]


# -- the command -------------------------------------------------------------------------------------------------

def _drive(root):
    """Two frames, frame_0 and frame_1 (1 m ahead): examples/synth_nuscenes (6 cameras, 800x450, the same images)
    with an ego pose."""
    poses = (_pose(), _pose(1.0))
    base = json.loads((SYNTH / "rig.json").read_text())
    for i, pose in enumerate(poses):
        d = root / f"frame_{i}"
        shutil.copytree(SYNTH / "images", d / "images")
        (d / "rig.json").write_text(json.dumps({**base, "ego_to_world": pose.tolist()}))
    return root


def test_eval_real_cli_novel_views(tmp_path, capsys):
    drive, out = _drive(tmp_path / "drive"), tmp_path / "out"
    assert cli.main(["eval-real", str(drive), "--out", str(out), "--lidar", "off", "--cameras", "CAM_FRONT",
                     "--threads", "2", "--quiet"]) == 0
    table = capsys.readouterr().out
    assert table.splitlines()[2].split()[:2] == ["off", "2"]
    r = json.loads((out / "report.json").read_text())
    assert r["format"] == "xyzcyl-eval-real" and r["kind"] == "novel_views"
    s = r["settings"]
    assert s["model"]["name"] and s["model"]["version"] and s["detail"]["stride"] == 2
    assert s["lidar"] == "off" and s["modes"] == ["off"] and s["cameras"] == ["CAM_FRONT"]
    assert (s["min_distance"], s["max_distance"]) == (0.8, 2.1)
    assert r["pairs"] == [{"a": "frame_0", "b": "frame_1", "distance_m": 1.0},
                          {"a": "frame_1", "b": "frame_0", "distance_m": 1.0}]
    assert [(x["a"], x["b"], x["lidar"], x["camera"]) for x in r["rows"]] == [
        ("frame_0", "frame_1", "off", "CAM_FRONT"), ("frame_1", "frame_0", "off", "CAM_FRONT")]
    for row in r["rows"]:
        # the same images at both frames: "not moving" is the ground truth itself (inf PSNR -> null)
        assert row["still_psnr"] is None and row["still_ssim"] == pytest.approx(1.0)
        assert 0 < row["render_ssim"] < 1 and row["render_psnr"] > 5 and row["render_sharpness"] > 0
    assert r["summary"]["off"]["views"] == 2
    assert [(p["a"], p["b"], p["lidar"], p["views"]) for p in r["pair_summaries"]] == [
        ("frame_0", "frame_1", "off", 1), ("frame_1", "frame_0", "off", 1)]
    assert [(x["frame"], x["lidar"]) for x in r["scenes"]] == [("frame_0", "off"), ("frame_1", "off")]
    assert all(x["counts"]["total"] > 0 and x["timings"]["total"] > 0 for x in r["scenes"])
    assert r["pictures"] == ["frame_0_frame_1_off.jpg", "frame_1_frame_0_off.jpg"]
    pic = cv2.imread(str(out / "frame_0_frame_1_off.jpg"))
    assert pic.shape[1] == 3 * 480 and pic.shape[0] == 22 + 270          # title row + one camera row

    # --pairs and --max-pairs pick the pairs; --no-detail is reported
    assert cli.main(["eval-real", str(drive), "--out", str(out), "--lidar", "off", "--cameras", "CAM_FRONT",
                     "--pairs", "frame_1:frame_0", "--no-detail", "--quiet"]) == 0
    r = json.loads((out / "report.json").read_text())
    assert [(p["a"], p["b"]) for p in r["pairs"]] == [("frame_1", "frame_0")] and r["settings"]["detail"] is None
    assert r["settings"]["min_distance"] is None
    assert cli.main(["eval-real", str(drive), "--out", str(out), "--lidar", "off", "--cameras", "CAM_FRONT",
                     "--max-pairs", "1", "--no-detail", "--quiet"]) == 0
    assert len(json.loads((out / "report.json").read_text())["pairs"]) == 1
    capsys.readouterr()


def test_eval_real_cli_input_views(tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:                                 # argparse: exclusive flags
        cli.main(["eval-real", str(SYNTH / "rig.json"), "--out", str(out), "--no-detail", "--detail-stride", "3"])
    assert exc.value.code == 2 and "--detail-stride" in capsys.readouterr().err
    assert cli.main(["eval-real", str(SYNTH / "rig.json"), "--out", str(out), "--lidar", "off", "--no-detail",
                     "--cameras", "CAM_BACK,CAM_FRONT"]) == 0
    cap = capsys.readouterr()
    assert "render CAM_FRONT 800x450" in cap.err                          # progress lines without --quiet
    r = json.loads((out / "report.json").read_text())
    assert r["kind"] == "input_views" and r["pairs"] == []
    assert [x["camera"] for x in r["rows"]] == ["CAM_FRONT", "CAM_BACK"]  # rig order
    assert all(0 < x["render_ssim"] <= 1 and "still_psnr" not in x for x in r["rows"])
    assert r["summary"]["off"]["views"] == 2 and "gain_psnr" not in r["summary"]["off"]
    assert cv2.imread(str(out / "inputs_off.jpg")).shape[1] == 2 * 480
    assert cap.out.splitlines()[2].split()[:2] == ["off", "2"]


def test_eval_real_cli_errors(tmp_path, capsys):
    drive = _drive(tmp_path / "drive")
    out = str(tmp_path / "out")

    def fails(*argv: str, out: str = out) -> str:
        assert cli.main(["eval-real", *argv, "--out", out, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("xyzcyl eval-real: ") and len(err.splitlines()) == 1
        return err

    assert "PATH" in fails(str(tmp_path / "nowhere"))
    assert "--max-distance" in fails(str(drive), "--min-distance", "2", "--max-distance", "1")
    assert "--min-distance" in fails(str(drive), "--min-distance", "-1")
    assert "--min-distance" in fails(str(drive), "--min-distance", "3", "--max-distance", "4", "--lidar", "off")
    err = fails(str(drive), "--pairs", "frame_0:frame_9")
    assert "--pairs" in err and "'frame_9'" in err
    assert "--pairs" in fails(str(drive), "--pairs", "frame_0")
    assert "--pairs" in fails(str(drive), "--pairs", "frame_0:frame_0")
    assert "--pairs" in fails(str(drive), "--pairs", "frame_0:frame_1", "--max-distance", "3")
    assert "--max-pairs" in fails(str(drive), "--max-pairs", "0")
    assert "--threads" in fails(str(drive), "--threads", "0")
    assert "--detail-stride" in fails(str(drive), "--detail-stride", "0")
    err = fails(str(drive), "--cameras", "CAM_FRONT,CAM_TOP,CAM_X", "--lidar", "off")
    assert "--cameras" in err and "'CAM_TOP', 'CAM_X'" in err
    err = fails(str(drive), "--lidar", "on")
    assert "--lidar on" in err and "'frame_0'" in err
    assert "--lidar both" in fails(str(drive))
    assert "--model" in fails(str(drive), "--model", str(tmp_path / "no_model"))
    assert "--pairs" in fails(str(SYNTH / "rig.json"), "--pairs", "a:b")
    assert "--out" in fails(str(drive), out=str(drive / "frame_0" / "rig.json"))     # a file
    shutil.rmtree(drive / "frame_1")
    assert "PATH" in fails(str(drive), "--lidar", "off")                 # one frame
    assert "rig.json" in fails(str(drive / "frame_0"), "--lidar", "off")  # one rig's folder: pass its rig.json
    assert not (tmp_path / "out").exists()                               # nothing written on an error


@pytest.mark.slow
def test_eval_real_cli_on_the_real_drive(real_data, tmp_path, capsys):
    """PandaSet frame 20 reconstructed (LiDAR on, no detail layer: quick), rendered at frame 34's front camera
    1.16 m ahead: the render is nearer to frame 34's image than frame 20's own image is (the camera was moved the
    right way). The values themselves are reported in docs, not asserted."""
    drive = real_data / "pandaset_002_seq"
    frames = realeval.load_frames(drive)
    d = {f.name: f for f in frames}
    assert realeval.frame_distance(d["frame_20"], d["frame_34"]) == pytest.approx(1.16, abs=0.01)   # its README
    assert cli.main(["eval-real", str(drive), "--out", str(tmp_path), "--pairs", "frame_20:frame_34", "--cameras",
                     "front_camera", "--lidar", "on", "--no-detail", "--threads", "2", "--quiet"]) == 0
    capsys.readouterr()
    r = json.loads((tmp_path / "report.json").read_text())
    s = r["summary"]["on"]
    assert s["views"] == 1 and s["render_psnr"] > s["still_psnr"] and s["render_ssim"] > s["still_ssim"]
    assert r["scenes"][0]["lidar_points"] > 10000 and r["scenes"][0]["counts"]["lidar_cameras"] == 6
    assert (tmp_path / "frame_20_frame_34_on.jpg").is_file()
