"""Evaluation of novel-view quality on synthetic data sets (paper Sec. 4, appendix "Evaluation Metrics").

    result = evaluate([data_dir], EvalConfig(settings=("ego-forward",), method="model"), checkpoint="render.pt")
    write_reports(result, out_dir)          # <tag>.json (per-view rows + aggregate) and <tag>.md (table)

Methods:
- ``model``: the network of a stage-2 checkpoint (its config, ablation switches included, comes from the
  checkpoint). One forward pass per scene (no gradients), the Gaussians rendered with the runtime renderer at
  every target view of the setting, the background network's image blended behind (I = I_fg + (1 - A) I_bg).
  Voxels are selected from the predicted occupancy (the paper's inference), or from the ground truth with
  ``occupancy="ground-truth"`` (labelled in the reports).
- ``unproject`` / ``unproject-gt-depth``: the pixel-unprojection ("2.5D") baseline. Every input pixel becomes
  one isotropic Gaussian at its depth: the checkpoint's depth head (bilinearly upsampled to the input
  resolution) or, for the oracle, the ground-truth input depth (sky pixels, which have no depth, get no
  Gaussian). sigma = (depth / sqrt(fx fy)) / sqrt(12): the standard deviation of the pixel's square footprint;
  opacity 0.99; colour = the pixel's RGB as the SH DC term. Rendered over black: the baseline has no background model, so sky it does not cover is black.

Metrics per target view (``metrics.py``): PSNR, SSIM (rendered image clipped to [0, 1]), ``psnr_fg`` (PSNR over
the target's non-sky pixels, sky < 0.5), ``psnr_seen`` (PSNR over the non-sky pixels whose surface an input
camera sees, ``metrics.seen_by_inputs`` with the ground-truth depths; ``seen_frac``: their share of the non-sky
pixels), ``colour_err`` (mean colour error over all pixels: a grey blur of a
coloured scene scores badly), depth PCC over the pixels whose ground-truth depth is in (0, ``pcc_max_depth``]
and not sky (the training's depth-validity rule), LPIPS only with local weights (otherwise ``null`` and the
reason). Aggregates are means over views per (setting, rig); views with an undefined value (PCC: fewer than 2
valid pixels, constant map; PSNR: an exact copy; PSNR fg: no non-sky pixel) are counted, not hidden.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import ConfigError, _Frozen

METHODS = ("model", "unproject", "unproject-gt-depth")
OCCUPANCY = ("predicted", "ground-truth")
SH_C0 = 0.28209479177387814
ALL_TARGETS = 1 << 30      # DatasetConfig.num_targets that keeps every target view of a setting
# baseline sigma in units of the pixel footprint depth / f: the standard deviation of a uniform pixel square
# (1 / sqrt(12)), so a Gaussian has the second moment of the pixel it replaces (docs/training.md)
UNPROJECT_SCALE = 1 / math.sqrt(12)


class EvalError(ValueError):
    """Bad evaluation input (checkpoint, data set, option); the message names the field."""


@dataclass(frozen=True)
class EvalConfig(_Frozen):
    settings: tuple[str, ...] = ("ego-forward",)
    method: str = "model"                 # model | unproject | unproject-gt-depth
    occupancy: str = "predicted"          # voxel selection of the model: predicted (paper) | ground-truth (oracle)
    rig: str | None = None                # only data sets generated with this rig (None: any; label from index.json)
    max_scenes: int | None = None         # first N scenes of each data set (None: all)
    pcc_max_depth: float = 80.0           # metres; PCC over gt depth in (0, this] (= the training's max_depth)
    unproject_scale: float = UNPROJECT_SCALE  # baseline sigma = scale * depth / sqrt(fx fy)
    unproject_opacity: float = 0.99       # baseline opacity
    lpips_backbone_path: str | None = None
    lpips_lin_path: str | None = None
    lpips_net: str = "vgg"
    sheet_scenes: int = 0                 # first view of the first N scenes per data set and setting -> sheet

    def __post_init__(self):
        from .dataset import SETTINGS

        if not self.settings:
            raise ConfigError("setting: at least one setting is needed")
        for s in self.settings:
            if s not in SETTINGS:
                raise ConfigError(f"setting: must be one of {', '.join(SETTINGS)}, got {s!r}")
        if self.method not in METHODS:
            raise ConfigError(f"method: must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.occupancy not in OCCUPANCY:
            raise ConfigError(f"occupancy: must be one of {', '.join(OCCUPANCY)}, got {self.occupancy!r}")
        if self.max_scenes is not None and (isinstance(self.max_scenes, bool) or not isinstance(self.max_scenes, int)
                                            or self.max_scenes < 1):
            raise ConfigError(f"max_scenes: must be a positive integer, got {self.max_scenes!r}")
        for n in ("pcc_max_depth", "unproject_scale"):
            if not (math.isfinite(getattr(self, n)) and getattr(self, n) > 0):
                raise ConfigError(f"{n}: must be a finite number > 0, got {getattr(self, n)!r}")
        if not 0 < self.unproject_opacity < 1:
            raise ConfigError(f"unproject_opacity: must be in (0, 1), got {self.unproject_opacity!r}")
        if self.lpips_net not in ("vgg", "alex"):
            raise ConfigError(f"lpips_net: must be vgg or alex, got {self.lpips_net!r}")
        if isinstance(self.sheet_scenes, bool) or not isinstance(self.sheet_scenes, int) or self.sheet_scenes < 0:
            raise ConfigError(f"sheet_scenes: must be an integer >= 0, got {self.sheet_scenes!r}")


# ------------------------------------------------------------------------------------------------ the baseline


def unproject_gaussians(images: np.ndarray, depth: np.ndarray, K: np.ndarray, cam_to_ego: np.ndarray,
                        scale: float = UNPROJECT_SCALE, opacity: float = 0.99):
    """Pixel unprojection: one isotropic Gaussian per input pixel with depth > 0.

    images: [N, H, W, 3] float 0..1; depth: [N, H, W] metres along the optical axis (<= 0 or non-finite: no
    Gaussian); K: [N, 3, 3] pixels; cam_to_ego: [N, 4, 4] OpenCV camera -> ego, metres.
    Pixel (u, v) (integer pixel centres, the data set's convention) with depth z goes to the ego point
    cam_to_ego @ [z inv(K) [u, v, 1], 1]; sigma = scale * z / sqrt(fx fy) metres; opacity logit = logit(opacity);
    SH DC = (rgb - 0.5) / SH_C0 (the renderer returns SH_C0 dc + 0.5 = rgb). Returns runtime Gaussians (float32)."""
    from xyzcyl.runtime.render import Gaussians

    images = np.asarray(images, np.float64)
    depth = np.asarray(depth, np.float64)
    n, h, w = depth.shape
    if images.shape != (n, h, w, 3):
        raise ValueError(f"images: expected shape {[n, h, w, 3]}, got {list(images.shape)}")
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], -1)                               # [H, W, 3]
    means, sig, cols = [], [], []
    for k in range(n):
        z = depth[k]
        keep = np.isfinite(z) & (z > 0)
        rays = pix[keep] @ np.linalg.inv(K[k]).T                              # [P, 3], z component 1
        p_cam = rays * z[keep][:, None]
        means.append(p_cam @ cam_to_ego[k][:3, :3].T + cam_to_ego[k][:3, 3])
        sig.append(scale * z[keep] / math.sqrt(K[k][0, 0] * K[k][1, 1]))
        cols.append(images[k][keep])
    m = np.concatenate(means).astype(np.float32)
    s = np.concatenate(sig)
    c = np.concatenate(cols)
    g = len(m)
    quats = np.zeros((g, 4), np.float32)
    quats[:, 0] = 1.0
    return Gaussians(m, quats, np.repeat(np.log(s)[:, None], 3, 1).astype(np.float32),
                     np.full(g, math.log(opacity / (1 - opacity)), np.float32),
                     ((c - 0.5) / SH_C0)[:, None, :].astype(np.float32))


def _native_depth_head(model, item: dict[str, Any]) -> np.ndarray:
    """The checkpoint's depth head at the input resolution: [N, H, W] metres (bilinear upsampling)."""
    import torch
    import torch.nn.functional as F
    from xyzcyl.runtime.lifting import focal_n

    from .train import _resize

    with torch.no_grad():
        # the rig's focal lengths (the focal-aware head needs them; the baseline's items carry no lifting inputs)
        focal = torch.from_numpy(focal_n(item["rig"]))
        _, d, _ = model.encode_images(_resize(item["images"], model.cfg), focal=focal)
        d = F.interpolate(d, size=item["images"].shape[-2:], mode="bilinear", align_corners=False)
    return d[:, 0].numpy()


# ------------------------------------------------------------------------------------------------ rendering


def _cameras(item: dict[str, Any]) -> list:
    from .train import target_cameras

    return target_cameras(item["targets"])


def model_views(model, item: dict[str, Any], occupancy: str = "predicted") -> Iterator[tuple[np.ndarray, np.ndarray, int]]:
    """Per target view of ``item``: (rgb [H, W, 3] composited over the background network's image, foreground
    depth [H, W] metres (0 where no Gaussian), number of Gaussians)."""
    import torch
    import torch.nn.functional as F
    from xyzcyl.runtime.render import Gaussians, render

    from .model import GAUSSIAN_KEYS
    from .train import _resize

    with torch.no_grad():   # never across a yield: grad mode is thread state the caller would inherit
        idx = None   # predicted: the occupancy head decides, whatever selection the model was trained with
        if occupancy == "ground-truth" and model.use_volume:
            idx = model.select_voxels(None, item["occupancy"] == 1, source="ground_truth")
        out = model(_resize(item["images"], model.cfg), item["lifting"], voxel_idx=idx)
    g = Gaussians(*(out["gaussians"][k].float().numpy() for k in GAUSSIAN_KEYS))
    grids = item["targets"]["background_grid"]
    for k, cam in enumerate(_cameras(item)):
        r = render(g, cam)
        rgb = r.rgb
        if out["app_plane"] is not None:
            with torch.no_grad():
                bg = model.background(out["app_plane"], grids[k:k + 1])
            if bg is not None:
                if bg.shape[-2:] != rgb.shape[:2]:
                    bg = F.interpolate(bg, size=rgb.shape[:2], mode="bilinear", align_corners=False)
                rgb = rgb + (1 - r.alpha[..., None]) * bg[0].permute(1, 2, 0).numpy()
        yield rgb, r.depth, len(g)


def unproject_views(item: dict[str, Any], depth: np.ndarray, cfg: EvalConfig
                    ) -> Iterator[tuple[np.ndarray, np.ndarray, int]]:
    """Per target view: (rgb [H, W, 3] over black, depth [H, W], number of Gaussians) of the baseline built
    from the input images and ``depth`` [N, H, W] metres."""
    from xyzcyl.runtime.render import render

    rig = item["rig"]
    g = unproject_gaussians(item["images"].permute(0, 2, 3, 1).numpy(), depth,
                            np.stack([c.K for c in rig.cameras]), np.stack([c.cam_to_ego for c in rig.cameras]),
                            cfg.unproject_scale, cfg.unproject_opacity)
    for cam in _cameras(item):
        r = render(g, cam)
        yield r.rgb, r.depth, len(g)


# ------------------------------------------------------------------------------------------------ the driver


def load_eval_model(checkpoint: str | Path, need_render_stage: bool):
    """(model in eval mode, checkpoint dict) from a training checkpoint; ``need_render_stage``: refuse a
    stage-1 (occ) checkpoint, whose render modules are untrained (a stage-2 or stage-depth one is taken)."""
    from .config import ModelConfig
    from .train import RENDER_STAGES, build_model, load_checkpoint

    try:
        ck = load_checkpoint(checkpoint)
    except (FileNotFoundError, ValueError) as e:
        raise EvalError(str(e)) from None
    stage = (ck.get("train_cfg") or {}).get("stage")
    if need_render_stage and stage not in RENDER_STAGES:
        raise EvalError(f"checkpoint: {checkpoint} is a stage {stage!r} checkpoint; the model needs a stage-2 "
                        "(render) checkpoint such as RUN/render.pt")
    model = build_model(ModelConfig.from_dict(ck["model_cfg"]))
    model.load_state_dict(ck["model"])
    model.eval()
    return model, ck


def data_rig(root: Path) -> str | None:
    """The rig a synthetic data set was generated with (index.json config.rig; a rig-file path gives the file's
    name without .json, or its folder's name for a file named rig.json), or None without index.json."""
    p = Path(root) / "index.json"
    if not p.is_file():
        return None
    try:
        rig = json.loads(p.read_text()).get("config", {}).get("rig")
    except json.JSONDecodeError as e:
        raise EvalError(f"data: {p} is not valid JSON ({e})") from None
    if not isinstance(rig, str):
        return None
    if rig.endswith(".json"):   # a rig file: its name (ring8.json -> ring8); a generic rig.json: its folder's
        path = Path(rig)
        return (path.parent.name if path.stem == "rig" else path.stem) or rig
    return rig


def _voxel_size(root: Path, model_cfg) -> float:
    """The model grid's voxel size, or (no model) the first grid stored in the first scene's occupancy.npz."""
    if model_cfg is not None:
        return float(model_cfg.grid.voxel_size)
    from .dataset import list_scenes

    with np.load(list_scenes(root)[0] / "occupancy.npz") as z:
        tags = sorted(k[len("semantic_"):] for k in z.files if k.startswith("semantic_"))
    if not tags:
        raise EvalError(f"data: {root} has no occupancy grid in occupancy.npz")
    return float(tags[0].replace("p", "."))


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def method_label(cfg: EvalConfig, model_cfg=None) -> str:
    """Row label: the method, the model's ablation switches that are off, and oracle choices."""
    if cfg.method == "unproject":
        return "unproject (depth head)"
    if cfg.method == "unproject-gt-depth":
        return "unproject (GT depth, oracle)"
    off = [k for k, v in model_cfg.ablation.to_dict().items() if v is False] if model_cfg is not None else []
    label = "XYZCylinder" + (f" ({model_cfg.name}" + "".join(f", no {k}" for k in off) + ")"
                             if model_cfg is not None else "")
    return label + (", GT occupancy (oracle)" if cfg.occupancy == "ground-truth" else "")


def evaluate(data_dirs: Sequence[str | Path], cfg: EvalConfig, checkpoint: str | Path | None = None,
             progress: bool = True, sheet: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Evaluate ``cfg.method`` on every scene (up to ``max_scenes``) of each data set and every target view
    of each setting. Returns {"method", "label", "checkpoint", "config", "lpips_unavailable", "views": [...],
    "aggregate": [...]} (JSON-ready: NaN / inf become null). ``sheet``: a list that receives, for the first
    ``cfg.sheet_scenes`` scenes of each data set and setting, their first view as {"title", "gt", "pred",
    "gt_depth", "depth", "psnr"} (images [H, W, 3] 0..1, depths [H, W] metres; gt_depth 0 outside the PCC's
    pixels) for ``write_sheet``."""
    from xyzcyl.common.progress import progress_bar

    from . import metrics as M
    from .dataset import DatasetConfig, SceneDataset

    model = ck = None
    if cfg.method in ("model", "unproject"):
        if checkpoint is None:
            raise EvalError(f"checkpoint: method {cfg.method!r} needs --checkpoint")
        model, ck = load_eval_model(checkpoint, need_render_stage=cfg.method == "model")
    model_cfg = model.cfg if model is not None else None
    lp_reason = M.lpips(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), None, None).reason \
        if cfg.lpips_backbone_path is None or cfg.lpips_lin_path is None else None

    jobs = []
    for root in data_dirs:
        root = Path(root)
        if not root.is_dir():
            raise EvalError(f"data: {root} is not a folder")
        rig = data_rig(root)
        if cfg.rig is not None and rig is not None and rig != cfg.rig:
            raise EvalError(f"rig: data set {root} was generated with rig {rig!r}, not {cfg.rig!r}")
        rig = rig or cfg.rig or "unknown"
        for setting in cfg.settings:
            # max_depth huge: the oracle unprojects every non-sky pixel; the PCC applies pcc_max_depth itself
            dcfg = DatasetConfig(setting=setting, num_targets=ALL_TARGETS, voxel_size=_voxel_size(root, model_cfg if cfg.method == "model" else None),
                                 max_depth=1e12)
            ds = SceneDataset(root, dcfg, model_cfg=model_cfg if cfg.method == "model" else None)
            n = len(ds) if cfg.max_scenes is None else min(cfg.max_scenes, len(ds))
            jobs.append((root, rig, setting, ds, n))

    rows: list[dict[str, Any]] = []
    bar = progress_bar(total=sum(j[4] for j in jobs), desc=f"eval {cfg.method}", unit="scene", enabled=progress,
                       dynamic_ncols=True)
    for root, rig, setting, ds, n in jobs:
        for i in range(n):
            item = ds.item(i, 0)
            t = item["targets"]
            if cfg.method == "model":
                views = model_views(model, item, cfg.occupancy)
            elif cfg.method == "unproject":
                views = unproject_views(item, _native_depth_head(model, item), cfg)
            else:
                views = unproject_views(item, item["depth"][:, 0].numpy(), cfg)
            in_depth = item["depth"][:, 0].numpy()
            for k, (rgb, depth, n_g) in enumerate(views):
                pred = np.clip(rgb, 0, 1)
                gt = t["images"][k].permute(1, 2, 0).numpy()
                gd = t["depth"][k].numpy()
                fg = t["sky"][k].numpy() < 0.5
                valid = (gd > 0) & (gd <= cfg.pcc_max_depth) & fg
                seen = fg & M.seen_by_inputs(gd, t["K"][k], t["cam_to_ego"][k], in_depth, item["rig"].cameras)
                lp = M.lpips(pred, gt, cfg.lpips_backbone_path, cfg.lpips_lin_path, cfg.lpips_net)
                if lp.value is None and lp_reason is None:
                    lp_reason = lp.reason
                psnr = _finite(M.psnr(pred, gt))
                if sheet is not None and k == 0 and i < cfg.sheet_scenes:
                    sheet.append({"title": f"{setting} {item['scene']}", "gt": gt, "pred": pred,
                                  "gt_depth": np.where(valid, gd, 0), "depth": depth, "psnr": psnr})
                rows.append({"data": str(root), "rig": rig, "setting": setting, "scene": item["scene"],
                             "view": t["names"][k], "psnr": psnr,
                             "psnr_inf": bool(np.array_equal(pred, gt)),
                             "psnr_fg": _finite(M.psnr_masked(pred, gt, fg)),
                             "psnr_fg_inf": bool(fg.any() and np.array_equal(pred[fg], gt[fg])),
                             "psnr_seen": _finite(M.psnr_masked(pred, gt, seen)),
                             "seen_frac": float(seen.sum() / fg.sum()) if fg.any() else None,
                             "colour_err": _finite(M.mean_colour_error(pred, gt)),
                             "ssim": M.ssim(pred, gt) if min(gt.shape[:2]) >= 11 else None,
                             "pcc": _finite(M.depth_pcc(depth, gd, valid)), "pcc_pixels": int(valid.sum()),
                             "lpips": lp.value, "n_gaussians": int(n_g)})
            bar.update(1)
            done = [r["psnr"] for r in rows if r["psnr"] is not None]
            bar.set_postfix(psnr=f"{np.mean(done):.2f}" if done else "-")
    bar.close()
    return {"method": cfg.method, "label": method_label(cfg, model_cfg),
            "checkpoint": None if checkpoint is None else str(checkpoint),
            "checkpoint_step": None if ck is None else ck.get("step"),
            "model_config": None if model_cfg is None else model_cfg.to_dict(),
            "config": cfg.to_dict(), "lpips_unavailable": lp_reason,
            "background": "none: rendered over black" if cfg.method != "model" or model_cfg is None or
            not model_cfg.ablation.separate_background else "background network (ZNet_bg)",
            "views": rows, "aggregate": aggregate(rows)}


# per-view columns averaged by ``aggregate`` (each with a ``<key>_undefined`` count)
AGGREGATED = ("psnr", "psnr_fg", "psnr_seen", "seen_frac", "ssim", "lpips", "pcc", "colour_err")
# Markdown names of the columns whose undefined views the report notes
_NAMES = {"psnr": "PSNR", "psnr_fg": "PSNR fg", "psnr_seen": "PSNR seen", "ssim": "SSIM", "pcc": "PCC",
          "colour_err": "colour error"}


def aggregate(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Means over views per (setting, rig). PSNR of an identical view (inf) counts as undefined and is
    reported in ``psnr_undefined``; PSNR fg (inf, or no non-sky pixel) in ``psnr_fg_undefined``; PCC likewise
    in ``pcc_undefined``; SSIM is undefined below 11 px."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["setting"], r["rig"]), []).append(r)
    out = []
    for (setting, rig), rs in groups.items():
        def mean(key, rs=rs):
            v = [r[key] for r in rs if r[key] is not None]
            return (float(np.mean(v)) if v else None), len(rs) - len(v)

        a = {"setting": setting, "rig": rig, "scenes": len({(r["data"], r["scene"]) for r in rs}),
             "views": len(rs)}
        means = {key: mean(key) for key in AGGREGATED}
        a.update({key: m for key, (m, _) in means.items()})
        a.update({f"{key}_undefined": u for key, (_, u) in means.items()})
        out.append(a)
    return out


# ------------------------------------------------------------------------------------------------ reports


def _fmt(v: float | None, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


_TABLE_HEAD = (("| method | setting | rig | scenes | views | PSNR ↑ | PSNR fg ↑ | PSNR seen ↑ | seen | SSIM ↑ "
                "| LPIPS ↓ | PCC ↑ | colour err ↓ |"),
               "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")


def _table_row(label: str, a: dict[str, Any]) -> str:
    """One table row; reports written before PSNR fg, PSNR seen and colour error existed show n/a for them."""
    seen = a.get("seen_frac")
    return (f"| {label} | {a['setting']} | {a['rig']} | {a['scenes']} | {a['views']} | {_fmt(a['psnr'], 2)} | "
            f"{_fmt(a.get('psnr_fg'), 2)} | {_fmt(a.get('psnr_seen'), 2)} | "
            f"{'n/a' if seen is None else f'{100 * seen:.0f} %'} | {_fmt(a['ssim'], 3)} | {_fmt(a['lpips'], 3)} | {_fmt(a['pcc'], 3)} | "
            f"{_fmt(a.get('colour_err'), 4)} |")


def markdown(result: dict[str, Any]) -> str:
    """The Markdown table (one row per setting and rig) with notes on what is unavailable or oracle."""
    lines = [f"# Evaluation: {result['label']}", ""]
    if result["checkpoint"]:
        lines.append(f"Checkpoint: `{result['checkpoint']}` (step {result['checkpoint_step']})")
    lines.append(f"Background: {result['background']}.")
    lines += ["", *_TABLE_HEAD]
    lines += [_table_row(result["label"], a) for a in result["aggregate"]]
    lines.append("")
    if result["lpips_unavailable"]:
        lines.append(f"LPIPS: n/a. {result['lpips_unavailable']}.")
    for a in result["aggregate"]:
        for key, name in _NAMES.items():
            if a.get(f"{key}_undefined"):
                lines.append(f"{a['setting']} / {a['rig']}: {name} undefined for {a[f'{key}_undefined']} of "
                             f"{a['views']} views (left out of the mean).")
    lines.append(f"PCC over ground-truth depth in (0, {result['config']['pcc_max_depth']:g}] m, sky excluded.")
    lines.append("PSNR fg: PSNR over the target's non-sky pixels. PSNR seen: over the non-sky pixels whose "
                 "surface an input camera sees (its depth agrees; the rest is space no camera of the rig saw: a "
                 "blind sector, the ego car); seen: their share of the non-sky pixels. Colour err: mean over R, G, B of |mean colour of "
                 "the render - mean colour of the target| over all pixels, in [0, 1] intensity.")
    return "\n".join(lines) + "\n"


def summary_markdown(results: list[dict[str, Any]]) -> str:
    """One table over several reports (e.g. a model, its ablations and the baselines): a row per report and
    (setting, rig), grouped by setting in the order first seen, then by report in the given order."""
    rows = [(a, r) for r in results for a in r["aggregate"]]
    keys = list(dict.fromkeys((a["setting"], a["rig"]) for a, _ in rows))
    lines = list(_TABLE_HEAD)
    for key in keys:
        lines += [_table_row(r["label"], a) for a, r in rows if (a["setting"], a["rig"]) == key]
    return "\n".join(lines) + "\n"


def report_tag(result: dict[str, Any]) -> str:
    tag = result["method"]
    mc = result.get("model_config")
    if result["method"] == "model" and mc is not None:
        tag += "".join(f"-no-{k.replace('_', '-')}" for k, v in mc["ablation"].items() if v is False)
        if result["config"]["occupancy"] == "ground-truth":
            tag += "-gt-occupancy"
    return tag + "_" + "+".join(result["config"]["settings"])


def put_label(img: np.ndarray, text: str, y: int) -> None:
    """Write ``text`` (white on a black outline, readable on any background) into a uint8 BGR image, in place;
    ``y`` is the baseline row."""
    import cv2

    cv2.putText(img, text, (3, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (3, y), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)


def write_sheet(tiles: list[dict[str, Any]], path: str | Path) -> Path:
    """A picture of ``evaluate(..., sheet=tiles)``: one column per tile; rows: ground truth, render (with its
    PSNR), ground-truth depth, rendered depth (turbo colour map, 0 to the 95th percentile of the column's
    ground-truth depth; black = no depth). Tiles of different sizes are padded to the largest."""
    import cv2

    from .train import _depth_vis

    h = max(t["gt"].shape[0] for t in tiles)
    w = max(t["gt"].shape[1] for t in tiles)
    cols = []
    for t in tiles:
        gd = t["gt_depth"]
        vmax = float(np.percentile(gd[gd > 0], 95)) if (gd > 0).any() else 1.0
        col = [t["gt"], np.clip(t["pred"], 0, 1), _depth_vis(gd, vmax), _depth_vis(t["depth"], vmax)]
        col = [np.pad(a.astype(np.float32), ((0, h - a.shape[0]), (0, w - a.shape[1]), (0, 0))) for a in col]
        img = (np.concatenate(col, axis=0)[..., ::-1] * 255).round().astype(np.uint8).copy()
        psnr = "n/a" if t["psnr"] is None else f"{t['psnr']:.1f} dB"
        put_label(img, t["title"], 12)
        put_label(img, f"render {psnr}", h + 12)
        cols.append(img)
    path = Path(path)
    if not cv2.imwrite(str(path), np.concatenate(cols, axis=1)):
        raise OSError(f"sheet: could not write {path}")
    return path


def write_reports(result: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """Write <tag>.json and <tag>.md into ``out_dir`` (created); returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tag = report_tag(result)
    jp, mp = out / f"{tag}.json", out / f"{tag}.md"
    jp.write_text(json.dumps(result, indent=1, allow_nan=False) + "\n")
    mp.write_text(markdown(result))
    return jp, mp
