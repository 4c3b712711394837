"""The table of exposure_eval.sh: per model, the real rigs' AbsRel against LiDAR as posted and with the inputs
x0.5 / x1.5 (appearance_probe.py), and the mean AbsRel over the synthetic pseudo-LiDAR scenes.
    .venv/bin/python docs/runs/cpu_2026-11-25_final/exposure_table.py runs/cpu7 base ctrl expo"""
import json
import sys
from pathlib import Path

import numpy as np

out = Path(sys.argv[1])
print("| model | real nuScenes AbsRel (x0.5 / as posted / x1.5) | real PandaSet AbsRel (x0.5 / as posted / x1.5) "
      "| PandaSet 0-10 m ratio | synthetic AbsRel, v1 (nuScenes / PandaSet rig) | synthetic, cars beside |")
print("| --- | --- | --- | ---: | ---: | ---: |")
for model in sys.argv[2:]:
    rows = json.loads((out / "probe" / f"{model}.json").read_text())["rows"]
    get = {(r["rig"], r["inputs"]): r for r in rows}
    real = []
    for rig in ("nuscenes_ca9a282c", "pandaset_002_00"):
        real.append(" / ".join(f"{get[rig, k]['abs_rel']:.3f}" for k in ("exposure_0.5", "none", "exposure_1.5")))
    syn = []
    for sets in (("lidar_val5_scene", "lidar_val5_pandaset"), ("lidar_val5_near_scene", "lidar_val5_near_pandaset")):
        vals = []
        for s in sets:
            docs = [json.loads(p.read_text()) for p in sorted((out / "lidar").glob(f"{model}_{s}*.json"))]
            vals.append(np.mean([d["all"]["abs_rel"] for d in docs]) if docs else float("nan"))
        syn.append(" / ".join(f"{v:.3f}" for v in vals))
    print(f"| {model} | {real[0]} | {real[1]} | {get['pandaset_002_00', 'none']['ratio_0_10']:.2f} | {syn[0]} | "
          f"{syn[1]} |")
