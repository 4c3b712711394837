"""Side-by-side renders of a run's models and baselines on validation scenes (docs/results.md).

    .venv/bin/python docs/runs/compare.py DATA OUT.jpg --model full=runs/cpu2/render_full \
        --model "no RGB=runs/cpu2/render_no-rgb" [--gt-occupancy full] [--scenes 0,1] [--voxel-size 1.6]

Columns: the first ego-forward and the first two ego-inward targets of each scene given by --scenes, at full size.
Rows: ground truth, then each --model (LABEL=RUN_DIR with RUN_DIR/render.pt) in the order given, the first
model with the ground-truth occupancy if --gt-occupancy names it, then the unprojection baselines from the
first model's depth head and from the ground-truth depth, each exactly as `xyzcyl eval` renders it
(evaluate.model_views / unproject_views) and labelled with its PSNR at full size.
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
ap.add_argument("data", type=Path)
ap.add_argument("out", type=Path)
ap.add_argument("--model", action="append", required=True, help="LABEL=RUN_DIR (repeatable, first = reference)")
ap.add_argument("--gt-occupancy", default=None, help="also render this model with the ground-truth occupancy")
ap.add_argument("--scenes", default="0,1")
ap.add_argument("--voxel-size", type=float, default=1.6)
args = ap.parse_args()
torch.set_num_threads(2)

models = {}
for spec in args.model:
    label, run = spec.split("=", 1)
    models[label] = load_eval_model(Path(run) / "render.pt", True)[0]
first = next(iter(models))
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
        dcfg = DatasetConfig(setting=setting, num_targets=ALL_TARGETS, voxel_size=args.voxel_size, max_depth=1e12)
        for name, model in models.items():
            item = SceneDataset(args.data, dcfg, model_cfg=model.cfg).item(scene, 0)
            gts = [t.permute(1, 2, 0).numpy() for t in item["targets"]["images"][:count]]
            if name == first:
                rows.setdefault("ground truth", []).extend(tile(g, None, f"GT {item['scene']} {setting}")
                                                           for g in gts)
            views = list(zip(range(count), model_views(model, item)))
            rows.setdefault(name, []).extend(tile(v[0], gts[k], name) for k, v in views)
            if name == args.gt_occupancy:
                oracle = list(zip(range(count), model_views(model, item, "ground-truth")))
                rows.setdefault(f"{name}, GT occupancy", []).extend(
                    tile(v[0], gts[k], f"{name}, GT occ (oracle)") for k, v in oracle)
            if name == first:
                base = list(zip(range(count), unproject_views(item, _native_depth_head(model, item), ecfg)))
                rows.setdefault("unproject", []).extend(tile(v[0], gts[k], "unproject") for k, v in base)
                gtd = list(zip(range(count), unproject_views(item, item["depth"][:, 0].numpy(), ecfg)))
                rows.setdefault("unproject GT depth", []).extend(
                    tile(v[0], gts[k], "unproject, GT depth (oracle)") for k, v in gtd)

order = ["ground truth", *[r for r in rows if r not in ("ground truth", "unproject", "unproject GT depth")],
         "unproject", "unproject GT depth"]
sheet = np.concatenate([np.concatenate(rows[k], axis=1) for k in order], axis=0)
cv2.imwrite(str(args.out), sheet, [cv2.IMWRITE_JPEG_QUALITY, 88])
print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
