"""`xyzcyl reconstruct` and `xyzcyl render` as a new user meets them (issue 27, defects 1 and 5): a cut or corrupt
image, a bad rig and bad flags exit 2 with one clean line naming the camera or the flag (docs/cli.md), and what the
rig alone decides is refused before the model loads."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from xyzcyl import cli

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_RIG = REPO / "examples" / "synth_nuscenes" / "rig.json"
SHIPPED_MODEL = REPO / "models" / "xyzcyl-cpu-v1"


@pytest.fixture
def jpeg_rig(tmp_path) -> Path:
    """The example rig with its six images as JPEG files (real data rigs ship JPEGs)."""
    d = tmp_path / "rig"
    d.mkdir()
    rig = json.loads(EXAMPLE_RIG.read_text())
    for c in rig["cameras"]:
        img = cv2.imread(str(EXAMPLE_RIG.parent / c["image"]))
        c["image"] = f"{c['name']}.jpg"
        assert cv2.imwrite(str(d / c["image"]), img)
    (d / "rig.json").write_text(json.dumps(rig))
    return d / "rig.json"


def _no_load(*a, **kw):
    raise AssertionError("the model was loaded before the rig was refused")


@pytest.fixture
def no_model_load(monkeypatch):
    """Fail the test if the command loads the model."""
    from xyzcyl.runtime.inference import Reconstructor

    monkeypatch.setattr(Reconstructor, "load", _no_load)


def _run(args: list[str], capfd) -> tuple[int, list[str]]:
    rc = cli.main(args)
    err = capfd.readouterr().err           # file-descriptor level: a C library's stray print shows up here too
    return rc, err.strip().splitlines()


def _cut(b: bytes) -> bytes:
    return b[: len(b) * 2 // 3]


def _ff_run(b: bytes) -> bytes:
    return b[: len(b) // 2] + b"\xff" * 100 + b[len(b) // 2 + 100:]


@pytest.mark.parametrize("case", ["jpeg cut", "png cut", "jpeg corrupt data"])
def test_reconstruct_refuses_a_cut_or_corrupt_image(jpeg_rig, tmp_path, capfd, monkeypatch, case):
    """Regression (issue 27, defect 1): a cut JPEG was reconstructed (libjpeg filled the rest with grey: exit 0, a
    grey wall in the scene); a cut PNG's line ended in '()' after a stray 'libpng error' line (defect 5)."""
    if case == "png cut":
        rig_json = tmp_path / "png" / "rig.json"
        shutil.copytree(EXAMPLE_RIG.parent, rig_json.parent)
        img = rig_json.parent / "images" / "CAM_BACK.png"
    else:
        rig_json = jpeg_rig
        img = rig_json.parent / "CAM_BACK.jpg"
    img.write_bytes((_ff_run if case == "jpeg corrupt data" else _cut)(img.read_bytes()))
    if case == "jpeg corrupt data":        # header and end are whole: the decoder finds it, after the model load
        if not (SHIPPED_MODEL / "model.json").is_file():
            pytest.skip("no shipped model in models/")
        model = SHIPPED_MODEL
    else:                                  # the file's structure gives it away: refused before the model loads
        from xyzcyl.runtime.inference import Reconstructor

        model = tmp_path
        monkeypatch.setattr(Reconstructor, "load", _no_load)
    rc, err = _run(["reconstruct", str(rig_json), "--out", str(tmp_path / "s"), "--model", str(model),
                    "--quiet", "--no-detail", "--threads", "1"], capfd)
    assert rc == 2 and len(err) == 1, err
    line = err[0]
    assert line.startswith("xyzcyl reconstruct: camera 'CAM_BACK': image: ") and "cut short or corrupt" in line, line
    assert "()" not in line and "libpng" not in line, line
    assert not (tmp_path / "s").exists()


def _negative_fx(rig: dict, root: Path) -> None:
    rig["cameras"][1]["K"][0][0] = -633.0


def _no_cameras(rig: dict, root: Path) -> None:
    rig["cameras"] = []


def _missing_image(rig: dict, root: Path) -> None:
    (root / rig["cameras"][2]["image"]).unlink()


@pytest.mark.parametrize("change,line", [
    (_negative_fx, "camera 'CAM_FRONT_RIGHT': K[0][0]: fx must be > 0 (got -633.0)"),
    (_no_cameras, "rig: cameras: must have 1..16 entries (got 0)"),
    (_missing_image, "camera 'CAM_BACK_RIGHT': image: file "),
])
def test_reconstruct_checks_the_rig_before_the_model_loads(jpeg_rig, tmp_path, capfd, no_model_load, change, line):
    """Regression (issue 27, defect 5): the model loaded (~1 s) before the rig was read; numbers showed as
    'np.float64(-633.0)'. The --model folder here is an empty one: loading it would fail the test (no_model_load)."""
    rig = json.loads(jpeg_rig.read_text())
    change(rig, jpeg_rig.parent)
    jpeg_rig.write_text(json.dumps(rig))
    rc, err = _run(["reconstruct", str(jpeg_rig), "--out", str(tmp_path / "s"), "--model", str(tmp_path), "--quiet"],
                   capfd)
    assert rc == 2 and len(err) == 1 and err[0].startswith(f"xyzcyl reconstruct: {line}"), err
    assert "np." not in err[0]


EYE = [str(v) for v in np.eye(4).ravel()]


@pytest.mark.parametrize("args,line", [
    (["--camera", "CAM_FRONT", "--width", "0"], "--width: must be >= 1, got 0"),
    (["--camera", "CAM_FRONT", "--height", "0"], "--height: must be >= 1, got 0"),
    (["--camera", "CAM_FRONT", "--width", "-100"], "--width: must be >= 1, got -100"),
    (["--K", "100", "100", "31.5", "23.5", "--cam-to-world", *EYE, "--width", "64", "--height", "0"],
     "--height: must be >= 1, got 0"),
])
def test_render_refuses_a_size_below_one(tmp_path, capfd, args, line):
    """Regression (issue 27, defect 5): with --camera, --width 0 was ignored (the camera's own width) while -100
    was refused as a '--camera' error. Checked before the scene is read (the folder here is not one)."""
    rc, err = _run(["render", str(tmp_path), *args, "--out", str(tmp_path / "v.png")], capfd)
    assert rc == 2 and err == [f"xyzcyl render: {line}"], err


@pytest.mark.parametrize("args", [["--camera", "X"], ["--K", "100", "100", "31.5", "23.5", "--cam-to-world", *EYE,
                                                       "--width", "64", "--height", "48"]])
def test_render_names_a_missing_path(tmp_path, capfd, args):
    """Regression (issue 27, defect 5): `render /nonexistent --camera X` said 'a PLY has no rig'."""
    missing = tmp_path / "nonexistent"
    rc, err = _run(["render", str(missing), *args, "--out", str(tmp_path / "v.png")], capfd)
    assert rc == 2 and err == [f"xyzcyl render: PLY|SCENE_DIR: {str(missing)!r} does not exist"], err
