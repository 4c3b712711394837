"""Pseudo-LiDAR for synthetic scenes, so that the real rigs' depth check (`xyzcyl lidar-eval`) runs on scenes whose
true depth is known: one JSON line per scene on stdout.

Each input camera's true depth, every --step-th pixel in both directions, depth <= 80 m (the sky left out), is
unprojected to ego points along the camera's own rays (docs/data.md: a pixel (u, v) with depth z is the ego point
cam_to_ego @ [z inv(K) [u, v, 1], 1]); the points are saved as SCENE/lidar.npy, and SCENE/rig_lidar.json is the
scene's rig.json with a lidar block naming them. Unlike a real sweep these points are exactly what the cameras
see (no LiDAR-camera parallax). docs/results.md "The model alone" quotes the model's synthetic AbsRel measured
this way, the mean over 5 validation scenes per rig:

    .venv/bin/xyzcyl data synth --out data/lidar_val5 --scenes 5 --seed 1 --targets "" --quiet
    .venv/bin/xyzcyl data synth --out data/lidar_val5_pandaset --rig pandaset --scenes 5 --seed 1 --targets "" --quiet
    .venv/bin/python benchmarks/synth_lidar.py data/lidar_val5 data/lidar_val5_pandaset
    .venv/bin/python benchmarks/exposure_probe.py data/lidar_val5/scene_*/rig_lidar.json --kinds none
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def pseudo_lidar(scene: Path, step: int, max_depth: float = 80.0) -> int:
    """Write scene/lidar.npy and scene/rig_lidar.json; returns the number of points."""
    from xyzcyl.runtime.rig import load_rig

    rig = load_rig(scene / "rig.json")
    pts = []
    for cam, d in zip(rig.cameras, rig.load_depths()):
        if d is None:
            continue
        v, u = np.mgrid[0:cam.height:step, 0:cam.width:step]
        z = d[v, u]
        ok = (z > 0) & (z <= max_depth)
        uv = np.stack([u[ok], v[ok]], axis=-1).astype(np.float64)
        o, dirs = cam.pixel_rays(uv)
        # pixel_rays gives unit directions; scale so the camera-frame z equals the stored depth
        zc = dirs @ cam.rotation[:, 2]
        pts.append(o + dirs * (z[ok] / zc)[:, None])
    if not pts:
        raise SystemExit(f"synth_lidar.py: {scene}: no camera has a depth file")
    points = np.concatenate(pts).astype(np.float32)
    np.save(scene / "lidar.npy", points)
    doc = json.loads((scene / "rig.json").read_text())
    doc["lidar"] = {"file": "lidar.npy", "format": "pseudo-LiDAR: ground-truth depth of the input cameras, "
                    f"every {step}th pixel, ego frame"}
    (scene / "rig_lidar.json").write_text(json.dumps(doc, indent=1))
    return len(points)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path, help="data sets of `xyzcyl data synth` (scene_* folders)")
    ap.add_argument("--step", type=int, default=4, help="every STEP-th pixel in both directions (default 4)")
    ap.add_argument("--scenes", type=int, default=None, help="only the first N scenes of each data set")
    args = ap.parse_args(argv)
    if args.step < 1:
        ap.error("--step: must be >= 1")
    for data in args.data:
        scenes = sorted(p for p in data.glob("scene_*") if p.is_dir())[:args.scenes]
        if not scenes:
            ap.error(f"no scene_* folder in {data}")
        for scene in scenes:
            n = pseudo_lidar(scene, args.step)
            print(json.dumps({"scene": str(scene), "rig": str(scene / "rig_lidar.json"), "points": n}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
