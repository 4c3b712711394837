"""The 5-camera (Waymo-like) rig with and without the paper's mirrored-camera completion (runtime.convert.
complete_waymo_rig: 5 -> 8 cameras), against the 6-camera rig, all through the shipped ONNX model and the runtime
renderer (the inference path users get), on the same held-out synthetic scenes. Novel-view PSNR of the ego-forward
and ego-inward targets of each data set (depth head, no supplied depth). Writes JSON, a markdown table and a picture.

    .venv/bin/python docs/runs/cpu_2026-11-23/waymo_completion.py --out docs/runs/cpu_2026-11-23/waymo_completion

The numbers are the runtime path's (baked background panorama), so they differ slightly from `xyzcyl eval`
(per-view background network); the rows compare with each other, not with the eval tables."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from xyzcyl.runtime.convert import complete_waymo_rig
from xyzcyl.runtime.imageio import write_png
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.runtime.rig import Rig, load_rig, read_image
from xyzcyl.runtime.scene import render_view, rig_camera

SETTINGS = ("ego-forward", "ego-inward")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def targets(scene_dir: Path, setting: str) -> Rig:
    doc = json.loads((scene_dir / "targets.json").read_text())["settings"][setting]
    return Rig.from_dict({"cameras": doc["cameras"]}, root=scene_dir)


def score(rec: Reconstructor, rig: Rig, images: list, scene_dir: Path, keep: dict | None = None) -> dict:
    scene = rec.reconstruct(rig, images, depths=[None] * len(rig))
    out = {}
    for setting in SETTINGS:
        t = targets(scene_dir, setting)
        vals = []
        for k, cam in enumerate(t.cameras):
            rgb, _, _ = render_view(scene, rig_camera(cam))
            gt = read_image(t.path(cam.image), f"target {cam.name}")
            vals.append(psnr(rgb, gt))
            if keep is not None and setting == "ego-inward" and k == keep.get("view", 0):
                keep["img"], keep["gt"] = rgb, gt
        out[setting] = vals
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="models/xyzcyl-cpu-v1")
    ap.add_argument("--waymo", default="data/val_waymo", help="5-camera synthetic validation scenes")
    ap.add_argument("--six", default="data/val", help="6-camera synthetic validation scenes (same seed)")
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True, help="output stem (.json, .md, .png are written)")
    args = ap.parse_args()
    rec = Reconstructor.load(args.model, threads=args.threads)
    rows = {"6 cameras": {s: [] for s in SETTINGS}, "5 cameras": {s: [] for s in SETTINGS},
            "5 cameras + mirrored completion (8)": {s: [] for s in SETTINGS}}
    pics = []
    for i in range(args.scenes):
        sdir = Path(args.six) / f"scene_{i:06d}"
        rig6 = load_rig(sdir / "rig.json")
        for s, v in score(rec, rig6, rig6.load_images(), sdir).items():
            rows["6 cameras"][s] += v
        wdir = Path(args.waymo) / f"scene_{i:06d}"
        rig5 = load_rig(wdir / "rig.json")
        imgs5 = rig5.load_images()
        k5, k8 = {"view": 0}, {"view": 0}
        for s, v in score(rec, rig5, imgs5, wdir, k5 if i == 0 else None).items():
            rows["5 cameras"][s] += v
        rig8, imgs8 = complete_waymo_rig(rig5, imgs5)
        for s, v in score(rec, rig8, imgs8, wdir, k8 if i == 0 else None).items():
            rows["5 cameras + mirrored completion (8)"][s] += v
        if i == 0:
            pics = [k5["gt"], k5["img"], k8["img"]]
        print(f"scene {i}: " + ", ".join(f"{k} {np.mean(v['ego-inward']):.2f}" for k, v in rows.items()),
              file=sys.stderr, flush=True)
    summary = {k: {s: {"psnr": float(np.mean(v[s])), "views": len(v[s])} for s in SETTINGS} for k, v in rows.items()}
    doc = {"model": args.model, "scenes": args.scenes, "path": "runtime (onnxruntime + numba renderer, baked "
           "background), depth head", "rows": summary}
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    base = summary["6 cameras"]
    lines = ["| rig | ego-forward PSNR | ego-inward PSNR | vs 6 cameras |", "| --- | --- | --- | --- |"]
    for k, v in summary.items():
        d = [v[s]["psnr"] - base[s]["psnr"] for s in SETTINGS]
        lines.append(f"| {k} | {v['ego-forward']['psnr']:.2f} | {v['ego-inward']['psnr']:.2f} | "
                     f"{d[0]:+.2f} / {d[1]:+.2f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    if pics:
        write_png(out.with_suffix(".png"), np.concatenate([np.clip(p, 0, 1) for p in pics], axis=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
