"""Experiment (2026-11-26, not shipped; CHANGELOG "Not shipped -- per-camera colour gains"): per-camera colour gains
(exposure / white balance) estimated from the detail cells that two cameras see on the same surface (both cells
placed by LiDAR, depths within 3 %: per ordered camera pair the median log colour ratio, then least squares over the
cameras with the geometric mean of the gains fixed at 1); each camera's detail cells harmonised (its image / its
gain, unclipped) at reconstruction, and the camera's gain re-applied to the whole render at that camera.
From the repository root:
    .venv/bin/python docs/runs/exposure_2026-11-26/expo.py ../shared/data/real/pandaset_002_00/rig.json > OUT.json
    (add `off` for no LiDAR; `whole` also feeds the harmonised images to the network; `whole min` with the
    darkest camera as the reference, so the harmonised images stay <= 1; see the CHANGELOG)
    .venv/bin/python docs/runs/exposure_2026-11-26/novel.py frame_20,frame_26,frame_32 on
    .venv/bin/python docs/runs/exposure_2026-11-26/picture.py docs/pictures/exposure_gains_experiment.jpg
"""
import json
import sys

import numpy as np
from xyzcyl.runtime import detail as D
from xyzcyl.runtime import realeval
from xyzcyl.runtime.inference import Reconstructor, as_rgb, default_model_dir
from xyzcyl.runtime.lidar import load_lidar
from xyzcyl.runtime.render.gaussians import SH_C0
from xyzcyl.runtime.rig import load_rig

cap = {"parts": [], "details": [], "cams": []}
GAINS = {}
WHOLE = [False]
orig_cd = D.camera_detail

def camera_detail(cam, image, *a, **k):
    g = GAINS.get(cam.name)
    if g is not None and not WHOLE[0]:
        image = (image / g[None, None, :]).astype(np.float32)
    out = orig_cd(cam, image, *a, **k)
    cap["parts"].append(out[0]); cap["details"].append(out[1]); cap["cams"].append(cam.name)
    return out
D.camera_detail = camera_detail

_gc = D.grid_colours
def grid_colours(image, grid, sharpen=0.0, footprint=0.5):
    import cv2
    c = _gc(image, grid, 0.0, footprint)       # the area means; the unsharp mask below, unclipped
    if sharpen > 0:
        blur = cv2.GaussianBlur(c, (0, 0), footprint, borderType=cv2.BORDER_REFLECT)
        c = np.maximum(c + np.float32(sharpen) * (c - blur), 0.0)
    return c
D.grid_colours = grid_colours      # as runtime.detail.grid_colours, without the clip at 1 (harmonised colours exceed it)

def render_raw(scene, cam):
    from xyzcyl.runtime.scene import render_view, rig_camera
    rgb, _, _ = render_view(scene, rig_camera(cam))
    return rgb

def estimate(tol=0.03, floor=0.04, measured=True):
    names, parts, details = cap["cams"], cap["parts"], cap["details"]
    n = len(names)
    cmap = []
    for g, d in zip(parts, details):
        m = np.zeros(d.keep.shape + (3,), np.float64)
        ys, xs = np.nonzero(d.keep)
        m[ys, xs] = 0.5 + SH_C0 * g.sh[:, 0, :]
        cmap.append(m)
    rows, rhs, w = [], [], []
    pairs = {}
    for j in range(n):
        cj = 0.5 + SH_C0 * parts[j].sh[:, 0, :].astype(np.float64)
        for i in range(n):
            if i == j:
                continue
            di = details[i]
            idx, u, v, z = D._grid_pixels(di.grid, details[j].means)
            dc = di.depth[v, u].astype(np.float64)
            ok = di.keep[v, u] & (np.abs(z - dc) <= tol * dc)
            if measured:
                ok &= (di.conf[v, u] == D.CONF_MEASURED) & (details[j].cell_conf()[idx] == D.CONF_MEASURED)
            a = cmap[i][v[ok], u[ok]]; b = cj[idx[ok]]
            good = np.all(a > floor, 1) & np.all(b > floor, 1) & np.all(a < 0.98, 1) & np.all(b < 0.98, 1)
            if good.sum() < 200:
                continue
            lr = np.median(np.log(a[good]) - np.log(b[good]), 0)     # log gain_i - log gain_j
            pairs[(names[i], names[j])] = (int(good.sum()), lr.round(3).tolist())
            r = np.zeros(n); r[i] = 1; r[j] = -1
            rows.append(r); rhs.append(lr); w.append(np.sqrt(good.sum()))
    A = np.array(rows) * np.array(w)[:, None]; B = np.array(rhs) * np.array(w)[:, None]
    A = np.vstack([A, np.ones(n) * 1e3]); B = np.vstack([B, np.zeros(3)])
    lg, *_ = np.linalg.lstsq(A, B, rcond=None)
    return {names[c]: np.exp(lg[c]) for c in range(n)}, pairs

def main(rig_path, pairs_folder=None, lidar_on=True):
    rec = Reconstructor.load(default_model_dir(), threads=2)
    rig = load_rig(rig_path)
    images = [as_rgb(im, c) for im, c in zip(rig.load_images(), rig.cameras)]
    lidar = load_lidar(rig).points if lidar_on else None
    res = {}
    # pass 1: baseline, and the gains
    scene0 = rec.reconstruct(rig, images=images, lidar=lidar)
    gains, pairs = estimate()
    res["gains"] = {k: v.round(3).tolist() for k, v in gains.items()}
    res["pairs"] = {f"{a}<-{b}": v for (a, b), v in pairs.items()}
    # pass 2: harmonised
    cap.update(parts=[], details=[], cams=[])
    GAINS.update(gains)
    if WHOLE[0] and "min" in sys.argv:     # the darkest camera as the reference: harmonised images stay <= 1
        lo = np.min(np.stack(list(gains.values())), 0)
        gains = {k: v / lo for k, v in gains.items()}
        GAINS.update(gains)
    if WHOLE[0]:
        images_h = [(im / gains[c.name][None, None, :]).astype(np.float32) for im, c in zip(images, rig.cameras)]
    else:
        images_h = images
    scene1 = rec.reconstruct(rig, images=images_h, lidar=lidar)
    out = {"base": [], "harm": [], "harm_regain": []}
    for cam, gt in zip(rig.cameras, images):
        r0 = realeval._render_rgb(scene0, cam); r1 = np.clip(render_raw(scene1, cam), 0, None)
        out["base"].append(realeval.image_metrics(r0, gt))
        out["harm"].append(realeval.image_metrics(np.clip(r1, 0, 1), gt))
        out["harm_regain"].append(realeval.image_metrics(np.clip(r1 * gains[cam.name], 0, 1), gt))
    res["inputs"] = {k: {m: float(np.mean([x[m] for x in v])) for m in v[0]} for k, v in out.items()}
    res["inputs_per_cam"] = {k: [round(x["psnr"], 2) for x in v] for k, v in out.items()}
    return res, scene0, scene1, gains

if __name__ == "__main__":
    WHOLE[0] = "whole" in sys.argv
    res, *_ = main(sys.argv[1], lidar_on="off" not in sys.argv)
    print(json.dumps(res, indent=1))
