"""Input views at their own pose, the fused scene against each camera's own view (runtime.detail.OwnViews; issue
35 item 2): one JSON document on stdout with PSNR / SSIM / sharpness ratio (runtime.realeval.image_metrics) per
camera, each way, at the cameras' full resolution, and a picture of the camera that gains most (a crop: input |
fused scene | own view).

    .venv/bin/python benchmarks/own_views.py ../shared/data/real/pandaset_002_00/rig.json --picture out/own.jpg

The rig's LiDAR is used when it names one (as `xyzcyl reconstruct` does); --no-lidar for camera only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rig", help="rig.json with images (and a lidar block)")
    ap.add_argument("--no-lidar", action="store_true", help="camera only")
    ap.add_argument("--picture", default=None, help="write the crop of the camera that gains most (.jpg / .png)")
    ap.add_argument("--crop", type=float, default=0.45, help="the picture's crop: this fraction of the width, "
                                                             "from the side that gains most (default 0.45)")
    args = ap.parse_args(argv)

    import cv2
    from xyzcyl.runtime.inference import Reconstructor, default_model_dir
    from xyzcyl.runtime.lidar import has_lidar, load_lidar
    from xyzcyl.runtime.realeval import image_metrics
    from xyzcyl.runtime.render import render
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import rig_camera

    rig = load_rig(args.rig)
    lidar = load_lidar(rig).points if has_lidar(rig) and not args.no_lidar else None
    rec = Reconstructor.load(default_model_dir())
    t0 = time.perf_counter()
    scene = rec.reconstruct(rig, lidar=lidar)
    took = time.perf_counter() - t0
    images = rig.load_images()
    rows, best = {}, None
    for k, cam in enumerate(rig.cameras):
        c = rig_camera(cam)
        img = images[k]
        gt = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 65535.0 if img.dtype == np.uint16 else 1.0)
        bg = scene.background.render(c) if scene.background is not None else None
        # the camera's exposure gain back, as Scene.render gives it (the cells were divided by it: runtime.exposure)
        gain_c = scene.exposure_gain(c, None)
        gain_c = np.ones(3, np.float32) if gain_c is None else gain_c.astype(np.float32)
        fused = render(scene.gaussians, c, background=bg).rgb * gain_c
        own = render(scene.gaussians_for(c), c, background=bg).rgb * gain_c
        rows[cam.name] = {"fused": image_metrics(fused, gt), "own": image_metrics(own, gt)}
        gain = rows[cam.name]["own"]["psnr"] - rows[cam.name]["fused"]["psnr"]
        if best is None or gain > best[0]:
            best = (gain, cam.name, gt, fused, own)
    mean = {w: {m: float(np.mean([r[w][m] for r in rows.values()])) for m in ("psnr", "ssim", "sharpness")}
            for w in ("fused", "own")}
    doc = {"rig": str(args.rig), "lidar": lidar is not None, "reconstruct_s": round(took, 2),
           "counts": {k: scene.counts.get(k) for k in ("detail", "carved", "coarse", "total")},
           "cameras": rows, "mean": mean}
    print(json.dumps(doc, indent=1))
    if args.picture:
        _, name, gt, fused, own = best
        w = gt.shape[1]
        cw = int(args.crop * w)
        # the side of the image where the two renders differ most (the overlap with a neighbour)
        diff = np.abs(own - fused).mean(axis=(0, 2))
        sl = slice(0, cw) if diff[:cw].sum() >= diff[-cw:].sum() else slice(w - cw, w)
        strip = np.concatenate([np.clip(a[:, sl], 0, 1) for a in (gt, fused, own)], axis=1)
        out = (strip[..., ::-1] * 255 + 0.5).astype(np.uint8)
        cv2.putText(out, f"{name}: input | fused scene | own view", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.9,
                    (255, 255, 255), 2)
        ext = Path(args.picture).suffix.lower()
        if not cv2.imwrite(args.picture, out, [cv2.IMWRITE_JPEG_QUALITY, 88] if ext in (".jpg", ".jpeg") else []):
            print(f"could not write {args.picture}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
