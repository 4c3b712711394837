"""Side-by-side renders of the run's models and baselines on validation scenes (docs/results.md).

    .venv/bin/python docs/runs/cpu_2026-11-22/compare.py runs/cpu1 data/val docs/runs/cpu_2026-11-22/compare.jpg

Columns: the first ego-forward and the first two ego-inward targets of each scene given by --scenes (default
0 and 1), at full size. Rows: ground truth, then each method exactly as `xyzcyl eval` renders it
(evaluate.model_views / unproject_views), each tile labelled with its PSNR.
"""

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch
from xyzcyl.model_export import metrics as M
from xyzcyl.model_export.dataset import DatasetConfig, SceneDataset
from xyzcyl.model_export.evaluate import (
    ALL_TARGETS,
    EvalConfig,
    _native_depth_head,
    load_eval_model,
    model_views,
    put_label,
    unproject_views,
)

ap = argparse.ArgumentParser()
ap.add_argument("runs", type=Path)
ap.add_argument("data", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--scenes", default="0,1")
args = ap.parse_args()
torch.set_num_threads(2)

models = {k: load_eval_model(args.runs / f"render_{v}" / "render.pt", True)[0]
          for k, v in [("full", "none"), ("no volume", "no-volume"), ("no pixel", "no-pixel"),
                       ("no separate bg", "no-background")]}
ecfg = EvalConfig(settings=("ego-forward",))
rows: dict[str, list[np.ndarray]] = {}


def tile(img: np.ndarray, gt: np.ndarray | None, text: str) -> np.ndarray:
    """The view at half size (PSNR measured at full size) with a label."""
    img = np.clip(img, 0, 1).astype(np.float32)
    label = text if gt is None else f"{text}  {M.psnr(img, gt):.1f} dB"
    h, w = img.shape[:2]
    out = (cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)[..., ::-1] * 255).round()
    out = out.astype(np.uint8).copy()
    put_label(out, label, 12)
    return out


for scene in (int(s) for s in args.scenes.split(",")):
    for setting, count in (("ego-forward", 1), ("ego-inward", 2)):
        dcfg = DatasetConfig(setting=setting, num_targets=ALL_TARGETS, voxel_size=1.6, max_depth=1e12)
        for name, model in models.items():
            item = SceneDataset(args.data, dcfg, model_cfg=model.cfg).item(scene, 0)
            gts = [t.permute(1, 2, 0).numpy() for t in item["targets"]["images"][:count]]
            if name == "full":
                rows.setdefault("ground truth", []).extend(tile(g, None, f"GT {item['scene']} {setting}")
                                                           for g in gts)
            views = list(zip(range(count), model_views(model, item)))
            rows.setdefault(name, []).extend(tile(v[0], gts[k], name) for k, v in views)
            if name == "full":
                oracle = list(zip(range(count), model_views(model, item, "ground-truth")))
                rows.setdefault("full, GT occupancy", []).extend(
                    tile(v[0], gts[k], "full, GT occ (oracle)") for k, v in oracle)
                base = list(zip(range(count), unproject_views(item, _native_depth_head(model, item), ecfg)))
                rows.setdefault("unproject", []).extend(tile(v[0], gts[k], "unproject") for k, v in base)
                gtd = list(zip(range(count), unproject_views(item, item["depth"][:, 0].numpy(), ecfg)))
                rows.setdefault("unproject GT depth", []).extend(
                    tile(v[0], gts[k], "unproject, GT depth (oracle)") for k, v in gtd)

order = ["ground truth", "full", "full, GT occupancy", "no volume", "no pixel", "no separate bg", "unproject",
         "unproject GT depth"]
sheet = np.concatenate([np.concatenate(rows[k], axis=1) for k in order], axis=0)
cv2.imwrite(str(args.out), sheet, [cv2.IMWRITE_JPEG_QUALITY, 88])
print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
