#!/usr/bin/env bash
# depth_only.py on the shipped 1.2.0 (runs/cpu5/base_1.2.0.pt, `xyzcyl import-model`), 800 steps each:
#   depth_near: data/train + data/train_near (half the new scenes with cars beside the ego)
#   depth_ctrl: data/train + data/train_s2 (the same streets without them)
#   bash docs/runs/cpu_2026-11-25_near/depth_only.sh   (near_train.sh makes the data)
set -euo pipefail
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu6}
STEPS=${STEPS:-800}
declare -A EXTRA=([near]=data/train_near [ctrl]=data/train_s2)
for run in near ctrl; do
  if [ ! -f "$OUT/depth_$run.pt" ]; then
    $P docs/runs/cpu_2026-11-25_near/depth_only.py runs/cpu5/base_1.2.0.pt "$OUT/depth_$run.pt" --data data/train \
      --data "${EXTRA[$run]}" --steps "$STEPS"
  fi
done
