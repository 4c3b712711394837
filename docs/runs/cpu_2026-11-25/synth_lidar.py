"""Pseudo-LiDAR for synthetic scenes: the same depth check as the real rigs (`xyzcyl lidar-eval`), on scenes whose
true depth is known. Each input camera's ground-truth depth, every STEP-th pixel in both directions, depth <= 80 m
(sky left out), is unprojected to ego points (docs/data.md: cam_to_ego @ [z inv(K) [u, v, 1], 1]); the points are
saved as SCENE/lidar.npy and SCENE/rig_lidar.json is the scene's rig.json with a lidar block. Unlike a real sweep
these points are exactly what the cameras see (no LiDAR-camera parallax).
    .venv/bin/python docs/runs/cpu_2026-11-25/synth_lidar.py DATA_DIR [DATA_DIR ...]"""
import json
import sys
from pathlib import Path

import numpy as np
from xyzcyl.runtime.rig import load_rig

STEP = 4
for data in sys.argv[1:]:
    for scene in sorted(Path(data).glob("scene_*")):
        rig = load_rig(scene / "rig.json")
        pts = []
        for cam, d in zip(rig.cameras, rig.load_depths()):
            v, u = np.mgrid[0:cam.height:STEP, 0:cam.width:STEP]
            z = d[v, u]
            ok = (z > 0) & (z <= 80.0)
            uv = np.stack([u[ok], v[ok]], axis=-1).astype(np.float64)
            o, dirs = cam.pixel_rays(uv)
            # pixel_rays gives unit directions; scale so the camera-frame z equals the stored depth
            zc = dirs @ cam.rotation[:, 2]
            pts.append(o + dirs * (z[ok] / zc)[:, None])
        np.save(scene / "lidar.npy", np.concatenate(pts).astype(np.float32))
        doc = json.loads((scene / "rig.json").read_text())
        doc["lidar"] = {"file": "lidar.npy", "format": "pseudo-LiDAR: ground-truth depth of the input cameras, "
                        f"every {STEP}th pixel, ego frame"}
        (scene / "rig_lidar.json").write_text(json.dumps(doc, indent=1))
        print(scene, sum(len(p) for p in pts))
