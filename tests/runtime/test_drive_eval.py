"""`xyzcyl eval-real --drive` (runtime/drive_eval.py): a tiny drive end to end (report.json, the three methods
scored, a picture per scored frame, the summary lines, an ego mask left out of the scores), the plan of keyframes
and scored frames, a frame range keeping its tracks, masked metrics, and the flags' errors (exit 2 naming the
flag)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.runtime import drive_eval, realeval
from xyzcyl.runtime.drive import load_drive
from xyzcyl.testing.drives import pose, write_drive


def _tiny(tmp, n: int = 3, mask: bool = False, tracks=None):
    """The example rig at n frames 0.5 m apart, 0.1 s apart; with ``mask``, CAM_BACK's lower quarter is the ego's."""
    def edit(i, rig):
        if mask:
            cam = next(c for c in rig["cameras"] if c["name"] == "CAM_BACK")
            m = np.zeros((cam["height"], cam["width"]), np.uint8)
            m[-cam["height"] // 4:] = 255
            cv2.imwrite(str(tmp / f"ego_{i}.png"), m)
            cam["ego_mask"] = str(tmp / f"ego_{i}.png")
    tmp.mkdir(parents=True, exist_ok=True)
    return write_drive(tmp, [pose(0.5 * i, 0.0, 10.0) for i in range(n)], [100.0 + 0.1 * i for i in range(n)],
                       edit=edit, tracks=tracks)


def test_eval_real_drive_end_to_end(tmp_path, capsys):
    path = _tiny(tmp_path / "drive", mask=True)
    out = tmp_path / "out"
    assert cli.main(["eval-real", "--drive", str(path), "--every", "2", "--width", "64", "--lidar", "off",
                     "--stride", "8", "--out", str(out), "--quiet"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [x.get("method") for x in lines[:3]] == ["drive", "one", "still"]
    assert set(lines[3]) == {"gaussians", "seconds"}
    r = json.loads((out / "report.json").read_text())
    assert r["format"] == "xyzcyl-eval-real" and r["kind"] == "drive" and r["lidar"] == "off" and r["stride"] == 8
    assert r["keyframes"] == [0, 2] and r["scored_frames"] == [1] and r["frames"] == 3
    assert r["pictures"] == ["frame_01.jpg"] and (out / "frame_01.jpg").is_file()
    assert cv2.imread(str(out / "frame_01.jpg")).shape[1] == 4 * drive_eval.PICTURE_WIDTH
    assert len(r["rows"]) == 6 and {row["camera"] for row in r["rows"]} == set(r["methods"]["drive"]["per_camera"])
    assert all(row["frame"] == 1 and row["keyframe"] == 0 for row in r["rows"])
    for m in ("drive", "one", "still"):                 # each method scored, on every camera
        s = r["methods"][m]
        assert s == {k: v for k, v in lines[("drive", "one", "still").index(m)].items() if k != "method"}
        if m == "still":            # every frame of this drive has the same images: not moving is exact (inf: null)
            assert s["psnr"] is None and s["ssim"] == pytest.approx(1.0) and s["sharpness"] == pytest.approx(1.0)
        else:
            assert 5 < s["psnr"] < 60 and 0 < s["ssim"] < 1 and s["sharpness"] > 0, (m, s)
    assert r["ego_masked"] == {"CAM_BACK": pytest.approx(0.25, abs=0.03)}
    assert r["gaussians"]["drive"] > 0 and list(r["gaussians"]["one_frame"]) == ["0"]


def test_plan_and_a_frame_range_with_its_tracks(tmp_path):
    assert drive_eval.plan(40, 8) == ([0, 8, 16, 24, 32], [k for k in range(40) if k % 8])
    # the selection of docs/results.md's camera-only run (--max-views 8)
    assert drive_eval.plan(40, 8, 8)[1] == [1, 6, 12, 18, 22, 28, 34, 39]
    assert drive_eval.plan(3, 1) == ([0, 1, 2], [])
    assert drive_eval.nearest_keyframe([0, 2], 1) == 0 and drive_eval.nearest_keyframe([0, 8], 5) == 8
    car = {"tracks": [{"id": "car-1", "label": "Car", "size": [5.0, 6.0, 4.0], "stationary": False,
                       "poses": [{"frame": k, "object_to_world": pose(12.0 + k, 0.0)} for k in range(4)]}]}
    path = _tiny(tmp_path, n=4, tracks=car)
    d = drive_eval.sub_drive(load_drive(path, check_images=False), 1, 3)
    assert [f.index for f in d.frames] == [0, 1] and [f.timestamp_s for f in d.frames] == [100.1, 100.2]
    assert sorted(d.tracks[0].poses) == [0, 1]
    np.testing.assert_allclose(d.tracks[0].poses[0][:3, 3], [13.0, 0.0, 0.0])
    assert sorted(drive_eval.sub_drive(load_drive(path, check_images=False), 3, 4).tracks[0].poses) == [0]


def test_masked_metrics_leave_the_masked_pixels_out():
    rng = np.random.default_rng(0)
    gt = rng.random((40, 50, 3)).astype(np.float32)
    pred = gt.copy()
    pred[30:] = 0.0                                         # wrong only under the mask
    keep = np.ones((40, 50), bool)
    keep[30:] = False
    m = realeval.image_metrics(pred, gt, keep)
    assert math.isinf(m["psnr"]) and m["ssim"] == pytest.approx(1.0) and m["sharpness"] == pytest.approx(1.0)
    assert realeval.image_metrics(pred, gt)["psnr"] < 20
    assert math.isnan(realeval.psnr(pred, gt, np.zeros((40, 50), bool)))      # nothing left to score


def test_eval_real_drive_flag_errors(tmp_path, capsys):
    path = _tiny(tmp_path / "drive")
    out = str(tmp_path / "out")

    def fails(*argv: str) -> str:
        assert cli.main(["eval-real", *argv, "--out", out, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("xyzcyl eval-real: ") and len(err.splitlines()) == 1, err
        return err

    d = ("--drive", str(path), "--lidar", "off")
    assert "--every" in fails(*d, "--every", "0")
    assert "--every" in fails(*d, "--every", "1")                           # every frame a keyframe: none scored
    assert "--frames" in fails(*d, "--frames", "0:99")
    assert "--frames" in fails(*d, "--frames", "2:1")
    assert "--frames" in fails(*d, "--frames", "seven")
    assert "--max-views" in fails(*d, "--max-views", "0")
    assert "--width" in fails(*d, "--width", "0")
    assert "--lidar" in fails("--drive", str(path), "--lidar", "both")
    assert "--lidar" in fails("--drive", str(path))                          # on, and the rig has no sweep
    assert "--stride" in fails(*d, "--stride", "0")
    assert "--stride" in fails(*d, "--stride", "4", "--no-detail")
    assert "--pairs" in fails(*d, "--pairs", "a:b")
    assert "--drive" in fails("--drive", str(tmp_path / "nowhere.json"))
    assert "--width" in fails(str(tmp_path / "drive"), "--width", "64")      # a --drive flag without --drive
    assert "--stereo" in fails(str(tmp_path / "drive"), "--stereo", "off")
    assert "PATH" in fails("--lidar", "off")
    assert not (tmp_path / "out").exists()                                   # nothing written on an error
