"""Two-stage training loop of XYZCylinder (paper Sec. 3.4) over the synthetic data set.

    train(data_dir, run_dir, model_cfg, TrainConfig(stage="occ"|"render", steps=...), resume=..., init=...)

Stage "occ": backbone (its trainable part), depth head and the occupancy module (YNet_occ, CPFG projection,
occupancy and BEV heads) with L_occ, plus a depth-head log-L1 on the input cameras' ground-truth depth (our
addition: the paper uses a pre-trained depth network, none ships here).
Stage "render": everything upstream of and inside the occupancy module is frozen (backbone, occ_*, bev_*); the
depth head, volume, pixel and background modules train with the stage-2 render loss (+ the depth-head log-L1).

One optimiser step = one scene with T random target views. The scene order is a seeded permutation per epoch,
so a resumed run sees exactly the scenes the uninterrupted run would have seen.

RUN_DIR layout: config.json (model + train config), last.pt (model, optimiser, scheduler, step: written every
``ckpt_every`` steps, at the end and on Ctrl-C / SIGTERM), <stage>.pt (weights + config at the end),
log.csv (one row per step), loss.png (curves), val.csv + val_<step>.png when a validation set is given.
"""

from __future__ import annotations

import csv
import json
import signal
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from xyzcyl.common.files import atomic_file

from .config import ConfigError, ModelConfig, _Frozen
from .dataset import DatasetConfig, SceneDataset
from .losses import TrainLossConfig, build_optimizer, clip_gradients, load_lpips, occupancy_loss, render_loss

STAGES = ("occ", "render", "depth")
# stages whose checkpoints hold a whole trained model (render modules trained): eval and export take these; a
# "depth" run starts from a render checkpoint (its --init is refused otherwise) and trains only the depth head
RENDER_STAGES = ("render", "depth")
OCC_MODULES = ("backbone", "occ_net", "occ_proj", "occ_head", "bev_proj", "bev_head")


@dataclass(frozen=True)
class TrainConfig(_Frozen):
    stage: str = "occ"
    steps: int = 2000                 # optimiser steps (= scenes seen) of this stage
    ckpt_every: int = 50              # steps between checkpoints (a kill loses at most this many)
    val_every: int = 0                # steps between validation passes (0: only at the end, if a val set is given)
    val_scenes: int = 4               # validation scenes per pass
    seed: int = 0
    depth_head_weight: float = 0.1    # log-L1 of the depth head against input-camera depth; 0 disables
    data: DatasetConfig = field(default_factory=DatasetConfig)
    loss: TrainLossConfig = field(default_factory=TrainLossConfig)

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ConfigError(f"stage: must be one of {', '.join(STAGES)}, got {self.stage!r}")
        for n in ("steps", "ckpt_every", "val_scenes"):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{n}: must be a positive integer, got {v!r}")
        if isinstance(self.val_every, bool) or not isinstance(self.val_every, int) or self.val_every < 0:
            raise ConfigError(f"val_every: must be an integer >= 0, got {self.val_every!r}")
        if not self.depth_head_weight >= 0:
            raise ConfigError(f"depth_head_weight: must be >= 0, got {self.depth_head_weight!r}")


# ------------------------------------------------------------------------------------------------ model set-up


def build_model(cfg: ModelConfig) -> torch.nn.Module:
    from .model import XYZCylinder

    return XYZCylinder(cfg)


def set_stage(model: torch.nn.Module, stage: str, base_flags: dict[str, bool]) -> list[torch.nn.Parameter]:
    """requires_grad per stage (never enabling a parameter the model froze itself, e.g. the Lite0 trunk);
    returns the trainable parameters."""
    out = []
    for name, p in model.named_parameters():
        top = name.split(".", 1)[0]
        in_occ = top in OCC_MODULES or top == "depth_head"
        on = in_occ if stage == "occ" else top == "depth_head" if stage == "depth" else top not in OCC_MODULES
        p.requires_grad_(bool(on and base_flags[name]))
        if p.requires_grad:
            out.append(p)
    return out


def train_mode(model: torch.nn.Module, stage: str) -> None:
    """model.train(), with the frozen occupancy modules in eval mode during stage 2 and everything but the depth
    head in eval mode during stage depth."""
    if stage == "depth":
        model.eval()
        model.depth_head.train()
        return
    model.train()
    if stage == "render":
        for name in OCC_MODULES:
            m = getattr(model, name, None)
            if m is not None:
                m.eval()


def _resize(images: torch.Tensor, cfg: ModelConfig) -> torch.Tensor:
    """[N, 3, H, W] -> the backbone input size (bilinear, antialiased); calibration-free (lifting grids are
    normalised image coordinates)."""
    h, w = cfg.backbone.input_height, cfg.backbone.input_width
    if images.shape[-2:] == (h, w):
        return images
    return F.interpolate(images, size=(h, w), mode="bilinear", align_corners=False, antialias=True)


def encode_item(model, item: dict[str, Any]):
    """The model's encoder on an item's input images (resized to the backbone's input) with their focal lengths:
    (lifted features, depth-head depth [N, 1, h, w] metres, confidence)."""
    return model.encode_images(_resize(item["images"], model.cfg), focal=item["lifting"].get("focal_n"))


def _head_truth(pred: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, sky: torch.Tensor):
    """Ground truth [N, 1, H, W] at the depth head's resolution [N, 1, h, w] by nearest sampling, and the mask
    of valid non-sky pixels with depth > 0 there (float 0/1)."""
    size = pred.shape[-2:]
    d = F.interpolate(depth, size=size, mode="nearest")
    m = F.interpolate((valid & (sky < 0.5)).float(), size=size, mode="nearest") * (d > 0)
    return d, m


def depth_head_loss(pred: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, sky: torch.Tensor) -> torch.Tensor:
    """Mean |log D_head - log D| of the depth head [N, 1, h, w] against ground truth [N, 1, H, W] taken at the
    head's resolution by nearest sampling, over valid non-sky pixels. Log (relative) error: a metre L1 would be
    dominated by distant pixels and outweigh the render loss under the global gradient clip."""
    d, m = _head_truth(pred, depth, valid, sky)
    n = m.sum()
    if not bool(n > 0):
        return pred.sum() * 0.0
    err = (torch.log(pred.clamp_min(1e-3)) - torch.log(d.clamp_min(1e-3))).abs()
    return (err * m).sum() / n


def depth_head_abs_rel(pred: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, sky: torch.Tensor) -> float:
    """Mean |D_head - D| / D over the pixels depth_head_loss uses (NaN when there are none)."""
    d, m = _head_truth(pred, depth, valid, sky)
    n = float(m.sum())
    return float(((pred - d).abs() / d.clamp_min(1e-3) * m).sum()) / n if n > 0 else float("nan")


def target_cameras(targets: dict[str, Any]) -> list:
    from xyzcyl.runtime.camera import Camera

    return [Camera(K=np.asarray(K, np.float64), cam_to_ego=np.asarray(T, np.float64), width=targets["width"],
                   height=targets["height"]) for K, T in zip(targets["K"], targets["cam_to_ego"])]


def lidar_depth_input(model, images: torch.Tensor, item: dict[str, Any]
                      ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The depth input of an item with a simulated sweep (dataset ``lidar_input``: item["lidar_depth"]
    [N, h, w] metres, item["lidar_surface"] [N, h, w] bool), made as the runtime makes it from a real sweep
    (runtime.lidar.fuse_depth, with the depth head's own output, no gradient, in place of the first pass's
    rendered depth and the surface mask in place of its alpha): (depth [N, 1, h, w], mask [N] of ones), or
    (None, None) for an item without one."""
    lid = item.get("lidar_depth")
    if lid is None:
        return None, None
    from xyzcyl.runtime.lidar import fuse_depth

    with torch.no_grad():
        _, head, _ = model.encode_images(images, focal=item["lifting"].get("focal_n"))
    head = head[:, 0].float().cpu().numpy()
    surf = item["lidar_surface"].cpu().numpy().astype(np.float32)
    fused = np.stack([fuse_depth(lid[n].cpu().numpy(), head[n], surf[n])[0] for n in range(head.shape[0])])
    depth = torch.from_numpy(fused)[:, None].to(images.device)
    return depth, torch.ones(depth.shape[0], dtype=depth.dtype, device=images.device)


def forward_render(model, item: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Full forward + splat render + background blend for an item's targets.
    Returns rgb [T, 3, H, W] (composited), alpha [T, 1, H, W] (foreground), depth [T, 1, H, W] (foreground),
    bg [T, 3, H, W] or None, depth_head [N, 1, h, w], n_gaussians."""
    from .model import blend
    from .render_fn import render_views

    cfg = model.cfg
    inp = item["lifting"]
    images = _resize(item["images"], cfg)
    depth_in, mask_in = lidar_depth_input(model, images, item)
    out = model(images, inp, depth_in, mask_in, occ_gt=item["occupancy"] == 1)   # 255 = unknown
    rgb, alpha, depth = render_views(out["gaussians"], target_cameras(item["targets"]))  # host CPU, any device
    bg = model.background(out["app_plane"], item["targets"]["background_grid"]) if out["app_plane"] is not None \
        else None
    if bg is not None and bg.shape[-2:] != rgb.shape[-2:]:
        bg = F.interpolate(bg, size=rgb.shape[-2:], mode="bilinear", align_corners=False)
    return {"rgb": blend(rgb, alpha, bg), "alpha": alpha, "depth": depth, "bg": bg, "depth_head": out["depth"],
            "n_gaussians": int(out["gaussians"]["means"].shape[0])}


def step_loss(model, item: dict[str, Any], tcfg: TrainConfig, lpips=None) -> tuple[torch.Tensor, dict[str, float]]:
    """The stage's total loss for one scene and its unweighted terms."""
    if tcfg.stage == "depth":   # the depth head alone: no lifting, no rendering; its term at weight 1
        _, d, _ = encode_item(model, item)
        dl = depth_head_loss(d, item["depth"], item["depth_valid"], item["sky"])
        return dl, {"depth_head": float(dl.detach())}
    if tcfg.stage == "occ":
        feats, d, _ = encode_item(model, item)
        occ, bev = model.occupancy(feats, item["lifting"])
        loss, parts = occupancy_loss(occ, bev, item["occupancy"], tcfg.loss.occ, bev_target=item["bev"])
    else:
        r = forward_render(model, item)
        t = item["targets"]
        loss, parts = render_loss(r["rgb"], t["images"], r["alpha"], t["sky"], r["depth"], t["depth"],
                                  t["depth_valid"], tcfg.loss.render, lpips)
        d = r["depth_head"]
        parts["n_gaussians"] = float(r["n_gaussians"])
    if tcfg.depth_head_weight > 0 and "lidar_depth" not in item:   # with a depth input the head is not used
        dl = depth_head_loss(d, item["depth"], item["depth_valid"], item["sky"])
        loss = loss + tcfg.depth_head_weight * dl
        parts["depth_head"] = float(dl.detach())
    return loss, parts


def resolve_device(device: str | torch.device = "cpu") -> torch.device:
    """"cpu", "cuda" or "cuda:N" as a torch.device; ValueError naming `device` when it is none of these or
    CUDA is asked for but not available."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device: expected cpu, cuda or cuda:N, got {device!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected cpu, cuda or cuda:N, got {device!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device: {str(device)!r} asked for, but CUDA is not available here (torch "
                             f"{torch.__version__}, CUDA build: {torch.version.cuda or 'none'}); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device: {str(device)!r} asked for, but only {torch.cuda.device_count()} CUDA "
                             "device(s) are visible")
    return dev


def to_device(item: Any, device: torch.device) -> Any:
    """The item with every tensor (nested dicts included: targets, lifting) on `device`; other values (rig,
    numpy K / cam_to_ego, names) as they are. A no-op copy of the dicts on the tensors' own device."""
    if isinstance(item, torch.Tensor):
        return item.to(device)
    if isinstance(item, dict):
        return {k: to_device(v, device) for k, v in item.items()}
    return item


# ------------------------------------------------------------------------------------------------ checkpoints


def save_atomic(obj: Any, path: Path) -> None:
    with atomic_file(path) as f:
        torch.save(obj, f)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint: no file {str(path)!r}")
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ck, dict) or "model" not in ck or "model_cfg" not in ck:
        raise ValueError(f"checkpoint: {path} is not an xyzcyl checkpoint (no 'model' / 'model_cfg')")
    return ck


def load_init(model: torch.nn.Module, state: dict[str, torch.Tensor], where: str,
              untrained: tuple[str, ...] = ()) -> None:
    """Load a previous stage's weights. Entries of modules the model does not have (an ablated branch) are
    skipped; anything else that is missing, unexpected or of another shape is an error naming the key.
    ``untrained``: top-level modules the previous stage did not train (stage 1 leaves the render modules at
    their initialisation); where their shapes differ (e.g. the no-RGB ablation reads 3 fewer input channels)
    the model keeps its own initialisation instead."""
    own = model.state_dict()
    tops = {k.split(".", 1)[0] for k in own}
    kept = {k: v for k, v in state.items() if k.split(".", 1)[0] in tops}
    for k in list(kept):
        if k.split(".", 1)[0] in untrained and (k not in own or tuple(kept[k].shape) != tuple(own[k].shape)):
            del kept[k]
    kept.update({k: v for k, v in own.items() if k.split(".", 1)[0] in untrained and k not in kept})
    for k, v in kept.items():
        if k not in own:
            raise ValueError(f"init: {where} has {k!r}, which this model does not (another model config?)")
        if tuple(v.shape) != tuple(own[k].shape):
            raise ValueError(f"init: {where}: {k} has shape {tuple(v.shape)}, the model {tuple(own[k].shape)}")
    missing = sorted(set(own) - set(kept))
    if missing:
        raise ValueError(f"init: {where} lacks {missing[0]!r} (and {len(missing) - 1} more): not a checkpoint of "
                         "this model")
    model.load_state_dict(kept)


def scene_order(n: int, seed: int, epoch: int) -> np.ndarray:
    return np.random.default_rng((seed, 7919, epoch)).permutation(n)


# ------------------------------------------------------------------------------------------------ logging


def read_log(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def write_log(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    with atomic_file(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow(r)


def plot_losses(rows: list[dict[str, Any]], path: Path, title: str = "") -> None:
    """Loss curves (raw, faint; EMA 0.9, solid) of the total and each term, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return
    steps = np.array([float(r["step"]) for r in rows])
    skip = {"step", "epoch", "lr", "grad_norm", "sec_per_it", "wall_s", "scene", "n_gaussians"}
    keys = [k for k in rows[0] if k not in skip]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    for k in keys:
        y = np.array([float(r[k]) if r.get(k) not in (None, "") else np.nan for r in rows])
        if not np.isfinite(y).any() or np.nanmax(y) <= 0:
            continue
        ema = np.empty_like(y)
        acc = y[np.isfinite(y)][0]
        for i, v in enumerate(y):
            acc = 0.9 * acc + 0.1 * v if np.isfinite(v) else acc
            ema[i] = acc
        (line,) = ax.plot(steps, ema, label=k, lw=2 if k == "loss" else 1)
        ax.plot(steps, y, color=line.get_color(), alpha=0.2, lw=0.7)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (unweighted terms; 'loss' = weighted total)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ validation


def validate(model, ds: SceneDataset, tcfg: TrainConfig, step: int, run_dir: Path) -> dict[str, float]:
    """Stage "occ": mean occupancy IoU and BEV IoU. Stage "render": mean PSNR / SSIM / PCC over the targets of
    the first ``val_scenes`` scenes; a sheet val_<step>.png (inputs, targets, renders, depths) of the first.
    Stage "depth": the depth head's log-L1 and AbsRel on the input cameras of those scenes."""
    from . import metrics as M

    model.eval()
    dev = next(model.parameters()).device
    res: dict[str, list[float]] = {}
    sheet = None
    with torch.no_grad():
        for i in range(min(tcfg.val_scenes, len(ds))):
            item = ds.item(i, 0)            # host tensors for the metrics; the model reads a copy on its device
            x = to_device(item, dev)
            if tcfg.stage == "depth":
                d = encode_item(model, x)[1].cpu()
                res.setdefault("depth_head", []).append(float(depth_head_loss(d, item["depth"], item["depth_valid"],
                                                                              item["sky"])))
                res.setdefault("abs_rel", []).append(depth_head_abs_rel(d, item["depth"], item["depth_valid"],
                                                                        item["sky"]))
                continue
            if tcfg.stage == "occ":
                feats, _, _ = encode_item(model, x)
                occ, bev = (a.cpu() for a in model.occupancy(feats, x["lifting"]))
                occ_t = item["occupancy"].numpy()
                res.setdefault("occ_iou", []).append(M.occupancy_iou(occ.argmax(0).numpy(), occ_t == 1, occ_t == 255))
                res.setdefault("bev_iou", []).append(M.occupancy_iou(bev.argmax(0).numpy(), item["bev"].numpy()))
                continue
            r = to_device(forward_render(model, x), torch.device("cpu"))
            t = item["targets"]
            for k in range(t["images"].shape[0]):
                pred = r["rgb"][k].clamp(0, 1).permute(1, 2, 0).numpy()
                gt = t["images"][k].permute(1, 2, 0).numpy()
                res.setdefault("psnr", []).append(M.psnr(pred, gt))
                if min(gt.shape[:2]) >= 11:
                    res.setdefault("ssim", []).append(M.ssim(pred, gt))
                valid = (t["depth_valid"][k] & (t["sky"][k] < 0.5)).numpy()
                res.setdefault("pcc", []).append(M.depth_pcc(r["depth"][k, 0].numpy(), t["depth"][k].numpy(), valid))
            if sheet is None:
                sheet = _sheet(item, r)
    if sheet is not None:
        import cv2

        cv2.imwrite(str(run_dir / f"val_{step:07d}.png"), (sheet[..., ::-1] * 255).round().astype(np.uint8))
    return {k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in res.items()}


def _depth_vis(d: np.ndarray, vmax: float) -> np.ndarray:
    import cv2

    x = (np.clip(d / max(vmax, 1e-6), 0, 1) * 255).astype(np.uint8)
    c = cv2.applyColorMap(x, cv2.COLORMAP_TURBO)[..., ::-1].astype(np.float32) / 255
    c[d <= 0] = 0
    return c


def _sheet(item: dict[str, Any], r: dict[str, torch.Tensor]) -> np.ndarray:
    """Rows: inputs; targets; renders; target depth; rendered depth (each row padded to the widest)."""
    import cv2

    t = item["targets"]
    th, tw = t["images"].shape[-2:]
    inputs = [cv2.resize(a.permute(1, 2, 0).numpy(), (tw, th), interpolation=cv2.INTER_AREA) for a in item["images"]]
    vmax = float(np.percentile(t["depth"][t["depth_valid"]].numpy(), 95)) if bool(t["depth_valid"].any()) else 1.0
    rows = [inputs,
            [a.permute(1, 2, 0).numpy() for a in t["images"]],
            [a.clamp(0, 1).permute(1, 2, 0).numpy() for a in r["rgb"]],
            [_depth_vis(a.numpy(), vmax) for a in t["depth"]],
            [_depth_vis(a[0].numpy(), vmax) for a in r["depth"]]]
    width = max(len(row) for row in rows) * tw
    out = []
    for row in rows:
        line = np.concatenate(row, axis=1)
        out.append(np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0))))
    return np.clip(np.concatenate(out, axis=0), 0, 1)


# ------------------------------------------------------------------------------------------------ the loop


class _Stop(Exception):
    pass


def train(data_dir: str | Path | list[str | Path], run_dir: str | Path, model_cfg: ModelConfig | None, tcfg: TrainConfig,
          resume: bool = False, init: str | Path | None = None, val_dir: str | Path | None = None,
          progress: bool = True, max_steps_now: int | None = None,
          device: str | torch.device = "cpu") -> dict[str, Any]:
    """Run (or resume) one stage. ``model_cfg`` None: taken from ``init`` (or the resumed checkpoint).
    ``max_steps_now``: stop after this many steps in this call (checkpointed; for tests and time-boxed runs).
    ``device``: where the network, its inputs and the losses live (resolve_device); the splatting renderer
    always runs on the host CPU (render_fn.RenderViews copies across). Checkpoints load onto any device.
    Returns a summary dict (steps done, last losses, wall time, paths)."""
    from xyzcyl.common.progress import progress_bar

    dev = resolve_device(device)
    run_dir = Path(run_dir)
    last = run_dir / "last.pt"
    ck = None
    if last.is_file():
        if not resume:
            raise ValueError(f"out: {run_dir} already holds a checkpoint (last.pt); pass --resume or a new folder")
        ck = load_checkpoint(last)
        if ck["train_cfg"]["stage"] != tcfg.stage:
            raise ValueError(f"stage: {run_dir} is a {ck['train_cfg']['stage']!r} run, not {tcfg.stage!r}")
        saved_cfg = ModelConfig.from_dict(ck["model_cfg"])
        if model_cfg is not None and model_cfg != saved_cfg:
            raise ValueError(f"preset: the model config differs from the one in {last}")
        model_cfg = saved_cfg
    init_ck = None
    if init is not None and ck is None:
        init_ck = load_checkpoint(init)
        if tcfg.stage == "depth" and (init_ck.get("train_cfg") or {}).get("stage") not in ("render", "depth"):
            raise ValueError(f"init: stage depth trains the depth head alone on a trained model; {init} is a stage "
                             f"{(init_ck.get('train_cfg') or {}).get('stage')!r} checkpoint, give a stage-2 render.pt")
        if model_cfg is None:
            model_cfg = ModelConfig.from_dict(init_ck["model_cfg"])
    if model_cfg is None:
        raise ValueError("preset: no model config (give --preset or --init)")
    if tcfg.stage == "depth" and ck is None and init_ck is None:
        raise ValueError("init: stage depth trains the depth head of a trained model; give --init render.pt")
    run_dir.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(tcfg.seed)
    model = build_model(model_cfg).to(dev)
    base_flags = {n: p.requires_grad for n, p in model.named_parameters()}
    if init_ck is not None:
        untrained = ()
        if (init_ck.get("train_cfg") or {}).get("stage") == "occ":
            untrained = tuple({n.split(".", 1)[0] for n in model.state_dict()} - set(OCC_MODULES) - {"depth_head"})
        load_init(model, init_ck["model"], str(init), untrained)
    params = set_stage(model, tcfg.stage, base_flags)
    opt, sched = build_optimizer(params, tcfg.loss.optim)
    start = 0
    if ck is not None:
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        start = int(ck["step"])
        torch.set_rng_state(ck["torch_rng"])
    (run_dir / "config.json").write_text(json.dumps({"model": model_cfg.to_dict(), "train": tcfg.to_dict(),
                                                     "data": [str(d) for d in data_dir] if isinstance(data_dir, (list, tuple)) else str(data_dir), "init": None if init is None else
                                                     str(init), "device": str(dev)}, indent=1) + "\n")
    lpips = load_lpips(tcfg.loss.render) if tcfg.stage == "render" else None
    if lpips is not None:
        lpips = lpips.to(dev)
    ds = SceneDataset(data_dir, tcfg.data, model_cfg=model_cfg)
    val_ds = SceneDataset(val_dir, tcfg.data.without_augmentation(), model_cfg=model_cfg) \
        if val_dir is not None else None
    log_path = run_dir / "log.csv"
    rows = [r for r in read_log(log_path) if int(r["step"]) <= start]   # drop steps after the checkpoint
    val_rows = [r for r in read_log(run_dir / "val.csv") if int(r["step"]) <= start]
    wall0 = float(rows[-1]["wall_s"]) if rows else 0.0

    def checkpoint(step: int) -> None:
        save_atomic({"step": step, "model": model.state_dict(), "optimizer": opt.state_dict(),
                     "scheduler": sched.state_dict(), "model_cfg": model_cfg.to_dict(), "train_cfg": tcfg.to_dict(),
                     "torch_rng": torch.get_rng_state()}, last)
        write_log(log_path, rows)
        if val_rows:
            write_log(run_dir / "val.csv", val_rows)
        plot_losses(rows, run_dir / "loss.png", f"{model_cfg.name} / stage {tcfg.stage}")

    def fetch(step: int) -> dict[str, Any]:
        epoch, pos = divmod(step, len(ds))
        return to_device(ds.item(int(scene_order(len(ds), tcfg.seed, epoch)[pos]), epoch), dev)

    end = tcfg.steps if max_steps_now is None else min(tcfg.steps, start + max_steps_now)
    stop = {"flag": False}

    def on_term(signum, frame):  # SIGTERM: finish the step, checkpoint, leave
        stop["flag"] = True

    old = signal.signal(signal.SIGTERM, on_term) if _main_thread() else None
    step = start
    t_start = time.perf_counter()
    try:
        with ThreadPoolExecutor(1) as pool:
            nxt = pool.submit(fetch, step) if step < end else None
            bar = progress_bar(total=tcfg.steps, initial=start, desc=f"train {tcfg.stage}", unit="step",
                               enabled=progress, dynamic_ncols=True)
            while step < end:
                t0 = time.perf_counter()
                item = nxt.result()
                nxt = pool.submit(fetch, step + 1) if step + 1 < end else None
                train_mode(model, tcfg.stage)
                opt.zero_grad(set_to_none=True)
                loss, parts = step_loss(model, item, tcfg, lpips)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"loss is {float(loss)} at step {step} (scene {item['scene']})")
                loss.backward()
                gnorm = clip_gradients(params, tcfg.loss.optim)
                lr = opt.param_groups[0]["lr"]
                opt.step()
                sched.step()
                step += 1
                dt = time.perf_counter() - t0
                rows.append({"step": step, "epoch": (step - 1) // len(ds), "scene": item["scene"],
                             "loss": float(loss.detach()), **parts, "lr": lr, "grad_norm": gnorm,
                             "sec_per_it": dt, "wall_s": wall0 + time.perf_counter() - t_start})
                bar.update(1)
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", s_it=f"{dt:.2f}")
                if val_ds is not None and tcfg.val_every and step % tcfg.val_every == 0:
                    val_rows.append({"step": step, **validate(model, val_ds, tcfg, step, run_dir)})
                if step % tcfg.ckpt_every == 0 or step == end:
                    checkpoint(step)
                if stop["flag"]:
                    raise _Stop
            bar.close()
    except (KeyboardInterrupt, _Stop):
        checkpoint(step)
        return {"steps": step, "interrupted": True, "run_dir": str(run_dir)}
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    if step >= tcfg.steps:
        if val_ds is not None and (not val_rows or int(val_rows[-1]["step"]) != step):
            val_rows.append({"step": step, **validate(model, val_ds, tcfg, step, run_dir)})
        checkpoint(step)
        save_atomic({"model": model.state_dict(), "model_cfg": model_cfg.to_dict(), "train_cfg": tcfg.to_dict(),
                     "step": step}, run_dir / f"{tcfg.stage}.pt")
    last_row = rows[-1] if rows else {}
    return {"steps": step, "interrupted": False, "run_dir": str(run_dir), "last": last_row,
            "val": val_rows[-1] if val_rows else None, "wall_s": float(last_row.get("wall_s", 0.0))}


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()
