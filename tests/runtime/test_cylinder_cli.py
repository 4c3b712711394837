"""`xyzcyl cylinder` on the real rigs and on bad input."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
from xyzcyl.cli import main


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
                 "--preset", "pandaset", "--module", "volume", "--sort-clockwise"]) == 0
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


def test_equirectangular_panorama_rig(real_data, tmp_path, capsys):
    """A single real equirectangular panorama (Poly Haven, CC0) as a one-camera rig covers the whole cylinder,
    and its forward direction (pano centre column) lands on the cylinder's centre column."""
    pano = real_data / "pano_potsdamer_platz" / "potsdamer_platz_1k_tonemapped.png"
    rig = {"cameras": [{"name": "pano", "image": str(pano), "model": "equirectangular", "width": 1024,
                        "height": 512, "cam_to_ego": [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.6], [0, 0, 0, 1]]}]}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    out = tmp_path / "o.png"
    assert main(["cylinder", str(tmp_path / "rig.json"), "--out", str(out), "--height", "64", "--width", "1024"]) == 0
    assert "covered: 100.00%" in capsys.readouterr().out
    cyl = cv2.imread(str(out)).astype(np.float32)
    src = cv2.imread(str(pano)).astype(np.float32)
    # Cylinder row 31 (p = 31.5/64, R_u = 8/tan(0.45 pi) = 1.267 m) looks up by atan(16 (1/2 - p) / R_u) =
    # 5.63 deg, i.e. pano row 84.37/180 * 512 - 1/2 = 239.5. Cylinder column j and pano column j sample the
    # same azimuth (both 1024 wide, forward at the centre), so the profiles match; a mirrored or shifted
    # azimuth convention would not.
    a = cyl[31].mean(axis=1)
    b = src[239:241].mean(axis=(0, 2))
    assert np.corrcoef(a, b)[0, 1] > 0.95
    assert np.corrcoef(a, b[::-1])[0, 1] < 0.5
    assert np.corrcoef(a, np.roll(b, 100))[0, 1] < 0.5
