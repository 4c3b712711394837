"""The table of docs/results.md "Depth against LiDAR" from lidar_runs.sh's JSON files (RUNS=runs/lidar).
Synthetic rows: the mean over the 5 scenes of each scene's all-camera figures.
    .venv/bin/python docs/runs/cpu_2026-11-25/lidar_table.py [RUNS] > docs/runs/cpu_2026-11-25/lidar_table.md"""
import json
import sys
from pathlib import Path

import numpy as np

runs = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/lidar")
KEYS = ("abs_rel", "rmse", "delta1", "median_ratio", "covered")
rows = []
for model in ("1.2.0", "1.1.0", "oracle"):
    for data, label in (("nuscenes_ca9a282c", "real nuScenes (LiDAR)"), ("pandaset_002_00", "real PandaSet (LiDAR)"),
                        ("lidar_val5", "synthetic nuScenes-like, 5 scenes (true depth)"),
                        ("lidar_val5_pandaset", "synthetic PandaSet-like, 5 scenes (true depth)")):
        files = sorted(runs.glob(f"{model}_{data}*.json"))
        if data.startswith("lidar_val5") and not data.endswith("pandaset"):
            files = [f for f in files if "pandaset" not in f.name]
        if not files:
            continue
        docs = [json.loads(f.read_text()) for f in files]
        vals = {k: float(np.mean([d["all"][k] for d in docs])) for k in KEYS}
        near = float(np.mean([d["ranges"][0]["median_ratio"] for d in docs if d["ranges"][0]["points"]]))
        far = float(np.mean([d["ranges"][2]["median_ratio"] for d in docs if d["ranges"][2]["points"]]))
        rows.append((model, label, vals, near, far, sum(d["all"]["points"] for d in docs)))
print("| model | data | AbsRel | RMSE m | δ < 1.25 | median ratio | ratio 0-10 m | ratio 20-40 m | covered | points |")
print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for model, label, v, near, far, n in rows:
    name = "oracle (true depth in)" if model == "oracle" else model
    print(f"| {name} | {label} | {v['abs_rel']:.3f} | {v['rmse']:.2f} | {v['delta1']:.3f} | {v['median_ratio']:.3f} | "
          f"{near:.3f} | {far:.3f} | {v['covered']:.3f} | {n} |")
