"""Colour/anchor parallax of the pixel-Gaussian placements, measured with ground-truth depth on synthetic scenes.

For each fine-lattice pixel (k_o = 4) seen by camera n, X = the point camera n sees there (GT depth). The colour
path samples X's colour; "camera_ray" anchors the Gaussian at X, "cylinder_ray" at X's horizontal radius on the
cylinder ray. Prints the reprojection error (pixels at 400 wide) and distance of the cylinder_ray anchor from X.

    .venv/bin/python docs/runs/cpu_2026-11-23/parallax.py      (reads data/train/scene_00000[0-4])
"""
import json
from pathlib import Path

import numpy as np
from xyzcyl.model_export.config import preset
from xyzcyl.runtime.lifting import LiftingParams, build_lifting_inputs
from xyzcyl.runtime.rig import load_rig, read_image

cfg = preset("cpu"); cfg = cfg.replace(pixel=cfg.pixel.replace(k_out=4))
res = []
for i in range(5):
    folder = f"data/train/scene_{i:06d}"
    rig = load_rig(folder + "/rig.json")
    doc = json.loads(Path(folder, "rig.json").read_text())
    p = LiftingParams.from_config_dict(cfg.to_dict())
    inp = build_lifting_inputs(rig, p)
    spec = p.spec(rig, "pixel")
    g, sel = inp["grid_pixc"], inp["sel_pixc"]
    centre = spec.centre
    dirs = inp["pix_dirs"]
    for n, cam in enumerate(rig.cameras):
        m = sel[n] > 0
        d = read_image(Path(folder) / doc["cameras"][n]["depth"], "d", channels=1, scale=False)[..., 0]
        u = (g[n][..., 0] + 1) * cam.width / 2 - 0.5; v = (g[n][..., 1] + 1) * cam.height / 2 - 0.5
        ui, vi = np.clip(np.round(u).astype(int), 0, cam.width - 1), np.clip(np.round(v).astype(int), 0, cam.height - 1)
        z = d[vi, ui]
        ok = m & (z > 0) & (z < 80)
        uu, vv, zz = u[ok], v[ok], z[ok]
        X = (cam.cam_to_ego @ np.stack([zz * (uu - cam.K[0,2]) / cam.K[0,0], zz * (vv - cam.K[1,2]) / cam.K[1,1], zz, np.ones_like(zz)]))[:3].T
        r = np.hypot(X[:, 0] - centre[0], X[:, 1] - centre[1])
        A = centre + r[:, None] * dirs[ok]
        uv, _, front = cam.project(A)
        err = np.hypot(uv[:, 0] - uu, uv[:, 1] - vv) * 400 / cam.width
        res.append(np.stack([err, np.linalg.norm(A - X, axis=1)], 1))
e = np.concatenate(res)
px, m = e[:, 0], e[:, 1]
print(f"cylinder_ray anchor vs camera point: reprojection px @400 wide: median {np.median(px):.2f} "
      f"p90 {np.percentile(px, 90):.2f} p99 {np.percentile(px, 99):.2f}; metres median {np.median(m):.3f} "
      f"p90 {np.percentile(m, 90):.3f}")
