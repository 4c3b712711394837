"""Depth against LiDAR with the input images changed in one appearance property at a time: one JSON line per rig
and change on stdout.

For each rig.json with a LiDAR block and each --kinds change (the images as posted, grey, a 1-pixel blur at the
network's 400-pixel input width, exposure x0.5 and x1.5, half contrast, or the synthetic training inputs'
per-channel colour statistics), the images are changed (and stored as 8-bit, as a camera would), the rig is
reconstructed with the model, and each input camera's rendered depth is checked against the rig's LiDAR sweep
exactly as `xyzcyl lidar-eval` checks it (runtime.lidar.camera_depths / summarise at --width pixels, no LiDAR
input): AbsRel, δ < 1.25 and the median ratio rendered / LiDAR at 0-10 m and 20-40 m. Geometry is untouched, so
a change that moves the AbsRel is one the depth head reads.

docs/results.md "The model alone" quotes the exposure rows for the shipped model (the model's Gaussians alone,
the default here; --detail adds the runtime's detail layer):

    .venv/bin/python benchmarks/exposure_probe.py path/to/nuscenes_rig/rig.json path/to/pandaset_rig/rig.json \
        --kinds none,exposure_0.5,exposure_1.5

The rigs are real ones with a LiDAR sweep (a nuScenes or PandaSet frame in the rig.json layout of docs/data.md).
The ``synth_stats`` change needs --synth-data, a data set of `xyzcyl data synth` (its first 10 scenes' inputs).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

KINDS = ("none", "grey", "blur", "exposure_0.5", "exposure_1.5", "contrast_half", "synth_stats")


def synth_stats(root: Path, scenes: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (mean, std) [3] RGB 0..1 over the input images of the first scenes of a synthetic data set."""
    import cv2

    px = []
    for d in sorted(root.glob("scene_*"))[:scenes]:
        for p in sorted((d / "inputs").glob("*.png")):
            if p.stem.endswith(("_sem", "_sky")):   # label images, not camera images
                continue
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
            px.append(img.reshape(-1, 3)[::7])
    if not px:
        raise SystemExit(f"exposure_probe.py: --synth-data: no scene inputs under {root}")
    x = np.concatenate(px)
    return x.mean(0), x.std(0)


def perturb(img: np.ndarray, kind: str, stats: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """img [H, W, 3] RGB float32 0..1 -> the same with one appearance property changed, rounded to 8 bits."""
    import cv2

    w = img.shape[1]
    if kind == "none":
        out = img
    elif kind == "grey":
        g = img @ np.array([0.299, 0.587, 0.114], np.float32)
        out = np.repeat(g[..., None], 3, axis=2)
    elif kind == "blur":   # sigma 1 px at the network's 400-px input width
        s = w / 400
        out = cv2.GaussianBlur(img, (0, 0), sigmaX=s, sigmaY=s)
    elif kind in ("exposure_0.5", "exposure_1.5"):   # a global gain, as a different exposure time would give
        out = img * float(kind.split("_")[1])
    elif kind == "contrast_half":
        m = img.mean(axis=(0, 1), keepdims=True)
        out = m + 0.5 * (img - m)
    elif kind == "synth_stats":   # per channel: the synthetic inputs' mean and standard deviation
        if stats is None:
            raise ValueError("synth_stats needs the synthetic inputs' statistics")
        mu, sd = img.reshape(-1, 3).mean(0), img.reshape(-1, 3).std(0)
        out = (img - mu) / np.maximum(sd, 1e-6) * stats[1] + stats[0]
    else:
        raise ValueError(kind)
    return (np.round(np.clip(out, 0, 1) * 255) / 255).astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rigs", nargs="+", type=Path, metavar="RIG_JSON", help="rig.json with a lidar block")
    ap.add_argument("--kinds", default="none,exposure_0.5,exposure_1.5",
                    help="comma-separated, of: " + ", ".join(KINDS) + " (default none,exposure_0.5,exposure_1.5)")
    ap.add_argument("--model", default=None, help="model folder (default: $XYZCYL_MODEL or the shipped one)")
    ap.add_argument("--detail", action="store_true", help="with the runtime's default detail layer (default: the "
                                                          "model's Gaussians alone, `lidar-eval --no-detail`)")
    ap.add_argument("--width", type=int, default=400, help="evaluation width in pixels (default 400, as lidar-eval)")
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    ap.add_argument("--synth-data", type=Path, default=None, help="synthetic data set for the synth_stats change")
    args = ap.parse_args(argv)
    kinds = args.kinds.split(",")
    if bad := [k for k in kinds if k not in KINDS]:
        ap.error(f"--kinds: unknown {bad}")
    if "synth_stats" in kinds and args.synth_data is None:
        ap.error("--kinds synth_stats needs --synth-data")
    if not 8 <= args.width <= 4096:
        ap.error(f"--width: must be in 8..4096, got {args.width}")

    from xyzcyl.runtime.inference import DEFAULT_DETAIL, Reconstructor, default_model_dir
    from xyzcyl.runtime.lidar import (
        MAX_DEPTH,
        MIN_DEPTH,
        OCCLUSION_RADIUS,
        RANGE_BINS,
        camera_depths,
        load_lidar,
        summarise,
    )
    from xyzcyl.runtime.rig import load_rig

    stats = synth_stats(args.synth_data) if "synth_stats" in kinds else None
    model_dir = Path(args.model) if args.model else default_model_dir()
    rec = Reconstructor.load(model_dir, threads=args.threads)
    bins = (*[b for b in RANGE_BINS if b < MAX_DEPTH], MAX_DEPTH)
    for rig_json in args.rigs:
        rig = load_rig(rig_json)
        points = load_lidar(rig).points
        posted = rig.load_images()
        for kind in kinds:
            t0 = time.perf_counter()
            images = [perturb(img, kind, stats) for img in posted]
            scene = rec.reconstruct(rig, images=images, depths=[None] * len(rig),
                                    detail=DEFAULT_DETAIL if args.detail else None)
            views = camera_depths(scene, points, args.width, MIN_DEPTH, MAX_DEPTH, OCCLUSION_RADIUS)
            r = summarise(views, bins=bins)
            rng = {f"{x['from']:g}-{x['to']:g}": x["median_ratio"] for x in r["ranges"]}
            row = {"rig": str(rig_json), "inputs": kind, "model": f"{rec.info.name} {rec.info.version}",
                   "detail": bool(args.detail), "width": args.width, "abs_rel": r["all"]["abs_rel"],
                   "delta1": r["all"]["delta1"], "ratio_0_10": rng.get("0-10"), "ratio_20_40": rng.get("20-40"),
                   "seconds": round(time.perf_counter() - t0, 2)}
            print(json.dumps({k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                              for k, v in row.items()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
