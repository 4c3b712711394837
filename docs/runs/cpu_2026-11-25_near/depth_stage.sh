#!/usr/bin/env bash
# Stage depth (docs/training.md), docs/results.md "Cars beside the ego": the depth head alone, STEPS steps on its
# log-L1 (lr 1e-3, warm-up 50, cosine), from INIT (default: the shipped 1.2.0, runs/cpu5/base_1.2.0.pt, which
# near_train.sh recovers with `xyzcyl import-model`), on data/train + data/train_near (near_train.sh makes them),
# inputs with the real-camera effects at strength 0.5 as in stage 2.
# Resumable: rerun after a kill.
#   bash docs/runs/cpu_2026-11-25_near/depth_stage.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu6/depth_stage}
INIT=${INIT:-runs/cpu5/base_1.2.0.pt}
STEPS=${STEPS:-1500}
if [ -f "$OUT/depth.pt" ]; then echo "done: $OUT/depth.pt"; exit 0; fi
resume=""
if [ -f "$OUT/last.pt" ]; then resume="--resume"; fi
$X train --stage depth --init "$INIT" --data data/train --data data/train_near --val data/val --val-scenes 8 \
  --val-every 500 --camera-aug 0.5 --steps "$STEPS" --lr 1e-3 --warmup 50 --seed 4 --out "$OUT" \
  --threads "${THREADS:-1}" --quiet $resume
