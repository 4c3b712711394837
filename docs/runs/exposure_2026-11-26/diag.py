"""nuScenes: where the gains lose (back-left) and win (front): ground truth | baseline | gains | |errors| x3. Usage:
    .venv/bin/python docs/runs/exposure_2026-11-26/diag.py docs/pictures/exposure_gains_nuscenes.jpg"""
import sys

import cv2
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import expo
from xyzcyl.runtime import realeval
from xyzcyl.runtime.inference import as_rgb
from xyzcyl.runtime.rig import load_rig

p = "../shared/data/real/nuscenes_ca9a282c/rig.json"
res, s0, s1, gains = expo.main(p)
rig = load_rig(p)
imgs = [as_rgb(im, c) for im, c in zip(rig.load_images(), rig.cameras)]
rows = []
for name in ("CAM_BACK_LEFT", "CAM_FRONT"):
    cam = rig.camera(name); gt = imgs[rig.names.index(name)]
    r0 = realeval._render_rgb(s0, cam); r1 = np.clip(expo.render_raw(s1, cam) * gains[name], 0, 1)
    e0 = np.abs(r0 - gt).mean(2, keepdims=True).repeat(3, 2) * 3; e1 = np.abs(r1 - gt).mean(2, keepdims=True).repeat(3, 2) * 3
    rows.append((name, [gt, r0, r1, e0, e1]))
cv2.imwrite(sys.argv[1], realeval.sheet(rows, ("gt", "base", "gains", "err base x3", "err gains x3"), 360)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
