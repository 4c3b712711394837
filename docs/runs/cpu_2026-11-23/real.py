"""Zero-shot on the real rigs: reconstruct each real rig of ../shared/data/real with a trained model (no
retraining, no depth given) and render it back at its own input cameras.

For every checkpoint and rig: input-view PSNR (and non-sky-agnostic mean-colour error) of the render composited
over the background network against the input image, both at WIDTH pixels wide (area-resized input, the camera
resized with Camera.resized). Input views are the easiest poses (the model saw exactly these pixels), so this
measures how much of a real image survives the lifting, not novel-view quality.

    .venv/bin/python docs/runs/cpu_2026-11-23/real.py --out docs/runs/cpu_2026-11-23/real \
        --checkpoint full=runs/cpu2/render_full/render.pt [--checkpoint no-rgb=...] [--width 400]

Writes <out>.json (one row per checkpoint x rig x camera, plus means) and <out>_<rig>.jpg (rows: inputs, then
the renders of each checkpoint, PSNR in each tile).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

RIGS = ("nuscenes_ca9a282c", "pandaset_002_00")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--checkpoint", action="append", required=True, help="LABEL=PATH (repeatable)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--real", type=Path, default=Path(os.environ.get("XYZCYL_REAL_DATA", "../shared/data/real")))
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    import cv2
    import torch
    from xyzcyl.model_export import metrics as M
    from xyzcyl.model_export.dataset import add_lifting, load_rig_folder
    from xyzcyl.model_export.evaluate import load_eval_model, model_views, put_label
    from xyzcyl.runtime.lifting import LiftingParams

    torch.set_num_threads(args.threads)
    rows, sheets = [], {}
    for spec in args.checkpoint:
        label, path = spec.split("=", 1)
        model, _ = load_eval_model(path, need_render_stage=True)
        params = LiftingParams.from_config_dict(model.cfg.to_dict())
        for rig_name in RIGS:
            folder = args.real / rig_name
            if not folder.is_dir():
                print(f"skipping {rig_name}: {folder} not found")
                continue
            item = load_rig_folder(folder)
            cams = list(item["rig"].cameras)
            h = round(cams[0].height * args.width / cams[0].width)
            small = [c.resized(args.width, h) for c in cams]
            gts = [cv2.resize(im.permute(1, 2, 0).numpy(), (args.width, h), interpolation=cv2.INTER_AREA)
                   for im in item["images"]]
            item["targets"] = {"K": np.stack([c.K for c in small]), "cam_to_ego": np.stack([c.cam_to_ego for c in small]),
                               "width": args.width, "height": h, "names": [c.name for c in small]}
            add_lifting(item, params)
            views = []
            for k, (rgb, _, n_g) in enumerate(model_views(model, item)):
                rgb = np.clip(rgb, 0, 1)
                p = M.psnr(rgb, gts[k])
                rows.append({"checkpoint": label, "rig": rig_name, "camera": cams[k].name, "psnr": p,
                             "colour_err": M.mean_colour_error(rgb, gts[k]), "gaussians": n_g})
                tile = (rgb[..., ::-1] * 255).round().astype(np.uint8).copy()
                put_label(tile, f"{label} {cams[k].name} {p:.2f} dB", 12)
                views.append(tile)
            sheet = sheets.setdefault(rig_name, [])
            if not sheet:
                inputs = []
                for k, g in enumerate(gts):
                    tile = (g[..., ::-1] * 255).round().astype(np.uint8).copy()
                    put_label(tile, f"input {cams[k].name}", 12)
                    inputs.append(tile)
                sheet.append(np.concatenate(inputs, 1))
            sheet.append(np.concatenate(views, 1))
    means = {}
    for r in rows:
        means.setdefault((r["checkpoint"], r["rig"]), []).append(r)
    summary = [{"checkpoint": c, "rig": g, "psnr": float(np.mean([x["psnr"] for x in v])),
                "colour_err": float(np.mean([x["colour_err"] for x in v])), "views": len(v)}
               for (c, g), v in means.items()]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{args.out}.json").write_text(json.dumps({"width": args.width, "summary": summary, "views": rows},
                                                   indent=1) + "\n")
    for rig_name, sheet in sheets.items():
        cv2.imwrite(f"{args.out}_{rig_name}.jpg", np.concatenate(sheet, 0), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
