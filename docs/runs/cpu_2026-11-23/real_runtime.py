"""The shipped ONNX model (models/xyzcyl-cpu-v1) through the service's runtime path on the real rigs of ../shared/data/real: input-view PSNR at 400 px wide, against the area-resized input (the rule of real.py, which runs the torch checkpoints).
    .venv/bin/python docs/runs/cpu_2026-11-23/real_runtime.py > docs/runs/cpu_2026-11-23/real_runtime.json
With --lidar each rig's LiDAR sweep is the depth input (docs/inference.md "LiDAR as the depth input"):
    .venv/bin/python docs/runs/cpu_2026-11-23/real_runtime.py --lidar > docs/runs/cpu_2026-11-25/real_runtime_lidar.json"""
import json
import sys

import cv2
import numpy as np
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.runtime.lidar import load_lidar
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import render_view, rig_camera

rec = Reconstructor.load("models/xyzcyl-cpu-v1", threads=2)
out = {}
for name in ("nuscenes_ca9a282c", "pandaset_002_00"):
    rig = load_rig(f"../shared/data/real/{name}/rig.json")
    imgs = rig.load_images()
    lidar = load_lidar(rig).points if "--lidar" in sys.argv[1:] else None
    scene = rec.reconstruct(rig, imgs, depths=[None] * len(rig), lidar=lidar)
    ps = []
    for cam, img in zip(rig.cameras, imgs):
        w = 400; h = round(cam.height * w / cam.width)
        rgb, _, _ = render_view(scene, rig_camera(cam, width=w, height=h))
        gt = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        ps.append(10 * np.log10(1 / np.mean((np.clip(rgb, 0, 1) - gt) ** 2)))
    out[name] = round(float(np.mean(ps)), 2)
print(json.dumps(out))
