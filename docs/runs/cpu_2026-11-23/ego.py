"""How much of the ego-inward error is the ego car, which no input camera sees (docs/results.md, issue 10)?

    .venv/bin/python docs/runs/cpu_2026-11-23/ego.py --checkpoint full=runs/cpu2/render_full/render.pt \
        [--checkpoint ...] [--occ runs/cpu2b/occ_ego/occ.pt] [--scenes 10] [--out ego.json]

Per render checkpoint, over the ego-inward views of the first --scenes validation scenes (full size, as
`xyzcyl eval`): the ego car's share of the pixels (target semantics class EGO) and of the squared error, the MSE
on and off the car, and PSNR of the pooled error with and without the car's pixels. Per checkpoint (render or
stage 1; --occ adds stage-1 ones): how many of the ego car's 1.6 m voxels the occupancy head selects.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from xyzcyl.model_export.config import ModelConfig
from xyzcyl.model_export.data.classes import EGO
from xyzcyl.model_export.dataset import DatasetConfig, SceneDataset
from xyzcyl.model_export.evaluate import ALL_TARGETS, load_eval_model, model_views
from xyzcyl.model_export.train import _resize, build_model, load_checkpoint
from xyzcyl.runtime.rig import read_image


def ego_voxels(model, ds: SceneDataset, n: int) -> dict:
    """Ego-car voxels (1.6 m grid) and how many the occupancy head selects, summed over n scenes."""
    ego_n = hit = sel = 0
    for i in range(n):
        item = ds.item(i, 0)
        sem = np.load(ds.scenes[i] / "occupancy.npz")[f"semantic_{ds.cfg.voxel_tag}"].transpose(2, 1, 0)
        ego = torch.from_numpy(sem == EGO)
        with torch.no_grad():
            occ = model.planes(_resize(item["images"], model.cfg), item["lifting"])["occ_logits"]
        pred = occ[1] > occ[0]
        ego_n, hit, sel = ego_n + int(ego.sum()), hit + int((pred & ego).sum()), sel + int(pred.sum())
    return {"scenes": n, "ego_voxels": ego_n, "ego_voxels_selected": hit, "voxels_selected": sel}


def ego_error(model, ds: SceneDataset, n: int) -> dict:
    se_ego = se_all = n_ego = n_all = 0.0
    for i in range(n):
        item = ds.item(i, 0)
        t = item["targets"]
        for k, (rgb, _, _) in enumerate(model_views(model, item, "predicted")):
            gt = t["images"][k].permute(1, 2, 0).numpy()
            err = ((np.clip(rgb, 0, 1) - gt) ** 2).mean(-1)
            path = ds.scenes[i] / "targets" / "ego-inward" / f"{t['names'][k]}_sem.png"
            sem = read_image(path, "semantics", channels=1, scale=False)[..., 0]    # 8-bit class ids, unscaled
            if sem.shape != err.shape:
                raise SystemExit(f"ego.py: {path}: {sem.shape}, not {err.shape}")
            ego = sem == EGO
            se_ego += float(err[ego].sum())
            se_all += float(err.sum())
            n_ego += int(ego.sum())
            n_all += err.size
    mse_rest = (se_all - se_ego) / (n_all - n_ego)
    return {"scenes": n, "ego_pixel_share": n_ego / n_all, "ego_error_share": se_ego / se_all,
            "mse_ego": se_ego / n_ego, "mse_rest": mse_rest, "psnr_pooled": -10 * np.log10(se_all / n_all),
            "psnr_pooled_without_ego": -10 * np.log10(mse_rest)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", action="append", default=[], help="LABEL=render.pt (repeatable)")
    ap.add_argument("--occ", action="append", default=[], help="LABEL=occ.pt: stage-1 checkpoints (voxels only)")
    ap.add_argument("--data", type=Path, default=Path("data/val"))
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    res = {}
    for spec, kind in [(s, "render") for s in args.checkpoint] + [(s, "occ") for s in args.occ]:
        label, _, path = spec.rpartition("=")
        label = label or path
        if kind == "render":
            model, _ = load_eval_model(path, need_render_stage=True)
        else:
            ck = load_checkpoint(path)
            model = build_model(ModelConfig.from_dict(ck["model_cfg"]))
            model.load_state_dict(ck["model"])
            model.eval()
        dcfg = DatasetConfig(setting="ego-inward", num_targets=ALL_TARGETS, voxel_size=model.cfg.grid.voxel_size,
                             max_depth=1e12)
        ds = SceneDataset(args.data, dcfg, model_cfg=model.cfg)
        n = min(args.scenes, len(ds))
        res[label] = {"checkpoint": path, "voxels": ego_voxels(model, ds, n)}
        if kind == "render":
            res[label]["error"] = ego_error(model, ds, n)
        print(label, json.dumps(res[label]), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
