"""Per input camera of the ego-forward views: the mean over views of A - B (PSNR, dB; colour error; depth PCC) for
pairs of `xyzcyl eval` report folders on the same views.
    .venv/bin/python docs/runs/cpu_2026-11-25_final/per_camera.py A1 B1 [A2 B2 ...]"""
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from paired import load_views

print("| A - B | rig | camera | views | PSNR (dB) | colour error | depth PCC |")
print("| --- | --- | --- | ---: | ---: | ---: | ---: |")
args = sys.argv[1:]
for a_dir, b_dir in zip(args[::2], args[1::2]):
    a, b = load_views(Path(a_dir)), load_views(Path(b_dir))
    per = defaultdict(list)
    for key, va in a.items():
        vb = b.get(key)
        if key[1] != "ego-forward" or vb is None:
            continue
        cam = key[3].rsplit("_", 1)[0]   # views are CAMERA_tK
        per[(va["rig"], cam)].append([va[m] - vb[m] for m in ("psnr", "colour_err", "pcc")])
    for (rig, cam), d in sorted(per.items()):
        d = np.asarray(d, float)
        m = d.mean(0)
        print(f"| {Path(a_dir).name} - {Path(b_dir).name} | {rig} | {cam} | {len(d)} | {m[0]:+.2f} | {m[1]:+.4f} | "
              f"{m[2]:+.3f} |")
