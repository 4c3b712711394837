"""Side by side from `xyzcyl lidar-eval --picture` sheets of the same rig (each: rows = cameras; columns = input with
the LiDAR points, rendered depth, per-point error): the input column once, then every model's depth column, then
every model's error column, each labelled.
    .venv/bin/python docs/runs/cpu_2026-11-25_near/near_picture.py OUT.jpg LABEL=SHEET.jpg [LABEL=SHEET.jpg ...]"""
import sys

import cv2
import numpy as np

out, pairs = sys.argv[1], [a.split("=", 1) for a in sys.argv[2:]]
sheets = [(label, cv2.imread(path)) for label, path in pairs]
for (label, img), (_, path) in zip(sheets, pairs):
    if img is None:
        sys.exit(f"cannot read {path}")
w = sheets[0][1].shape[1] // 3


def col(img, k, title):
    c = img[:, k * w:(k + 1) * w].copy()
    cv2.rectangle(c, (0, 0), (w, 18), (0, 0, 0), -1)
    cv2.putText(c, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return c


cols = [col(sheets[0][1], 0, "input + LiDAR (red near, blue far)")]
cols += [col(img, 1, f"depth: {label}") for label, img in sheets]
cols += [col(img, 2, f"error: {label} (green 0, red >= 0.5)") for label, img in sheets]
pic = np.concatenate(cols, axis=1)
scale = min(1.0, 2400 / pic.shape[1])
pic = cv2.resize(pic, (round(pic.shape[1] * scale), round(pic.shape[0] * scale)), interpolation=cv2.INTER_AREA)
cv2.imwrite(out, pic, [cv2.IMWRITE_JPEG_QUALITY, 85])
print(f"wrote {out} ({pic.shape[1]}x{pic.shape[0]})")
