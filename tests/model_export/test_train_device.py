"""`xyzcyl train --device`: the network on a torch device, the numba renderer on the host CPU.

CPU here: the device plumbing must leave the CPU losses unchanged, the render Function must hand each gradient
back on its input's device and dtype, and asking for CUDA where there is none must exit 2 naming `device`.
The CUDA tests run only where a GPU is visible."""

import csv
import json

import numpy as np
import pytest
import torch
from xyzcyl.cli import main
from xyzcyl.model_export.dataset import DatasetConfig, SceneDataset
from xyzcyl.model_export.losses import OptimConfig, TrainLossConfig
from xyzcyl.model_export.render_fn import KEYS, render_views
from xyzcyl.model_export.train import (
    TrainConfig,
    build_model,
    resolve_device,
    scene_order,
    set_stage,
    step_loss,
    to_device,
    train,
    train_mode,
)
from xyzcyl.runtime.camera import Camera
from xyzcyl.testing.model import synth_test_config

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/model_export/conftest.py

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _tcfg(stage, steps):
    return TrainConfig(stage=stage, steps=steps, ckpt_every=2, val_scenes=1, seed=1,
                       data=DatasetConfig(num_targets=2, voxel_size=1.6, flip_prob=0.5, brightness=0.1),
                       loss=TrainLossConfig(optim=OptimConfig(lr=1e-3, warmup_steps=1, total_steps=steps)))


def _losses(run):
    with open(run / "log.csv", newline="") as f:
        return [float(r["loss"]) for r in csv.DictReader(f)]


def _gaussians(dtypes, device="cpu", n=5):
    g = torch.Generator().manual_seed(0)
    means = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) - 0.5,
                         4 + torch.rand(n, generator=g)], 1)
    raw = {"means": means, "quats": torch.tensor([1.0, 0, 0, 0]) + 0.2 * torch.randn(n, 4, generator=g),
           "log_scales": torch.full((n, 3), -1.5) + 0.2 * torch.randn(n, 3, generator=g),
           "opacity_logits": 0.5 * torch.randn(n, generator=g), "sh": 0.5 * torch.randn(n, 1, 3, generator=g)}
    return {k: raw[k].to(device=device, dtype=dtypes[k]).requires_grad_(True) for k in KEYS}


def _render_grads(g):
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    rgb, alpha, depth = render_views(g, [Camera(K=K, cam_to_ego=np.eye(4), width=32, height=24)])
    (rgb.sum() + alpha.sum() + 0.1 * depth.sum()).backward()
    return rgb


def test_resolve_device(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu") == resolve_device(torch.device("cpu"))
    for bad in ("gpu", "tpu:0", ""):
        with pytest.raises(ValueError, match="^device: expected cpu, cuda"):
            resolve_device(bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="^device: 'cuda' asked for, but CUDA is not available"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="^device: 'cuda:1'"):
        resolve_device("cuda:1")


def test_to_device_moves_tensors_only():
    item = {"images": torch.zeros(2, 3, 4, 4), "rig": object(), "targets": {"K": np.eye(3), "names": ["a"],
                                                                          "depth": torch.ones(1, 4, 4)},
            "lifting": {"grid": torch.zeros(3)}}
    moved = to_device(item, torch.device("cpu"))
    assert moved is not item and moved["rig"] is item["rig"] and moved["targets"]["K"] is item["targets"]["K"]
    assert moved["targets"]["names"] == ["a"] and moved["lifting"]["grid"].device.type == "cpu"
    assert torch.equal(moved["targets"]["depth"], item["targets"]["depth"])


def test_render_function_gradients_follow_each_input_dtype():
    dtypes = {"means": torch.float32, "quats": torch.float64, "log_scales": torch.float32,
              "opacity_logits": torch.float32, "sh": torch.float64}
    g = _gaussians(dtypes)
    rgb = _render_grads(g)
    assert rgb.dtype == torch.float32 and rgb.device.type == "cpu"      # the images follow the means
    for k in KEYS:
        assert g[k].grad is not None and g[k].grad.dtype == dtypes[k] and g[k].grad.device == g[k].device, k
        assert g[k].grad.shape == g[k].shape and bool(torch.isfinite(g[k].grad).all()), k
    assert float(g["means"].grad.abs().sum()) > 0


def test_cli_cuda_without_cuda_exits_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    rc = main(["train", "--data", str(tmp_path), "--stage", "occ", "--out", str(tmp_path / "run"),
               "--device", "cuda", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("xyzcyl train: device:") and "CUDA is not available" in err
    assert not (tmp_path / "run").exists()


def test_cpu_device_gives_the_plain_cpu_losses(tiny_synth_data, tmp_path):
    """train(device="cpu") = train() = the loss computed by hand without any device plumbing."""
    cfg, tcfg = synth_test_config(), _tcfg("occ", 2)
    train(tiny_synth_data, tmp_path / "default", cfg, tcfg, progress=False)
    train(tiny_synth_data, tmp_path / "cpu", cfg, tcfg, progress=False, device="cpu")
    assert _losses(tmp_path / "cpu") == _losses(tmp_path / "default")
    assert json.loads((tmp_path / "cpu" / "config.json").read_text())["device"] == "cpu"
    torch.manual_seed(tcfg.seed)
    model = build_model(cfg)
    set_stage(model, "occ", {n: p.requires_grad for n, p in model.named_parameters()})
    ds = SceneDataset(tiny_synth_data, tcfg.data, model_cfg=cfg)
    item = ds.item(int(scene_order(len(ds), tcfg.seed, 0)[0]), 0)
    train_mode(model, "occ")
    loss, _ = step_loss(model, item, tcfg)
    assert float(loss.detach()) == _losses(tmp_path / "cpu")[0]
    # stage render (the host renderer inside): the moved copy gives the same loss
    rtcfg = _tcfg("render", 1)
    model.eval()
    with torch.no_grad():
        a, _ = step_loss(model, item, rtcfg)
        b, _ = step_loss(model, to_device(item, torch.device("cpu")), rtcfg)
    assert float(a) == float(b) and np.isfinite(float(a))


@cuda
def test_render_function_on_cuda_returns_cuda_gradients():
    dtypes = dict.fromkeys(KEYS, torch.float32)
    g = _gaussians(dtypes, device="cuda")
    rgb = _render_grads(g)
    assert rgb.device.type == "cuda"
    ref = _gaussians(dtypes)
    _render_grads(ref)
    for k in KEYS:
        assert g[k].grad.device == g[k].device and g[k].grad.dtype == torch.float32, k
        torch.testing.assert_close(g[k].grad.cpu(), ref[k].grad, rtol=1e-5, atol=1e-6)


@cuda
def test_train_on_cuda_matches_cpu(tiny_synth_data, tmp_path):
    cfg, tcfg = synth_test_config(), _tcfg("occ", 2)
    train(tiny_synth_data, tmp_path / "cpu", cfg, tcfg, progress=False, device="cpu")
    train(tiny_synth_data, tmp_path / "cuda", cfg, tcfg, progress=False, device="cuda")
    assert _losses(tmp_path / "cuda") == pytest.approx(_losses(tmp_path / "cpu"), rel=2e-2)  # TF32 convs
    ck = torch.load(tmp_path / "cuda" / "last.pt", map_location="cpu", weights_only=False)
    assert ck["step"] == 2
    rt = _tcfg("render", 1)
    s = train(tiny_synth_data, tmp_path / "ren", None, rt, init=tmp_path / "cuda" / "occ.pt",
              val_dir=tiny_synth_data, progress=False, device="cuda")
    assert s["steps"] == 1 and np.isfinite(s["val"]["psnr"])
