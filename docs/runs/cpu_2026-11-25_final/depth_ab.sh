#!/usr/bin/env bash
# Stage-depth A/B runs of docs/results.md "Issue 10: the targets, for 1.3.0", from the shipped 1.3.0, STEPS steps
# each on data/train + data/train_near, seed 5, side by side, one thread each:
#   ctrl: the recipe of depth_stage.sh (--camera-aug 0.5: per camera exposure +-15 %, white balance, ...)
#   expo: the same plus --jitter 0.5 (per scene brightness, contrast and saturation x0.5..1.5) and --camera-aug 1
#         (per camera exposure +-30 %): appearance_probe.py found the real-rig depth follows the image brightness
#   zoom: the same as ctrl plus --lens-zoom 0.5: the depth stage alone cost the held-out 5-camera rig (50 deg
#         lenses) 0.46 dB on ego-forward views; the head then sees narrower lenses too
# Resumable: rerun after a kill.
#   RUNS="ctrl expo" bash docs/runs/cpu_2026-11-25_final/depth_ab.sh; RUNS=zoom bash ...
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu7}
INIT=${INIT:-runs/cpu6/render_readapt2/render.pt}   # 1.3.0
STEPS=${STEPS:-600}
declare -A AUG=([ctrl]="--camera-aug 0.5" [expo]="--camera-aug 1 --jitter 0.5" [zoom]="--camera-aug 0.5 --lens-zoom 0.5")
pids=""
for run in ${RUNS:-ctrl expo}; do
  out="$OUT/depth_$run"
  [ -f "$out/depth.pt" ] && continue
  resume=""
  [ -f "$out/last.pt" ] && resume="--resume"
  # shellcheck disable=SC2086
  $X train --stage depth --init "$INIT" --data data/train --data data/train_near --val data/val --val-scenes 8 \
    --val-every 300 ${AUG[$run]} --steps "$STEPS" --lr 1e-3 --warmup 50 --seed 5 --out "$out" --threads "${THREADS:-1}" --quiet \
    $resume > "$out.log" 2>&1 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done
sha256sum "$OUT"/depth_*/depth.pt
