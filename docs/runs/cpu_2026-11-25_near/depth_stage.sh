#!/usr/bin/env bash
# Stage depth (docs/training.md "Stage depth"), the candidate model of docs/results.md "Cars beside the ego": the
# depth head alone, STEPS steps on its log-L1 (lr 1e-3, warm-up 50, cosine), from INIT (default: near_train.sh's
# "near" run), on data/train + data/train_near, inputs with the real-camera effects at strength 0.5 as in stage 2.
# Resumable: rerun after a kill.
#   bash docs/runs/cpu_2026-11-25_near/depth_stage.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu6/depth_stage}
INIT=${INIT:-runs/cpu6/render_near/render.pt}
STEPS=${STEPS:-1500}
if [ -f "$OUT/depth.pt" ]; then echo "done: $OUT/depth.pt"; exit 0; fi
resume=""
if [ -f "$OUT/last.pt" ]; then resume="--resume"; fi
$X train --stage depth --init "$INIT" --data data/train --data data/train_near --val data/val --val-scenes 8 \
  --val-every 500 --camera-aug 0.5 --steps "$STEPS" --lr 1e-3 --warmup 50 --seed 4 --out "$OUT" \
  --threads "${THREADS:-1}" --quiet $resume
