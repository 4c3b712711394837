#!/usr/bin/env bash
# Stage 2 again after stage depth (docs/results.md "Cars beside the ego"): the depth stage's head alone made the
# novel views worse (ego-inward -0.8 dB: the pixel branch was fitted to the old head's depth), so the render modules
# are fitted again to the new head, STEPS steps with lidar_train.sh's recipe (warm restart lr 3e-4, warm-up 30,
# cosine; 4 targets at half size; --camera-aug 0.5; --camera-drop 0.5), seed 6, on data/train + data/train_near.
# Resumable.   bash docs/runs/cpu_2026-11-25_near/readapt.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu6/render_readapt}
INIT=${INIT:-runs/cpu6/depth_stage/depth.pt}
STEPS=${STEPS:-300}
if [ -f "$OUT/render.pt" ]; then echo "done: $OUT/render.pt"; exit 0; fi
resume=""
if [ -f "$OUT/last.pt" ]; then resume="--resume"; fi
$X train --init "$INIT" --data data/train --data data/train_near --camera-drop 0.5 --val data/val --stage render \
  --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 --steps "$STEPS" --lr 3e-4 --warmup 30 --seed 6 \
  --val-every 150 --val-scenes 4 --out "$OUT" --threads "${THREADS:-2}" --quiet $resume
