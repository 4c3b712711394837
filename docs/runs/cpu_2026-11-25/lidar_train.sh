#!/usr/bin/env bash
# Stage 2e (issue 10, docs/results.md "Training with a LiDAR depth input"): the shipped 1.2.0 continued STEPS more
# steps, side by side, one thread each. Its checkpoint was gone, so it is first recovered from the model folder
# (`xyzcyl import-model`: the exact weights, verified by re-export). Same recipe as drop.sh's "focal" run
# (warm restart lr 3e-4, warm-up 30, cosine; 4 targets at half size; --camera-aug 0.5; --camera-drop 0.5) but seed 3:
#   "lidar": --lidar-input 0.5 (half the scenes carry a simulated LiDAR sweep, made into the depth input as the
#            runtime makes a real one: the model learns to use it);
#   "more":  the control, the same steps without it.
# Resumable: rerun after a kill (finished runs are skipped).
#   bash docs/runs/cpu_2026-11-25/lidar_train.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu5}
RUNS=${RUNS-"lidar more"}
STEPS=${STEPS:-300}
declare -A EXTRA=([lidar]="--lidar-input 0.5" [more]="")
mkdir -p "$OUT"
$X data synth --out data/train --scenes 200 --seed 0 --voxels 0.8,1.6 --quiet   # run.sh's training set
$X data synth --out data/val --scenes 50 --seed 1 --voxels 0.8,1.6 --quiet      # and validation set
BASE=$OUT/base_1.2.0.pt
if [ ! -f "$BASE" ]; then $X import-model models/xyzcyl-cpu-v1 --out "$BASE" --quiet; fi
pids=""
for run in $RUNS; do
  out="$OUT/render_$run"
  if [ -f "$out/render.pt" ]; then continue; fi
  resume=""
  if [ -f "$out/last.pt" ]; then resume="--resume"; fi
  # shellcheck disable=SC2086
  $X train --init "$BASE" --ablation no-volume ${EXTRA[$run]} --data data/train --camera-drop 0.5 \
    --val data/val --stage render --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 \
    --steps "$STEPS" --lr 3e-4 --warmup 30 --seed 3 --val-every 100 --val-scenes 4 --out "$out" \
    --threads 1 --quiet $resume >> "$out.log" 2>&1 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done
echo done
