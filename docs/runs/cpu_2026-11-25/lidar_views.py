"""Picture: the real PandaSet rig reconstructed by the shipped model without and with its LiDAR sweep as the depth
input, seen from poses no camera had: each listed camera moved 4 m forward along ego x. Columns: RGB without
LiDAR, RGB with LiDAR, depth without, depth with (turbo, log scale 1-80 m, red near).
    .venv/bin/python docs/runs/cpu_2026-11-25/lidar_views.py OUT.jpg [RIG_JSON] [CAMERA ...]"""
import sys

import cv2
import numpy as np
from xyzcyl.runtime.inference import Reconstructor, default_model_dir
from xyzcyl.runtime.lidar import _depth_colours, load_lidar
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import render_view, rig_camera

out = sys.argv[1]
rig = load_rig(sys.argv[2] if len(sys.argv) > 2 else "../shared/data/real/pandaset_002_00/rig.json")
names = sys.argv[3:] or ["front_camera", "front_left_camera", "front_right_camera"]
rec = Reconstructor.load(default_model_dir())
scenes = [rec.reconstruct(rig, depths=[None] * len(rig)),
          rec.reconstruct(rig, depths=[None] * len(rig), lidar=load_lidar(rig).points)]
rows = []
for name in names:
    cam = rig.camera(name)
    w = 400
    h = round(cam.height * w / cam.width)
    rgbs, deps = [], []
    for s in scenes:
        rgb, depth, alpha = render_view(s, rig_camera(cam, forward=4.0, width=w, height=h))
        rgbs.append(np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
        d = _depth_colours(depth, 80.0)
        d[alpha < 0.5] = 0
        deps.append(d)
    row = np.concatenate([*rgbs, *deps], axis=1)
    for i, t in enumerate(("no LiDAR", "LiDAR depth in", "depth, no LiDAR", "depth, LiDAR in")):
        cv2.putText(row, f"{name} +4 m: {t}" if i == 0 else t, (4 + i * w, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                    (255, 255, 255), 1, cv2.LINE_AA)
    rows.append(row)
cv2.imwrite(out, np.concatenate(rows, axis=0)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
print(out)
