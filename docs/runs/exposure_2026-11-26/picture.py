"""Picture: PandaSet frame (pandaset_002_00) input views of the two cameras the gains change most, and a novel view
(drive 002, frame_20 reconstructed, rendered at frame_26's front-left camera): ground truth | baseline | gains."""
import sys

import cv2
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
import expo
from xyzcyl.runtime import realeval
from xyzcyl.runtime.inference import as_rgb
from xyzcyl.runtime.rig import load_rig

rows = []
res, s0, s1, gains = expo.main("../shared/data/real/pandaset_002_00/rig.json")
rig = load_rig("../shared/data/real/pandaset_002_00/rig.json")
imgs = [as_rgb(im, c) for im, c in zip(rig.load_images(), rig.cameras)]
for name in ("left_camera", "back_camera"):
    cam = rig.camera(name); gt = imgs[rig.names.index(name)]
    r0 = realeval._render_rgb(s0, cam); r1 = np.clip(expo.render_raw(s1, cam) * gains[name], 0, 1)
    rows.append((f"input {name}: base {realeval.psnr(r0, gt):.2f} dB, gains {realeval.psnr(r1, gt):.2f} dB", [gt, r0, r1]))
frames = realeval.load_frames("../shared/data/real/pandaset_002_seq")
a = next(f for f in frames if f.name == "frame_20"); b = next(f for f in frames if f.name == "frame_26")
expo.cap.update(parts=[], details=[], cams=[]); expo.GAINS.clear()
from xyzcyl.runtime.lidar import load_lidar

ia = [as_rgb(im, c) for im, c in zip(a.rig.load_images(), a.rig.cameras)]
lid = load_lidar(a.rig).points
t0 = expo.Reconstructor.load(expo.default_model_dir(), threads=2)
sa0 = t0.reconstruct(a.rig, images=ia, lidar=lid); g, _ = expo.estimate()
expo.cap.update(parts=[], details=[], cams=[]); expo.GAINS.update(g)
sa1 = t0.reconstruct(a.rig, images=ia, lidar=lid)
ib = [as_rgb(im, c) for im, c in zip(b.rig.load_images(), b.rig.cameras)]
for name in ("front_left_camera",):
    c = realeval.camera_in(a, b, name); gt = ib[b.rig.names.index(name)]
    r0 = realeval._render_rgb(sa0, c); r1 = np.clip(expo.render_raw(sa1, c) * g[name], 0, 1)
    still = ia[a.rig.names.index(name)]
    rows.append((f"novel {name} 20->26: base {realeval.psnr(r0, gt):.2f}, gains {realeval.psnr(r1, gt):.2f}, "
                 f"not moving {realeval.psnr(still, gt):.2f} dB", [gt, r0, r1]))
pic = realeval.sheet(rows, ("ground truth", "baseline (detail, LiDAR)", "per-camera gains"), 560)
cv2.imwrite(sys.argv[1], pic[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 88])
