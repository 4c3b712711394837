import json
import sys

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import expo
from xyzcyl.runtime import realeval
from xyzcyl.runtime.inference import Reconstructor, as_rgb, default_model_dir
from xyzcyl.runtime.lidar import load_lidar

seq = "../shared/data/real/pandaset_002_seq"
frames = realeval.load_frames(seq)
pairs = realeval.pairs_within(frames, 0.8, 2.1)
A_names = sys.argv[1].split(",")
lidar_on = sys.argv[2] == "on"
rec = Reconstructor.load(default_model_dir(), threads=2)
rows = []
for an in A_names:
    a = next(f for f in frames if f.name == an)
    imgs_a = [as_rgb(im, c) for im, c in zip(a.rig.load_images(), a.rig.cameras)]
    lidar = load_lidar(a.rig).points if lidar_on else None
    expo.cap.update(parts=[], details=[], cams=[]); expo.GAINS.clear()
    s0 = rec.reconstruct(a.rig, images=imgs_a, lidar=lidar)
    gains, _ = expo.estimate()
    expo.cap.update(parts=[], details=[], cams=[]); expo.GAINS.update(gains)
    s1 = rec.reconstruct(a.rig, images=imgs_a, lidar=lidar)
    for aa, b in pairs:
        if aa.name != an:
            continue
        imgs_b = [as_rgb(im, c) for im, c in zip(b.rig.load_images(), b.rig.cameras)]
        for cam, gt in zip(b.rig.cameras, imgs_b):
            still = imgs_a[a.rig.names.index(cam.name)]
            c = realeval.camera_in(a, b, cam.name)
            r0 = realeval._render_rgb(s0, c); r1 = np.clip(expo.render_raw(s1, c) * gains[cam.name], 0, 1)
            m0, m1, ms = (realeval.image_metrics(x, gt) for x in (r0, r1, still))
            rows.append({"a": an, "b": b.name, "cam": cam.name, "base": m0, "harm": m1, "still": ms})
            print(an, b.name, cam.name, round(m0["psnr"], 2), round(m1["psnr"], 2), round(ms["psnr"], 2), flush=True)
json.dump(rows, open(f"novel_{sys.argv[1].replace(',', '_')}_{sys.argv[2]}.json", "w"))
for k in ("base", "harm", "still"):
    print(k, {m: round(float(np.mean([r[k][m] for r in rows])), 3) for m in ("psnr", "ssim", "sharpness")})
