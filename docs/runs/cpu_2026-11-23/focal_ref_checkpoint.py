"""A copy of a stage-2 checkpoint whose model config turns the focal-aware depth head on (or off), weights
unchanged: the zero-shot test of docs/results.md "Focal-aware depth" (v1.1.0's focal-blind head, its depth
rescaled by each camera's focal_n / F without retraining).

    .venv/bin/python docs/runs/cpu_2026-11-23/focal_ref_checkpoint.py runs/cpu2b/render_no-volume/render.pt \\
        runs/cpu4/v110_focal.pt [--ref 1.0553|off]
    .venv/bin/xyzcyl eval --checkpoint runs/cpu4/v110_focal.pt --data data/val_waymo --max-scenes 10 ...
"""

import argparse

import torch
from xyzcyl.model_export.config import ModelConfig, parse_focal_ref

ap = argparse.ArgumentParser()
ap.add_argument("src")
ap.add_argument("dst")
ap.add_argument("--ref", default="nuscenes", help="F, 'nuscenes' (1.0553) or 'off'")
args = ap.parse_args()
ck = torch.load(args.src, map_location="cpu", weights_only=False)
cfg = ModelConfig.from_dict(ck["model_cfg"])
ck["model_cfg"] = cfg.replace(backbone=cfg.backbone.replace(depth_focal_ref=parse_focal_ref(args.ref))).to_dict()
torch.save(ck, args.dst)
print(f"wrote {args.dst}: backbone.depth_focal_ref = {ck['model_cfg']['backbone']['depth_focal_ref']}")
