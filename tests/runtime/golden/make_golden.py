"""Write the golden reference of the shipped model on the example rig (run once after exporting the model):

    .venv/bin/python tests/runtime/golden/make_golden.py [--model models/xyzcyl-cpu-v1]

Stores tests/runtime/golden/<model name>.json (the model.json sha256, the exact Gaussian count, the smallest
|occupancy margin| and opacity distance to the pruning threshold -- how robust the count is to float round-off on
another CPU) and <model name>_CAM_FRONT.png (a 400x225 render with the background) of the model's Gaussians alone
(detail=None), and under "detail" the same of the default reconstruction (with the detail layer, runtime.detail):
its counts and <model name>_CAM_FRONT_detail.png. tests/runtime/test_shipped_model.py compares against them."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[3]
VIEW = {"camera": "CAM_FRONT", "width": 400, "height": 225}


# a Gaussian whose opacity is within this fraction of the pruning threshold may be kept on one CPU and pruned on
# another: float32 kernels differ by ~1e-6 relative; 1e-4 leaves a factor 100
BORDER_REL = 1e-4


def borderline(enc: dict, threshold: float) -> int:
    """How many of the encode graph's pixel Gaussians have an opacity within BORDER_REL of the threshold (the
    count test allows that many flips)."""
    op = 1 / (1 + np.exp(-enc["pixel_opacity_logits"].astype(np.float64)))
    return int(np.sum(np.abs(op - threshold) <= BORDER_REL * threshold))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=REPO / "models" / "xyzcyl-cpu-v1")
    args = ap.parse_args()
    from xyzcyl.runtime.imageio import write_png
    from xyzcyl.runtime.inference import DEFAULT_DETAIL, PRUNE_OPACITY, Reconstructor
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import render_view, rig_camera

    rec = Reconstructor.load(args.model, threads=2)
    rig = load_rig(REPO / "examples" / "synth_nuscenes" / "rig.json")
    scene = rec.reconstruct(rig, detail=None)
    imgs, depth, mask = rec.prepare(rig, rig.load_images())
    lift, _ = rec.lifting(rig)
    enc = rec._run("encode", {"images": imgs, "depth": depth, "depth_mask": mask, **lift})
    margin = np.abs(enc["occ_logits"][1] - enc["occ_logits"][0])
    op = 1 / (1 + np.exp(-scene.gaussians.opacity_logits.astype(np.float64)))
    cam = rig_camera(rig.camera(VIEW["camera"]), width=VIEW["width"], height=VIEW["height"])
    rgb, _, _ = render_view(scene, cam)
    out = Path(__file__).resolve().parent
    out.mkdir(exist_ok=True)
    png = f"{rec.info.name}_{VIEW['camera']}.png"
    write_png(out / png, rgb)
    meta = {"model": rec.info.name, "version": rec.info.version,
            "model_json_sha256": hashlib.sha256((args.model / "model.json").read_bytes()).hexdigest(),
            "count": len(scene.gaussians), "counts": scene.counts, "view": {**VIEW, "png": png},
            "min_abs_occupancy_margin": float(margin.min()),
            "min_opacity_over_threshold": float((op - PRUNE_OPACITY).min()) if op.size else None,
            "borderline": borderline(enc, PRUNE_OPACITY)}
    full = rec.reconstruct(rig)                      # the default: with the detail layer
    rgb, _, _ = render_view(full, cam)
    dpng = f"{rec.info.name}_{VIEW['camera']}_detail.png"
    write_png(out / dpng, rgb)
    meta["detail"] = {"options": dataclasses.asdict(DEFAULT_DETAIL), "count": len(full.gaussians),
                      "counts": full.counts, "png": dpng}
    (out / f"{rec.info.name}.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(json.dumps(meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
