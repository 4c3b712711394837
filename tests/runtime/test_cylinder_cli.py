"""`xyzcyl cylinder` on the real rigs and on bad input."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest

from xyzcyl.clients.cli import main


@pytest.mark.parametrize("folder", ["nuscenes_ca9a282c", "pandaset_002_00"])
def test_real_rig_panorama(real_data, tmp_path, capsys, folder):
    out = tmp_path / "pano.png"
    assert main(["cylinder", str(real_data / folder / "rig.json"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    covered = float(re.search(r"covered: ([0-9.]+)%", text).group(1))
    assert covered >= 90.0, text  # the acceptance figure for the default settings
    img = cv2.imread(str(out))
    assert img.shape == (224, 1024, 3)
    assert img.mean() > 20  # real content, not an empty canvas
    assert len(re.findall(r"% of the cylinder", text)) == 6


def test_ccw_and_preset_options(real_data, tmp_path, capsys):
    rig = str(real_data / "pandaset_002_00" / "rig.json")
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    assert main(["cylinder", rig, "--out", str(a), "--order", "cw", "--height", "32", "--width", "128"]) == 0
    assert main(["cylinder", rig, "--out", str(b), "--order", "ccw", "--height", "32", "--width", "128",
                 "--preset", "pandaset", "--module", "volume"]) == 0
    text = capsys.readouterr().out
    assert "rho 1.6, dh 0" in text
    assert cv2.imread(str(a)).shape == (32, 128, 3)


def _tiny_rig(tmp_path, **changes):
    cam = {"name": "CAM_A", "image": "a.png", "width": 32, "height": 24,
           "K": [[20.0, 0, 15.5], [0, 20.0, 11.5], [0, 0, 1]],
           "cam_to_ego": [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], "distortion": None}
    cam.update(changes)
    cv2.imwrite(str(tmp_path / "a.png"), np.full((24, 32, 3), 128, np.uint8))
    path = tmp_path / "rig.json"
    path.write_text(json.dumps({"cameras": [cam]}))
    return str(path)


@pytest.mark.parametrize("case, needle", [
    ("missing_rig", "cannot read"),
    ("bad_K", "K[0][1]"),
    ("size", "width x height"),
    ("rho", "rho"),
    ("z_range", "z_range"),
    ("out_suffix", "--out"),
    ("out_folder", "--out"),
    ("width", "--width"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, case, needle):
    out = str(tmp_path / "o.png")
    args = {
        "missing_rig": lambda: [str(tmp_path / "nope.json"), "--out", out],
        "bad_K": lambda: [_tiny_rig(tmp_path, K=[[20.0, 1.0, 15.5], [0, 20.0, 11.5], [0, 0, 1]]), "--out", out],
        "size": lambda: [_tiny_rig(tmp_path, width=33), "--out", out],
        "rho": lambda: [_tiny_rig(tmp_path), "--out", out, "--rho", "9"],
        "z_range": lambda: [_tiny_rig(tmp_path), "--out", out, "--z-range", "4", "1"],
        "out_suffix": lambda: [_tiny_rig(tmp_path), "--out", str(tmp_path / "o.jpg")],
        "out_folder": lambda: [_tiny_rig(tmp_path), "--out", str(tmp_path / "no" / "o.png")],
        "width": lambda: [_tiny_rig(tmp_path), "--out", out, "--width", "0"],
    }[case]()
    assert main(["cylinder", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert "Traceback" not in err


def test_tiny_rig_runs(tmp_path, capsys):
    assert main(["cylinder", _tiny_rig(tmp_path), "--out", str(tmp_path / "o.png"), "--height", "8",
                 "--width", "64"]) == 0
    assert "covered:" in capsys.readouterr().out
