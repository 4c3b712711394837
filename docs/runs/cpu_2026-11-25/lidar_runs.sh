#!/usr/bin/env bash
# The depth check (`xyzcyl lidar-eval`) of the shipped model (1.2.0) and of 1.1.0 (models/ at commit 6b1e799) on the
# real rigs (LiDAR sweeps) and on 5 synthetic scenes of the nuScenes-like and PandaSet-like rigs (pseudo-LiDAR from
# their true depth, synth_lidar.py), plus the oracle (the true depth files as input) on the synthetic ones.
#   bash docs/runs/cpu_2026-11-25/lidar_runs.sh   (writes OUT=runs/lidar/*.json; about 5 min on 2 cores)
set -euo pipefail
OUT=${OUT:-runs/lidar}
REAL=${REAL:-../shared/data/real}
mkdir -p "$OUT"
if [ ! -d "$OUT/m110/models/xyzcyl-cpu-v1" ]; then
  mkdir -p "$OUT/m110" && git archive 6b1e799 models/xyzcyl-cpu-v1 | tar -x -C "$OUT/m110"
fi
if [ ! -d data/lidar_val5 ]; then
  .venv/bin/xyzcyl data synth --out data/lidar_val5 --scenes 5 --seed 1 --targets "" --quiet
  .venv/bin/xyzcyl data synth --out data/lidar_val5_pandaset --rig pandaset --scenes 5 --seed 1 --targets "" --quiet
  .venv/bin/python docs/runs/cpu_2026-11-25/synth_lidar.py data/lidar_val5 data/lidar_val5_pandaset
fi
for model in 1.2.0 1.1.0; do
  dir=models/xyzcyl-cpu-v1; [ "$model" = 1.1.0 ] && dir=$OUT/m110/models/xyzcyl-cpu-v1
  for rig in nuscenes_ca9a282c pandaset_002_00; do
    .venv/bin/xyzcyl lidar-eval "$REAL/$rig/rig.json" --model "$dir" --json "$OUT/${model}_$rig.json" \
      --picture "$OUT/${model}_$rig.jpg" --quiet > /dev/null
  done
  for set in lidar_val5 lidar_val5_pandaset; do
    for s in data/$set/scene_*; do
      .venv/bin/xyzcyl lidar-eval "$s/rig_lidar.json" --model "$dir" --json "$OUT/${model}_${set}_$(basename "$s").json" \
        --quiet > /dev/null
      if [ "$model" = 1.2.0 ]; then
        .venv/bin/xyzcyl lidar-eval "$s/rig_lidar.json" --model "$dir" --use-depth \
          --json "$OUT/oracle_${set}_$(basename "$s").json" --quiet > /dev/null
      fi
    done
  done
done
echo done
