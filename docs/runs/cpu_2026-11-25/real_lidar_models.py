"""Per model folder, on both real rigs: input-view PSNR at 400 px without LiDAR, with a random half of the sweep
(seed 0, `xyzcyl lidar-eval --holdout 0.5`'s rule) and with all of it; and the depth errors on the other half.
    .venv/bin/python docs/runs/cpu_2026-11-25/real_lidar_models.py MODEL_DIR [MODEL_DIR ...] > OUT.json"""
import json
import sys

import cv2
import numpy as np
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.runtime.lidar import camera_depths, load_lidar, summarise
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import render_view, rig_camera

out = {}
for model in sys.argv[1:]:
    rec = Reconstructor.load(model, threads=1)
    out[model] = {}
    for name in ("nuscenes_ca9a282c", "pandaset_002_00"):
        rig = load_rig(f"../shared/data/real/{name}/rig.json")
        imgs = rig.load_images()
        pts = load_lidar(rig).points
        pick = np.random.default_rng(0).random(len(pts)) < 0.5
        res = {}
        for label, lidar in (("none", None), ("half", pts[pick]), ("all", pts)):
            scene = rec.reconstruct(rig, imgs, depths=[None] * len(rig), lidar=lidar)
            ps = []
            for cam, img in zip(rig.cameras, imgs):
                w = 400
                h = round(cam.height * w / cam.width)
                rgb, _, _ = render_view(scene, rig_camera(cam, width=w, height=h))
                gt = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                ps.append(10 * np.log10(1 / np.mean((np.clip(rgb, 0, 1) - gt) ** 2)))
            r = summarise(camera_depths(scene, pts[~pick]))["all"]
            res[label] = {"psnr": round(float(np.mean(ps)), 2), "abs_rel_heldout": round(r["abs_rel"], 3),
                          "delta1_heldout": round(r["delta1"], 3)}
        out[model][name] = res
print(json.dumps(out, indent=1))
