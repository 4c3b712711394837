#!/usr/bin/env bash
# The 5-camera A/B of docs/results.md "Issue 10: the targets, for 1.3.0": 1.3.0 lost 0.46 dB on the held-out
# 5-camera rig's ego-forward views against 1.2.0 (every camera, every scene; depth scale and PCC unchanged), after
# 600 stage-2 steps that saw only the 6-camera rig's 65/89 deg lenses. Two runs from 1.3.0, STEPS stage-2 steps
# each with readapt.sh's recipe (warm restart lr 3e-4, warm-up 30, cosine; 4 targets at half size;
# --camera-aug 0.5; --camera-drop 0.5; data/train + data/train_near), seed 7, side by side, one thread each:
#   ctrl3: that recipe;
#   zoom3: the same plus --lens-zoom 0.25 (a quarter of the input cameras narrowed to 65/U(1, 1.4) deg).
# Resumable: rerun after a kill.
#   bash docs/runs/cpu_2026-11-25_final/zoom.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu7}
INIT=${INIT:-runs/cpu6/render_readapt2/render.pt}   # 1.3.0
STEPS=${STEPS:-300}
declare -A EXTRA=([ctrl3]="" [zoom3]="--lens-zoom 0.25")
pids=""
for run in ${RUNS:-ctrl3 zoom3}; do
  out="$OUT/render_$run"
  [ -f "$out/render.pt" ] && continue
  resume=""
  [ -f "$out/last.pt" ] && resume="--resume"
  # shellcheck disable=SC2086
  $X train --init "$INIT" --data data/train --data data/train_near --camera-drop 0.5 --val data/val --stage render \
    --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 ${EXTRA[$run]} --steps "$STEPS" --lr 3e-4 \
    --warmup 30 --seed 7 --val-every 150 --val-scenes 4 --out "$out" --threads 1 --quiet $resume > "$out.log" 2>&1 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done
sha256sum "$OUT"/render_*/render.pt
