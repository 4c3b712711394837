"""Test-time appearance probe of the real-rig depth gap (docs/results.md "Issue 10: the targets, for 1.3.0"): the
real rigs' input images changed in one appearance property at a time (grey, blur, contrast, the synthetic
inputs' colour statistics), then `xyzcyl lidar-eval` of the same model against the same LiDAR sweep. If the depth
head's real error came from one such property, changing it moves the AbsRel; geometry is untouched.

    .venv/bin/python docs/runs/cpu_2026-11-25_final/appearance_probe.py [--model DIR] [--json OUT.json] \
        [--rig RIG_JSON ...] [--kinds none,exposure_0.5,...] [--pictures DIR]

Default rigs: the real nuScenes and PandaSet rigs; a synthetic scene with pseudo-LiDAR (synth_lidar.py) is
DATA/scene_N/rig_lidar.json.

Synthetic statistics: per-channel mean and standard deviation of the input images of data/val scenes 0-9.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

REAL = Path("../shared/data/real")
RIGS = (REAL / "nuscenes_ca9a282c" / "rig.json", REAL / "pandaset_002_00" / "rig.json")


def synth_stats(root: Path, scenes: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (mean, std) [3] RGB 0..1 over the input images of the first scenes of a data set."""
    px = []
    for d in sorted(root.glob("scene_*"))[:scenes]:
        for p in sorted((d / "inputs").glob("*.png")):
            if p.stem.endswith(("_sem", "_sky")):   # label images, not camera images
                continue
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
            px.append(img.reshape(-1, 3)[::7])
    x = np.concatenate(px)
    return x.mean(0), x.std(0)


def perturb(img: np.ndarray, kind: str, stats: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """img [H, W, 3] RGB float32 0..1 -> same, one appearance property changed."""
    w = img.shape[1]
    if kind == "none":
        return img
    if kind == "grey":
        g = img @ np.array([0.299, 0.587, 0.114], np.float32)
        return np.repeat(g[..., None], 3, axis=2)
    if kind == "blur":   # sigma 1 px at the network's 400-px input width
        s = w / 400
        return cv2.GaussianBlur(img, (0, 0), sigmaX=s, sigmaY=s)
    if kind in ("exposure_0.5", "exposure_1.5"):   # a global gain, as a different exposure time would give
        return np.clip(img * float(kind.split("_")[1]), 0, 1)
    if kind == "contrast_half":
        m = img.mean(axis=(0, 1), keepdims=True)
        return np.clip(m + 0.5 * (img - m), 0, 1)
    if kind == "synth_stats":   # per channel: the synthetic inputs' mean and standard deviation
        mu, sd = img.reshape(-1, 3).mean(0), img.reshape(-1, 3).std(0)
        return np.clip((img - mu) / np.maximum(sd, 1e-6) * stats[1] + stats[0], 0, 1)
    raise ValueError(kind)


KINDS = ("none", "grey", "blur", "exposure_0.5", "exposure_1.5", "contrast_half", "synth_stats")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="models/xyzcyl-cpu-v1")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--xyzcyl", default=".venv/bin/xyzcyl")
    ap.add_argument("--rig", action="append", type=Path, help="rig.json with a lidar block (repeatable)")
    ap.add_argument("--kinds", default=",".join(KINDS), help="comma-separated, of: " + ", ".join(KINDS))
    ap.add_argument("--pictures", type=Path, help="also write lidar-eval's --picture sheets here, RIG_KIND.jpg")
    args = ap.parse_args()
    stats = synth_stats(Path("data/val"))
    if args.pictures:
        args.pictures.mkdir(parents=True, exist_ok=True)
    out = {"model": args.model, "synth_mean": stats[0].tolist(), "synth_std": stats[1].tolist(), "rows": []}
    print("| rig | inputs | AbsRel | δ<1.25 | 0-10 m ratio | 20-40 m ratio |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    kinds = args.kinds.split(",")
    if bad := [k for k in kinds if k not in KINDS]:
        ap.error(f"--kinds: unknown {bad}")
    for rig_json in args.rig or RIGS:
        src = rig_json.parent
        rig = src.name
        meta = json.loads(rig_json.read_text())
        for kind in kinds:
            with tempfile.TemporaryDirectory() as tmp:
                tmp = Path(tmp)
                for f in src.iterdir():   # the LiDAR file and the rest, linked
                    if f.name != rig_json.name:
                        (tmp / f.name).symlink_to(f.resolve())
                for cam in meta["cameras"]:   # lossless PNG of the changed image, named in the copied rig.json
                    img = cv2.imread(str(src / cam["image"]), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
                    img = perturb(img, kind, stats)
                    name = "probe_" + Path(cam["image"]).stem + ".png"
                    cv2.imwrite(str(tmp / name), np.round(img[..., ::-1] * 255).astype(np.uint8))
                    cam["image"] = name
                (tmp / "rig.json").write_text(json.dumps(meta))
                rep = tmp / "rep.json"
                pic = ["--picture", str(args.pictures / f"{rig}_{kind}.jpg")] if args.pictures else []
                subprocess.run([args.xyzcyl, "lidar-eval", str(tmp / "rig.json"), "--model", args.model,
                                "--json", str(rep), "--quiet", *pic], check=True, stdout=subprocess.DEVNULL)
                r = json.loads(rep.read_text())
                meta = json.loads(rig_json.read_text())
            rng = {f"{x['from']:g}-{x['to']:g}": x for x in r["ranges"]}
            nan = {"median_ratio": float("nan")}
            row = {"rig": rig, "inputs": kind, "abs_rel": r["all"]["abs_rel"], "delta1": r["all"]["delta1"],
                   "ratio_0_10": rng.get("0-10", nan)["median_ratio"],
                   "ratio_20_40": rng.get("20-40", nan)["median_ratio"]}
            out["rows"].append(row)
            print(f"| {rig} | {kind} | {row['abs_rel']:.3f} | {row['delta1']:.3f} | {row['ratio_0_10']:.2f} | "
                  f"{row['ratio_20_40']:.2f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
