"""Training loop: both stages run, checkpoints resume exactly, logs/curves/sheets appear, CLI errors exit 2."""

import csv
import math
import subprocess
import sys

import pytest
import torch
from xyzcyl.model_export.dataset import DatasetConfig
from xyzcyl.model_export.losses import OptimConfig, TrainLossConfig
from xyzcyl.model_export.train import (
    OCC_MODULES,
    TrainConfig,
    build_model,
    depth_head_loss,
    load_init,
    set_stage,
    train,
)
from xyzcyl.testing.model import synth_test_config


def _tcfg(stage, steps, **kw):
    return TrainConfig(stage=stage, steps=steps, ckpt_every=2, val_scenes=1, seed=1,
                       data=DatasetConfig(num_targets=2, voxel_size=1.6, flip_prob=0.5, brightness=0.1),
                       loss=TrainLossConfig(optim=OptimConfig(lr=1e-3, warmup_steps=1, total_steps=steps)), **kw)


def _train_cli(args, capsys) -> tuple[int, str]:
    """`xyzcyl train ARGS` in this process (a subprocess per call cost ~5 s of interpreter and torch start-up):
    (exit status, stderr). The thread counts that --threads sets are restored after (later tests' results depend
    on them)."""
    import numba
    from xyzcyl import cli

    n_torch, n_numba = torch.get_num_threads(), numba.get_num_threads()
    try:
        rc = cli.main(["train", *map(str, args)])
    except SystemExit as e:                             # argparse's own refusals
        rc = e.code
    finally:
        torch.set_num_threads(n_torch)
        numba.set_num_threads(n_numba)
    return rc, capsys.readouterr().err


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_simulated_lidar_becomes_the_depth_input_and_trains_the_rest(tiny_synth_data):
    """An item with a simulated sweep (dataset lidar_input): the model gets the runtime's fused depth (LiDAR cells
    exact), the render loss reaches the pixel branch, and the depth head (replaced) gets no gradient."""
    import numpy as np
    from xyzcyl.model_export.dataset import SceneDataset
    from xyzcyl.model_export.train import _resize, lidar_depth_input, step_loss

    torch.manual_seed(0)
    cfg = synth_test_config()
    model = build_model(cfg)
    data = SceneDataset(tiny_synth_data, DatasetConfig(setting="both", num_targets=2, voxel_size=1.6,
                                                       lidar_input=1.0), model_cfg=cfg)
    item = data.item(0, 0)
    depth, mask = lidar_depth_input(model, _resize(item["images"], cfg), item)
    lid = item["lidar_depth"].numpy()
    assert depth.shape == (lid.shape[0], 1, *lid.shape[1:]) and torch.all(mask == 1)
    has = lid > 0
    np.testing.assert_array_equal(depth[:, 0].numpy()[has], lid[has])
    assert (depth[:, 0].numpy()[~has & item["lidar_surface"].numpy()] > 0).all()    # the head's depth, rescaled
    tcfg = _tcfg("render", 1)
    loss, parts = step_loss(model, item, tcfg)
    loss.backward()
    assert "depth_head" not in parts
    head = [p.grad for p in model.depth_head.parameters()]
    assert all(g is None or not g.any() for g in head)
    pix = [p.grad for n, p in model.named_parameters() if n.startswith(("pix_net", "pix_mlp", "pix_out"))]
    assert pix and any(g is not None and g.abs().sum() > 0 for g in pix)


def test_depth_head_loss_by_hand():
    pred = torch.tensor([[[[2.0, 4.0]]]])                       # head output [1, 1, 1, 2]
    gt = torch.tensor([[[[1.0, 9.0, 4.0, 9.0], [9.0, 9.0, 9.0, 9.0]]]])  # nearest 2x4 -> 1x2 takes (0,0), (0,2)
    valid = torch.ones_like(gt, dtype=torch.bool)
    sky = torch.zeros_like(gt)
    # |log 2 - log 1| and |log 4 - log 4| -> mean log(2) / 2
    assert float(depth_head_loss(pred, gt, valid, sky)) == pytest.approx(math.log(2) / 2, rel=1e-6)
    sky[0, 0, 0, 2] = 1.0                                        # the second pixel is sky: only log 2 is left
    assert float(depth_head_loss(pred, gt, valid, sky)) == pytest.approx(math.log(2), rel=1e-6)


def test_stage_parameters():
    model = build_model(synth_test_config())
    base = {n: p.requires_grad for n, p in model.named_parameters()}
    occ = {id(p) for p in set_stage(model, "occ", base)}
    ren = {id(p) for p in set_stage(model, "render", base)}
    for n, p in model.named_parameters():
        top = n.split(".")[0]
        if top in OCC_MODULES:
            assert id(p) not in ren, n          # frozen in stage 2
        if not base[n]:
            assert id(p) not in occ and id(p) not in ren, n   # the model's own frozen trunk stays frozen
    assert occ and ren and not (occ & ren - {id(p) for p in model.depth_head.parameters()})


def test_occ_resume_matches_uninterrupted(tiny_synth_data, tmp_path):
    a = train(tiny_synth_data, tmp_path / "a", synth_test_config(), _tcfg("occ", 3), progress=False)
    assert not a["interrupted"] and a["steps"] == 3
    b1 = train(tiny_synth_data, tmp_path / "b", synth_test_config(), _tcfg("occ", 3), progress=False, max_steps_now=2)
    assert b1["steps"] == 2
    with pytest.raises(ValueError, match="resume"):
        train(tiny_synth_data, tmp_path / "b", synth_test_config(), _tcfg("occ", 3), progress=False, max_steps_now=0)
    b2 = train(tiny_synth_data, tmp_path / "b", synth_test_config(), _tcfg("occ", 3), progress=False, resume=True)
    assert b2["steps"] == 3
    ra, rb = _rows(tmp_path / "a" / "log.csv"), _rows(tmp_path / "b" / "log.csv")
    assert [r["step"] for r in rb] == ["1", "2", "3"]
    assert [r["scene"] for r in ra] == [r["scene"] for r in rb]
    # same data, RNG and optimiser state after resuming -> the same losses and weights (CPU float32 kernels
    # are deterministic for a fixed thread count; 1e-5 leaves room for reduction-order effects)
    for x, y in zip(ra, rb):
        assert float(x["loss"]) == pytest.approx(float(y["loss"]), rel=1e-5)
    wa = torch.load(tmp_path / "a" / "occ.pt", weights_only=False)["model"]
    wb = torch.load(tmp_path / "b" / "occ.pt", weights_only=False)["model"]
    for k in wa:
        assert torch.allclose(wa[k].float(), wb[k].float(), rtol=1e-4, atol=1e-6), k
    assert (tmp_path / "a" / "loss.png").stat().st_size > 0
    for k in ("sem", "geo", "ce", "bev", "depth_head", "lr", "grad_norm", "sec_per_it"):
        assert k in ra[0]


@pytest.mark.slow
def test_render_stage_from_occ(tiny_synth_data, tmp_path):
    train(tiny_synth_data, tmp_path / "occ", synth_test_config(), _tcfg("occ", 1), progress=False)
    s = train(tiny_synth_data, tmp_path / "ren", None, _tcfg("render", 2), init=tmp_path / "occ" / "occ.pt",
              val_dir=tiny_synth_data, progress=False)
    assert s["steps"] == 2 and s["val"] is not None
    assert 0 < s["val"]["psnr"] < 60
    rows = _rows(tmp_path / "ren" / "log.csv")
    for k in ("l1", "perceptual", "sky", "depth", "pearson"):
        assert k in rows[0]
    assert (tmp_path / "ren" / "val_0000002.png").is_file()
    # the occupancy module did not move in stage 2
    w0 = torch.load(tmp_path / "occ" / "occ.pt", weights_only=False)["model"]
    w1 = torch.load(tmp_path / "ren" / "render.pt", weights_only=False)["model"]
    for k in w0:
        if k.split(".")[0] in OCC_MODULES:
            assert torch.equal(w0[k], w1[k]), k


def test_cli_errors_exit_2(tmp_path, tiny_synth_data, capsys):
    exe = [sys.executable, "-m", "xyzcyl", "train"]
    r = subprocess.run(exe + ["--data", str(tmp_path / "nope"), "--stage", "occ", "--out", str(tmp_path / "r")],
                       check=False, capture_output=True, text=True)
    assert r.returncode == 2 and "data" in r.stderr and "Traceback" not in r.stderr
    # the rest in this process (the same cli.main; an uncaught exception would fail the test, not exit 2)
    rc, err = _train_cli(["--data", str(tiny_synth_data), "--stage", "occ", "--out", str(tmp_path / "r"),
                         "--resume"], capsys)
    assert rc == 2 and "resume" in err
    # each bad value exits 2 naming its config field, without a traceback
    for flag, value, field in (("--targets", "0", "num_targets"), ("--camera-drop", "2", "camera_drop"),
                               ("--depth-focal-ref", "wide", "depth_focal_ref"), ("--lens-zoom", "-1", "lens_zoom"),
                               ("--lidar-input", "1.5", "lidar_input")):
        rc, err = _train_cli(["--data", str(tiny_synth_data), "--stage", "occ", "--out", str(tmp_path / "r"),
                             flag, value], capsys)
        assert rc == 2 and field in err and "Traceback" not in err, (flag, err)
    rc, err = _train_cli(["--data", str(tiny_synth_data), "--data", str(tmp_path / "nope"), "--stage", "occ",
                         "--out", str(tmp_path / "r")], capsys)
    assert rc == 2 and "nope" in err


def test_load_init_skips_ablated_modules_only():
    full = build_model(synth_test_config())
    state = full.state_dict()
    cfg = synth_test_config()
    ablated = build_model(cfg.replace(ablation=cfg.ablation.replace(volume_branch=False)))
    dropped = {k.split(".")[0] for k in state} - {k.split(".")[0] for k in ablated.state_dict()}
    assert dropped                                      # the volume modules are not in the ablated model
    load_init(ablated, state, "full.pt")
    for k, v in ablated.state_dict().items():
        assert torch.equal(v, state[k]), k
    with pytest.raises(ValueError, match="lacks"):       # the ablated model's weights cannot start the full one
        load_init(build_model(synth_test_config()), ablated.state_dict(), "ablated.pt")
    bad = dict(state)
    k = next(k for k in bad if bad[k].ndim == 2)
    bad[k] = torch.zeros(bad[k].shape[0] + 1, bad[k].shape[1])
    with pytest.raises(ValueError, match="shape"):
        load_init(build_model(synth_test_config()), bad, "bad.pt")


def test_load_init_keeps_own_init_of_untrained_modules_that_changed_shape():
    """The no-RGB ablation starts from the full model's stage-1 checkpoint: its occupancy weights load, its
    volume/pixel modules (3 fewer input channels, untrained in stage 1) keep their own initialisation."""
    cfg = synth_test_config()
    state = build_model(cfg).state_dict()
    ablated = build_model(cfg.replace(ablation=cfg.ablation.replace(rgb_path=False)))
    own = {k: v.clone() for k, v in ablated.state_dict().items()}
    with pytest.raises(ValueError, match="shape"):
        load_init(ablated, state, "full_occ.pt")
    untrained = ("pix_net", "pix_out", "pix_norm", "pix_mlp", "proj_conv", "vol_net", "geo_proj", "app_proj",
                 "geo_mlp", "app_mlp", "bg_net")
    load_init(ablated, state, "full_occ.pt", untrained)
    new = ablated.state_dict()
    for k, v in new.items():
        top = k.split(".")[0]
        if top in untrained and tuple(state[k].shape) != tuple(v.shape):
            assert torch.equal(v, own[k]), k
        else:
            assert torch.equal(v, state[k]), k
    assert any(tuple(state[k].shape) != tuple(v.shape) for k, v in new.items())


def test_cli_config_overrides(tmp_path, tiny_synth_data, capsys):
    import json

    exe = ["--data", str(tiny_synth_data), "--stage", "occ", "--steps", "1", "--quiet", "--threads", "1"]
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "a"), "--volume-selection", "ground_truth", "--max-voxels",
                         "1234", "--ablation", "no-pixel", "--voxel-size", "1.6"], capsys)
    assert rc == 0, err
    model = json.loads((tmp_path / "a" / "config.json").read_text())["model"]
    assert model["volume_selection"] == "ground_truth" and model["volume"]["max_voxels"] == 1234
    assert model["ablation"]["pixel_branch"] is False and model["grid"]["voxel_size"] == 1.6
    # without --preset the overrides apply to the --init checkpoint's config
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "b"), "--init", str(tmp_path / "a" / "occ.pt"),
                         "--max-voxels", "99"], capsys)
    assert rc == 0, err
    model = json.loads((tmp_path / "b" / "config.json").read_text())["model"]
    assert model["volume"]["max_voxels"] == 99 and model["volume_selection"] == "ground_truth"
    assert model["grid"]["voxel_size"] == 1.6
    # the issue-10 switches: no-RGB ablation, pixel lattice, placement, surface occupancy labels
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "c"), "--ablation", "no-rgb", "--pixel-upsample", "4",
                         "--placement", "cylinder_ray", "--occupancy-labels", "surface", "--voxel-size", "1.6"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "c" / "config.json").read_text())
    model = doc["model"]
    assert model["ablation"]["rgb_path"] is False and model["ablation"]["rgb_occupancy"] is True
    assert model["pixel"]["k_out"] == 4 and model["pixel"]["placement"] == "cylinder_ray"
    assert doc["train"]["data"]["occupancy_labels"] == "surface"
    assert doc["data"] == str(tiny_synth_data)
    # mixed data sets (--data repeated) and the camera drop
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "d"), "--data", str(tiny_synth_data), "--camera-drop", "0.5",
                         "--lens-zoom", "0.25"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "d" / "config.json").read_text())
    assert doc["data"] == [str(tiny_synth_data)] * 2 and doc["train"]["data"]["camera_drop"] == 0.5
    assert doc["train"]["data"]["lens_zoom"] == 0.25
    # the focal-aware depth head: on (the occ stage's encoder reads the rigs' focal_n), then off again over --init
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "e"), "--depth-focal-ref", "nuscenes"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "e" / "config.json").read_text())["model"]["backbone"]["depth_focal_ref"] == 1.0553
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "f"), "--init", str(tmp_path / "e" / "occ.pt"),
                         "--depth-focal-ref", "off"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "f" / "config.json").read_text())["model"]["backbone"]["depth_focal_ref"] is None
    # standardised backbone input over --init (no weights added: the occ checkpoint loads), inherited by a later run
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "g"), "--init", str(tmp_path / "e" / "occ.pt"),
                         "--input-norm", "standardize"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "g" / "config.json").read_text())["model"]["backbone"]["input_norm"] == "standardize"
    rc, err = _train_cli(exe + ["--out", str(tmp_path / "h"), "--init", str(tmp_path / "g" / "occ.pt")], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "h" / "config.json").read_text())["model"]["backbone"]["input_norm"] == "standardize"


def test_threads_option_sets_torch_and_numba():
    import numba
    from xyzcyl.model_export.commands.common import set_threads

    n_torch, n_numba = torch.get_num_threads(), numba.get_num_threads()
    try:
        set_threads(1)
        assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
        set_threads(10_000)                       # numba's pool is capped at its size, not an error
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
        with pytest.raises(ValueError, match="threads"):
            set_threads(0)
    finally:
        torch.set_num_threads(n_torch)
        numba.set_num_threads(n_numba)


@pytest.mark.slow
@pytest.mark.heavy
def test_overfit_one_scene_halves_the_render_loss(tiny_synth_data, tmp_path):
    """The issue's overfit check: stage render on one scene, all 12 ego-forward targets every step (so the loss
    of each step measures the same views), from random weights. Mean of the first / last 3 steps, measured on
    this scene: 0.298 -> 0.127 (ratio 0.43) at 80 steps when written; on 2026-11-25's packages 80 steps gave
    ratios of 0.48-0.54 from run to run and test order (before the thread counts were pinned here), so 120 steps
    (ratio 0.466 then). With the counts pinned, on 2026-11-29's packages the run is the same every time: 60 steps
    0.493, 80 steps 0.419 (0.2674 -> 0.1119, twice alike), 120 steps 0.349; 80 steps again (the ratio is printed by
    the assertion), 27 s less on the CI's critical path. The floor is the image L1: the 32x56 inputs reach the
    network through 4x7 feature maps, so per-pixel texture cannot be reproduced."""
    import shutil

    import numba

    data = tmp_path / "one"
    shutil.copytree(tiny_synth_data / "scene_000000", data / "scene_000000")
    # the trajectory depends on the thread counts (the order of float reductions in torch and in the renderer's
    # backward); earlier tests leave them set (a CLI test with --threads 1 sets numba's), which moved the ratio
    # from 0.46 to 0.52: pinned here to the counts of a fresh process on the two-core machine, restored after
    n_torch, n_numba = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(2)
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    cfg = synth_test_config()
    cfg = cfg.replace(volume=cfg.volume.replace(max_voxels=20000))    # all ~13k occupied 1.6 m voxels
    steps = 80
    tcfg = TrainConfig(stage="render", steps=steps, ckpt_every=steps, seed=1, depth_head_weight=0.0,
                       data=DatasetConfig(num_targets=12, voxel_size=1.6, target_scale=0.5),
                       loss=TrainLossConfig(optim=OptimConfig(lr=1e-2, warmup_steps=5, total_steps=steps,
                                                              min_lr_ratio=0.1)))
    try:
        s = train(data, tmp_path / "run", cfg, tcfg, progress=False)
    finally:
        torch.set_num_threads(n_torch)
        numba.set_num_threads(n_numba)
    assert s["steps"] == steps
    rows = _rows(tmp_path / "run" / "log.csv")
    assert {r["scene"] for r in rows} == {"scene_000000"}
    loss = [float(r["loss"]) for r in rows]                # depth_head_weight 0: the render loss alone
    first, last = sum(loss[:3]) / 3, sum(loss[-3:]) / 3
    print(f"overfit: {first:.4f} -> {last:.4f} (ratio {last / first:.3f})")
    assert last <= 0.5 * first, (first, last)
