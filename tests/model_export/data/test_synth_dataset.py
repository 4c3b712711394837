"""On-disk data set: format loads with the runtime rig loader, resumable, deterministic, CLI."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from xyzcyl.cli import main
from xyzcyl.model_export.data.synth import SynthConfig, read_exr, synth
from xyzcyl.runtime.rig import Rig, load_rig

CFG = SynthConfig(height=32, width=56, inward_views=3, seed=3, voxels=(0.8,))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    assert synth(out, 2, CFG, progress=False) == 2
    return out


def test_scene_loads_with_runtime_rig_loader(dataset):
    folder = dataset / "scene_000000"
    rig = load_rig(folder / "rig.json")  # checks that every image and depth file exists with the declared size
    assert len(rig.cameras) == 6
    imgs = rig.load_images()
    depths = rig.load_depths()
    assert imgs[0].shape == (32, 56, 3) and depths[0].shape == (32, 56)
    assert all(np.all(d >= 0) for d in depths)
    targets = json.loads((folder / "targets.json").read_text())["settings"]
    assert set(targets) == {"ego-forward", "ego-inward"}
    inward = Rig.from_dict(targets["ego-inward"], root=folder)
    inward.check_images()
    assert len(inward.cameras) == 3 and len(Rig.from_dict(targets["ego-forward"], root=folder).cameras) == 12
    cam = json.loads((folder / "rig.json").read_text())["cameras"][0]
    sky = np.asarray(__import__("cv2").imread(str(folder / cam["sky"]), 0))
    assert np.array_equal(sky > 0, read_exr(folder / cam["depth"]) == 0)  # sky <=> depth 0
    occ = np.load(folder / "occupancy.npz")
    assert occ["semantic_0p8"].shape == (100, 100, 20) and occ["bev_0p8"].shape == (100, 100)
    assert np.array_equal(occ["occupied_0p8"], occ["semantic_0p8"] > 0)
    index = json.loads((dataset / "index.json").read_text())
    assert index["seed"] == 3 and index["generator_version"] and index["scenes"] == 2


def test_resume_skips_finished_scenes_and_is_deterministic(dataset, tmp_path):
    assert synth(dataset, 2, CFG, progress=False) == 0
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    before = (copy / "scene_000001" / "inputs" / "CAM_FRONT.png").read_bytes()
    shutil.rmtree(copy / "scene_000001")
    assert synth(copy, 3, CFG, progress=False) == 2
    assert (copy / "scene_000001" / "inputs" / "CAM_FRONT.png").read_bytes() == before
    assert not (copy / ".tmp").exists()
    with pytest.raises(ValueError, match="^seed"):
        synth(copy, 3, replace(CFG, seed=4), progress=False)


def test_cli_synth_and_gallery(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = main(["data", "synth", "--out", str(out), "--scenes", "1", "--height", "24", "--width", "40",
               "--targets", "ego-inward", "--inward-views", "2", "--voxels", "0.8", "--seed", "1", "--quiet"])
    assert rc == 0 and (out / "scene_000000" / "rig.json").is_file()
    assert main(["data", "gallery", str(out), "--out", str(tmp_path / "sheet.png"), "--tile-width", "60"]) == 0
    assert (tmp_path / "sheet.png").stat().st_size > 1000
    assert main(["data", "synth", "--out", str(out), "--scenes", "1", "--targets", "sideways"]) == 2
    assert "targets" in capsys.readouterr().err
    assert main(["data", "synth", "--out", str(out), "--scenes", "1", "--rig", "nope"]) == 2
    assert main(["data", "synth", "--out", str(out), "--scenes", "1", "--voxels", "0.7"]) == 2
    (tmp_path / "file").write_text("x")
    assert main(["data", "synth", "--out", str(tmp_path / "file"), "--scenes", "1"]) == 2
