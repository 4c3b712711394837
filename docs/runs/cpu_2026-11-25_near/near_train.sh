#!/usr/bin/env bash
# Stage 2f (issue 10, docs/results.md "Cars beside the ego"): does traffic beside the ego in the training data fix
# the real rigs' near depth? Generator v1 keeps every car >= 8 m from the ego (6 m discs), while real rigs see
# parked cars 2-3 m from a side camera; `xyzcyl data synth --near-cars P` lifts that (docs/data.md).
# Two runs from the shipped 1.2.0 (recovered by `xyzcyl import-model`), side by side, one thread each, the same
# recipe as lidar_train.sh (warm restart lr 3e-4, warm-up 30, cosine; 4 targets at half size; --camera-aug 0.5;
# --camera-drop 0.5; seed 3), on 350 scenes each:
#   "near": data/train (200, v1) + data/train_near (150 of seed 2 with --near-cars 1: half the scenes have them)
#   "ctrl": data/train (200, v1) + data/train_s2   (the same 150 streets of seed 2 without them)
# Resumable: rerun after a kill (finished runs are skipped).
#   bash docs/runs/cpu_2026-11-25_near/near_train.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu6}
RUNS=${RUNS-"near ctrl"}
STEPS=${STEPS:-1200}
declare -A EXTRA=([near]="data/train_near" [ctrl]="data/train_s2")
mkdir -p "$OUT"
$X data synth --out data/train --scenes 200 --seed 0 --voxels 0.8,1.6 --quiet --workers 2   # run.sh's training set
$X data synth --out data/val --scenes 50 --seed 1 --voxels 0.8,1.6 --quiet --workers 2      # and validation set
$X data synth --out data/train_near --scenes 150 --seed 2 --voxels 0.8,1.6 --near-cars 1 --quiet --workers 2
$X data synth --out data/train_s2 --scenes 150 --seed 2 --voxels 0.8,1.6 --quiet --workers 2
BASE=runs/cpu5/base_1.2.0.pt
if [ ! -f "$BASE" ]; then mkdir -p runs/cpu5; $X import-model models/xyzcyl-cpu-v1 --out "$BASE" --quiet; fi
pids=""
for run in $RUNS; do
  out="$OUT/render_$run"
  if [ -f "$out/render.pt" ]; then continue; fi
  resume=""
  if [ -f "$out/last.pt" ]; then resume="--resume"; fi
  $X train --init "$BASE" --ablation no-volume --data data/train --data "${EXTRA[$run]}" --camera-drop 0.5 \
    --val data/val --stage render --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 \
    --steps "$STEPS" --lr 3e-4 --warmup 30 --seed 3 --val-every 200 --val-scenes 4 --out "$out" \
    --threads 1 --quiet $resume >> "$out.log" 2>&1 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done
echo done
