"""The depth table of docs/results.md "Cars beside the ego" from near_eval.sh's files: per model, AbsRel / δ < 1.25 /
median ratio at 0-10 m against the real rigs' LiDAR (the depth head alone, no LiDAR input), the same on the
synthetic pseudo-LiDAR sets (mean over 5 scenes of each rig), and the input-view PSNR on the real rigs.
    .venv/bin/python docs/runs/cpu_2026-11-25_near/near_table.py [RUNS/lidar] [real_lidar_models.json] > near_table.md"""
import json
import sys
from pathlib import Path

import numpy as np

runs = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/cpu6/lidar")
real_path = Path(sys.argv[2] if len(sys.argv) > 2 else "docs/runs/cpu_2026-11-25_near/real_lidar_models.json")
real = json.loads(real_path.read_text()) if real_path.is_file() and real_path.stat().st_size else {}
MODELS = {"base": ("1.2.0 (shipped)", "models/xyzcyl-cpu-v1"),
          "ctrl": ("ctrl: +1200 steps, v1 data", "runs/cpu6/m_ctrl"),
          "near": ("near: +1200 steps, new scenes with cars beside", "runs/cpu6/m_near"),
          "dctrl": ("dctrl: 1.2.0 + depth head alone 800 steps, v1 data", "runs/cpu6/m_dctrl"),
          "dnear": ("dnear: 1.2.0 + depth head alone 800 steps, cars beside", "runs/cpu6/m_dnear"),
          "readapt": ("readapt: 1.2.0 + stage depth 1500 + stage render 300", "runs/cpu6/m_readapt"),
          "readapt2": ("readapt2: readapt + stage render 300", "runs/cpu6/m_readapt2")}
DATA = (("nuscenes_ca9a282c", "real nuScenes"), ("pandaset_002_00", "real PandaSet"),
        ("lidar_val5_scene", "synthetic nuScenes-like, v1"), ("lidar_val5_pandaset", "synthetic PandaSet-like, v1"),
        ("lidar_val5_near_scene", "synthetic nuScenes-like, cars beside"),
        ("lidar_val5_near_pandaset", "synthetic PandaSet-like, cars beside"))


def fig(docs, key, rng=None):
    vals = [(d["ranges"][rng] if rng is not None else d["all"]) for d in docs]
    vals = [v[key] for v in vals if v["points"]]
    return float(np.mean(vals)) if vals else float("nan")


print("| model | data | AbsRel | δ < 1.25 | median ratio | AbsRel 0-10 m | ratio 0-10 m | points 0-10 m |")
print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
for model, (label, _) in MODELS.items():
    for key, name in DATA:
        docs = [json.loads(f.read_text()) for f in sorted(runs.glob(f"{model}_{key}*.json"))]
        if not docs:
            continue
        n0 = sum(d["ranges"][0]["points"] for d in docs)
        print(f"| {label} | {name} | {fig(docs, 'abs_rel'):.3f} | {fig(docs, 'delta1'):.3f} | "
              f"{fig(docs, 'median_ratio'):.3f} | {fig(docs, 'abs_rel', 0):.3f} | {fig(docs, 'median_ratio', 0):.3f} | "
              f"{n0} |")
print()
print("| model | real nuScenes input-view PSNR dB | real PandaSet input-view PSNR dB |")
print("| --- | ---: | ---: |")
for model, (label, folder) in MODELS.items():
    r = real.get(folder)
    if r:
        print(f"| {label} | {r['nuscenes_ca9a282c']['none']['psnr']:.2f} | {r['pandaset_002_00']['none']['psnr']:.2f} |")
