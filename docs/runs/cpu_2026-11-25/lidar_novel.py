"""Does LiDAR depth help novel views? On synthetic scenes with ego-forward targets (`xyzcyl data synth --targets
ego-forward`, then synth_lidar.py for the pseudo-LiDAR), the shipped ONNX model through the runtime:
reconstruct without depth, and with half of the pseudo-LiDAR points as the depth input (`reconstruct(lidar=...)`,
the same random half rule as `xyzcyl lidar-eval --holdout 0.5`); render every ego-forward target camera (the rig
moved forward, unseen poses) and score PSNR, PSNR over non-sky pixels, and the depth AbsRel against the target's
true depth (non-sky pixels with alpha >= 0.5, depth <= 80 m).
    .venv/bin/python docs/runs/cpu_2026-11-25/lidar_novel.py data/lidar_val5_t > docs/runs/cpu_2026-11-25/lidar_novel.json"""
import json
import sys
from pathlib import Path

import numpy as np
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.runtime.rig import Rig, load_rig
from xyzcyl.runtime.scene import render_view, rig_camera

rec = Reconstructor.load(sys.argv[2] if len(sys.argv) > 2 else "models/xyzcyl-cpu-v1", threads=2)
rows = []
for scene_dir in sorted(Path(sys.argv[1]).glob("scene_*")):
    rig = load_rig(scene_dir / "rig.json")
    pts = np.load(scene_dir / "lidar.npy").astype(np.float64)
    pick = np.random.default_rng(0).random(len(pts)) < 0.5
    targets = Rig.from_dict(json.loads((scene_dir / "targets.json").read_text())["settings"]["ego-forward"],
                            root=scene_dir)
    gts, gdepths = targets.load_images(), targets.load_depths()
    for label, lidar in (("none", None), ("lidar", pts[pick])):
        scene = rec.reconstruct(rig, depths=[None] * len(rig), lidar=lidar)
        for cam, gt, gd in zip(targets.cameras, gts, gdepths):
            rgb, depth, alpha = render_view(scene, rig_camera(cam))
            rgb = np.clip(rgb, 0, 1)
            fg = gd > 0
            ok = fg & (gd <= 80) & (alpha >= 0.5)
            rows.append({"scene": scene_dir.name, "camera": cam.name, "input": label,
                         "psnr": float(10 * np.log10(1 / np.mean((rgb - gt) ** 2))),
                         "psnr_fg": float(10 * np.log10(1 / np.mean((rgb[fg] - gt[fg]) ** 2))),
                         "abs_rel": float(np.mean(np.abs(depth[ok] - gd[ok]) / gd[ok]))})
out = {}
for label in ("none", "lidar"):
    r = [x for x in rows if x["input"] == label]
    out[label] = {k: round(float(np.mean([x[k] for x in r])), 3) for k in ("psnr", "psnr_fg", "abs_rel")}
    out[label]["views"] = len(r)
d = [a["psnr"] - b["psnr"] for a, b in zip([x for x in rows if x["input"] == "lidar"],
                                          [x for x in rows if x["input"] == "none"])]
out["lidar_minus_none_psnr"] = {"mean": round(float(np.mean(d)), 3), "views_better": int(np.sum(np.array(d) > 0)),
                                "views": len(d)}
print(json.dumps({"summary": out, "rows": rows}, indent=1))
