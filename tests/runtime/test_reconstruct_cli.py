"""`xyzcyl reconstruct` and `xyzcyl render SCENE_DIR` on the shipped example rig (examples/synth_nuscenes) with the
tiny test model; bad inputs exit 2 with one line naming the camera or the file."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from xyzcyl import cli
from xyzcyl.testing import EXAMPLE_RIG, REPO

pytestmark = pytest.mark.slow   # the session's ONNX export (tests/conftest.py)


@pytest.fixture(scope="module")
def scene_dir(tiny_export, tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "scene"
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(out), "--model", str(tiny_export.dir),
                     "--threads", "1", "--quiet"]) == 0
    return out


@pytest.fixture
def rig_copy(tmp_path):
    d = tmp_path / "rig"
    shutil.copytree(EXAMPLE_RIG.parent, d)
    return d


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def test_reconstruct_writes_a_scene_folder(scene_dir):
    meta = json.loads((scene_dir / "scene.json").read_text())
    assert meta["model"]["name"] == "tiny-test" and len(meta["rig"]["cameras"]) == 6
    assert meta["counts"]["total"] > 0 and (scene_dir / "background.png").is_file()


def test_render_scene_from_an_input_camera(scene_dir, tmp_path):
    import cv2
    import OpenImageIO as oiio

    png = tmp_path / "v.png"
    assert cli.main(["render", str(scene_dir), "--camera", "CAM_FRONT", "--width", "160", "--height", "90",
                     "--out", str(png), "--threads", "1"]) == 0
    img = cv2.imread(str(png))
    assert img.shape == (90, 160, 3) and img.std() > 0
    exr = tmp_path / "v.exr"
    assert cli.main(["render", str(scene_dir), "--camera", "CAM_FRONT", "--width", "160", "--height", "90",
                     "--forward", "3", "--out", str(exr)]) == 0
    inp = oiio.ImageInput.open(str(exr))
    assert inp.spec().channelnames == ("R", "G", "B", "A", "Z")
    moved = inp.read_image(oiio.FLOAT)
    inp.close()
    assert not np.allclose(moved[..., :3], cv2.imread(str(png))[..., ::-1] / 255.0, atol=0.02)
    # the pose flags work on a scene folder too
    eye = [str(v) for v in np.eye(4).ravel()]
    assert cli.main(["render", str(scene_dir), "--width", "64", "--height", "32", "--equirect", "--cam-to-world",
                     *eye, "--out", str(tmp_path / "p.png")]) == 0


def test_reconstruct_without_a_shipped_model(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("XYZCYL_MODEL", str(tmp_path / "absent"))
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s")]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "no shipped model" in err[0] and "--model" in err[0]


def test_altered_model_file(tiny_export, tmp_path, capsys):
    m = tmp_path / "m"
    shutil.copytree(tiny_export.dir, m)
    with open(m / "encode.onnx", "r+b") as f:
        f.seek(1000)
        b = f.read(1)
        f.seek(1000)
        f.write(bytes([b[0] ^ 0xFF]))
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--model", str(m), "--quiet"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "encode.onnx" in err[0] and "altered" in err[0]


@pytest.mark.parametrize("case", ["size", "corrupt", "nan_depth"])
def test_bad_rig_input_names_the_camera(tiny_export, rig_copy, tmp_path, capsys, case):
    import cv2

    img = rig_copy / "images" / "CAM_BACK.png"
    if case == "size":
        cv2.imwrite(str(img), cv2.resize(cv2.imread(str(img)), (400, 225)))
    elif case == "corrupt":
        img.write_bytes(img.read_bytes()[:200] + b"\x00" * 300)
    else:
        from xyzcyl.common.media import write_exr

        d = np.full((450, 800, 1), 10.0, np.float32)
        d[5, 7] = np.nan
        write_exr(rig_copy / "back_depth.exr", d, ("Z",))
        rig = json.loads((rig_copy / "rig.json").read_text())
        rig["cameras"][3]["depth"] = "back_depth.exr"
        (rig_copy / "rig.json").write_text(json.dumps(rig))
    rc = cli.main(["reconstruct", str(rig_copy / "rig.json"), "--out", str(tmp_path / "s"), "--model",
                   str(tiny_export.dir), "--quiet"])
    err = _err(capsys)
    assert rc == 2 and len(err) == 1 and "CAM_BACK" in err[0], err
    assert not (tmp_path / "s").exists()


def test_render_errors(scene_dir, tmp_path, capsys):
    out = str(tmp_path / "v.png")
    assert cli.main(["render", str(scene_dir), "--camera", "NOPE", "--out", out]) == 2
    assert "--camera" in _err(capsys)[0]
    ply = scene_dir / "scene.ply"
    assert cli.main(["render", str(ply), "--camera", "CAM_FRONT", "--out", out]) == 2
    assert "SCENE_DIR" in _err(capsys)[0]
    assert cli.main(["render", str(tmp_path), "--camera", "CAM_FRONT", "--out", out]) == 2
    assert "scene.json" in _err(capsys)[0]


def test_existing_out_needs_force(scene_dir, tiny_export, capsys):
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(scene_dir), "--model",
                     str(tiny_export.dir)]) == 2
    assert "--force" in _err(capsys)[0]


def test_export_refuses_existing_folder_and_stage1(tiny_export, tmp_path, capsys):
    import torch

    assert cli.main(["export-model", "--checkpoint", str(tiny_export.checkpoint), "--out", str(tiny_export.dir)]) == 2
    assert "exists" in _err(capsys)[0]
    ck = torch.load(tiny_export.checkpoint, weights_only=False)
    ck["train_cfg"]["stage"] = "occ"
    torch.save(ck, tmp_path / "occ.pt")
    assert cli.main(["export-model", "--checkpoint", str(tmp_path / "occ.pt"), "--out", str(tmp_path / "m")]) == 2
    assert "stage" in _err(capsys)[0] and not (tmp_path / "m").exists()


def test_reconstruct_uses_the_rigs_lidar_and_lidar_eval_holdout(tiny_export, rig_copy, tmp_path, capsys):
    """A rig whose lidar block names a sweep: `reconstruct` makes the depth from it by default (counts.lidar_cameras),
    not with --no-lidar; `lidar-eval --holdout` checks on the points it did not use; bad LiDAR input exits 2 naming
    the file."""
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-1.0, 4.0, 30))
    wall = np.stack([15 * np.cos(az).ravel(), 15 * np.sin(az).ravel(), z.ravel()], axis=1)
    np.save(rig_copy / "sweep.npy", wall)
    rig = json.loads((rig_copy / "rig.json").read_text())
    rig["lidar"] = {"file": "sweep.npy"}
    (rig_copy / "rig.json").write_text(json.dumps(rig))
    args = ["reconstruct", str(rig_copy / "rig.json"), "--model", str(tiny_export.dir), "--quiet", "--no-depth"]
    assert cli.main([*args, "--out", str(tmp_path / "a")]) == 0
    assert json.loads((tmp_path / "a" / "scene.json").read_text())["counts"]["lidar_cameras"] == 6
    assert cli.main([*args, "--out", str(tmp_path / "b"), "--no-lidar"]) == 0
    assert "lidar_cameras" not in json.loads((tmp_path / "b" / "scene.json").read_text())["counts"]
    capsys.readouterr()
    assert cli.main([*args, "--out", str(tmp_path / "c"), "--no-lidar", "--lidar-file", "x.npy"]) == 2
    assert "--no-lidar" in _err(capsys)[0]
    assert cli.main([*args, "--out", str(tmp_path / "c"), "--lidar-file", str(tmp_path / "none.npy")]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "none.npy" in err[0] and "does not exist" in err[0]
    out = tmp_path / "h.json"
    assert cli.main(["lidar-eval", str(rig_copy / "rig.json"), "--model", str(tiny_export.dir), "--holdout", "0.5",
                     "--width", "80", "--json", str(out), "--quiet"]) == 0
    r = json.loads(out.read_text())
    n_check = sum(c["lidar_pixels"] for c in r["cameras"])
    assert r["holdout"] == 0.5 and 0 < n_check == r["all"]["lidar_pixels"]
    assert cli.main(["lidar-eval", str(rig_copy / "rig.json"), "--scene", str(tmp_path / "a"), "--holdout", "0.5",
                     "--quiet"]) == 2
    assert "--holdout" in _err(capsys)[-1]


SHIPPED_MODEL = REPO / "models" / "xyzcyl-cpu-v1"


@pytest.mark.parametrize("flags,named", [
    (["--detail-stride", "0"], ["--detail-stride", "1..16"]),
    (["--detail-stride", "17"], ["--detail-stride", "1..16"]),
])
def test_detail_flags_are_checked_before_the_model_loads(tmp_path, capsys, flags, named):
    """A bad detail flag exits 2 naming it, before anything else is looked at (here the --model folder is absent:
    its error would come next)."""
    rc = cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--model", str(tmp_path / "none"),
                   *flags])
    err = _err(capsys)
    assert rc == 2 and len(err) == 1 and all(n in err[0] for n in named) and "--model" not in err[0], err
    assert not (tmp_path / "s").exists()


def test_no_detail_with_detail_stride_is_a_usage_error(tmp_path, capsys):
    """The two flags are one mutually exclusive group (runtime/commands/detail_flags.py): argparse exits 2 with a
    line naming both, before the model or the rig is looked at."""
    with pytest.raises(SystemExit) as exc:
        cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--model", str(tmp_path / "none"),
                  "--no-detail", "--detail-stride", "4"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and "--no-detail" in err[-1] and "--detail-stride" in err[-1], err
    assert not (tmp_path / "s").exists()


@pytest.mark.skipif(not (SHIPPED_MODEL / "model.json").is_file(), reason="no shipped model in models/ yet")
def test_detail_stride_and_no_detail_reach_the_reconstruction(tmp_path, capsys):
    """--detail-stride N: the detail layer at that stride (at most one Gaussian per N x N block of each 800x450
    camera), named in the summary line and in scene.json's counts; --no-detail: the model's Gaussians only."""
    base = ["reconstruct", str(EXAMPLE_RIG), "--model", str(SHIPPED_MODEL), "--threads", "1", "--quiet"]
    capsys.readouterr()
    assert cli.main([*base, "--out", str(tmp_path / "d8"), "--detail-stride", "8"]) == 0
    line = capsys.readouterr().out.splitlines()[0].split(": ", 1)[1]     # after the folder's name
    c = json.loads((tmp_path / "d8" / "scene.json").read_text())["counts"]
    assert 0 < c["detail"] <= 6 * 100 * 57 and c["total"] == c["coarse"] + c["detail"] + c["carved"] + 3 * c["split"], c
    assert f"{c['detail']} detail (stride 8)" in line and f"{c['culled']} model Gaussians culled" in line, line
    assert cli.main([*base, "--out", str(tmp_path / "off"), "--no-detail"]) == 0
    line = capsys.readouterr().out.splitlines()[0].split(": ", 1)[1]
    c = json.loads((tmp_path / "off" / "scene.json").read_text())["counts"]
    assert not {"detail", "culled", "coarse"} & set(c) and "detail" not in line, (c, line)


def test_a_bad_workers_count_is_refused_before_any_work(tmp_path, capsys):
    """`reconstruct DRIVE --workers -1` exits 2 naming the flag, before the model or any frame is read; with a rig
    (one timestamp) the flag is refused as the other drive flags are."""
    from xyzcyl.testing.drives import write_drive

    drive = write_drive(tmp_path / "d", [np.eye(4), np.eye(4)], [0.0, 1.0])
    assert cli.main(["reconstruct", str(drive), "--out", str(tmp_path / "s"), "--workers", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--workers: must be >= 0" in err and "load model" not in err
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--workers", "1"]) == 2
    assert "--workers: goes with a drive file" in capsys.readouterr().err
    assert cli.main(["reconstruct", str(EXAMPLE_RIG), "--out", str(tmp_path / "s"), "--stationary-actors"]) == 2
    assert "--stationary-actors: goes with a drive file" in capsys.readouterr().err


def test_a_drives_summary_line_counts_its_chunks_and_camera_layers(tmp_path, capsys):
    """`reconstruct DRIVE` (two keyframes 3 m apart) prints the shared Gaussians, then the viewpoint chunks' and the
    camera layers' (runtime.cameralayers) as scene.json counts them; the folder holds the layers' files."""
    import re

    from xyzcyl.testing.drives import pose, write_drive

    E = np.array(pose(7, 3, 20))
    drive = write_drive(tmp_path / "d", [E, E @ np.array(pose(3.0, 0.0))], [0.0, 0.5])
    out = tmp_path / "s"
    assert cli.main(["reconstruct", str(drive), "--out", str(out), "--detail-stride", "16", "--no-stereo",
                     "--workers", "0", "--quiet"]) == 0
    c = json.loads((out / "scene.json").read_text())["counts"]
    line = capsys.readouterr().out.splitlines()[0]
    m = re.match(r".*: (\d+) Gaussians \(\+ (\d+) in (\d+) viewpoint chunks, \+ (\d+) in its keyframes' camera "
                 r"layers\) from 2 keyframes of 2 frames", line)
    assert m is not None, line
    assert [int(v) for v in m.groups()] == [c["total"], c["viewpoint_gaussians"], c["viewpoints"],
                                            c["camera_layer_gaussians"]], (line, c)
    assert sorted(p.name for p in (out / "cameras").iterdir()) == ["keyframe_000.ply", "keyframe_001.ply"]
