"""Depth-head scale per input camera: the median over valid pixels of (the checkpoint's depth head, upsampled to
the input size) / (ground-truth depth), averaged over the first N scenes, per camera of each data set. A
focal-blind head shows its lens bias here: 1.0 is right, < 1 puts surfaces too near (docs/results.md
"Focal-aware depth").

    .venv/bin/python docs/runs/cpu_2026-11-23/depth_scale.py --checkpoint v1.1.0=runs/cpu2b/render_no-volume/render.pt \\
        --data data/val --data data/val_waymo [--scenes 4] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--checkpoint", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import torch
    from xyzcyl.model_export.dataset import DatasetConfig, SceneDataset
    from xyzcyl.model_export.evaluate import _native_depth_head, load_eval_model

    torch.set_num_threads(1)
    rows = []
    for spec in args.checkpoint:
        label, path = spec.split("=", 1)
        model, _ = load_eval_model(path, need_render_stage=True)
        for data in args.data:
            ds = SceneDataset(data, DatasetConfig(setting="ego-forward", num_targets=1, voxel_size=1.6),
                              model_cfg=model.cfg)
            per: dict[tuple[str, float], list[float]] = {}
            for i in range(min(args.scenes, len(ds))):
                item = ds.item(i, 0)
                pred = _native_depth_head(model, item)
                gt = item["depth"][:, 0].numpy()
                for k, cam in enumerate(item["rig"].cameras):
                    ok = (gt[k] > 1) & (gt[k] < 60)      # metres: the near and far ends are clamped / rare
                    fov = float(np.degrees(cam.horizontal_fov))
                    per.setdefault((cam.name, round(fov)), []).append(float(np.median(pred[k][ok] / gt[k][ok])))
            for (name, fov), v in per.items():
                rows.append({"checkpoint": label, "data": str(data), "camera": name, "hfov_deg": fov,
                             "depth_ratio": float(np.mean(v)), "scenes": len(v)})
    print("| checkpoint | data | camera | hfov | depth head / true depth (median) |")
    print("| --- | --- | --- | ---: | ---: |")
    for r in rows:
        print(f"| {r['checkpoint']} | {r['data']} | {r['camera']} | {r['hfov_deg']}° | {r['depth_ratio']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
