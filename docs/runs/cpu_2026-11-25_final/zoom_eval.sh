#!/usr/bin/env bash
# zoom.sh's runs measured like 1.3.0: `xyzcyl eval` on the 50 validation scenes and the held-out 5-camera rig
# (10 scenes), two evaluations at a time, one thread each; then the paired differences against 1.3.0
# (runs/cpu6/eval/readapt2, runs/cpu7/eval/new_waymo from targets.sh) into zoom_paired.txt.
#   bash docs/runs/cpu_2026-11-25_final/zoom_eval.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu7}
D=docs/runs/cpu_2026-11-25_final
for data in val_waymo val; do
  pids=""
  for run in ${RUNS:-ctrl3 zoom3}; do
    e="$OUT/eval/${run}_$data"
    if ! ls "$e"/*.json > /dev/null 2>&1; then
      $X eval --checkpoint "$OUT/render_$run/render.pt" --data "data/$data" --setting ego-forward,ego-inward \
        --out "$e" --threads 1 --quiet > "$e.log" 2>&1 &
      pids="$pids $!"
    fi
  done
  for p in $pids; do wait "$p"; done
done
for run in ${RUNS:-ctrl3 zoom3}; do
  $P docs/runs/paired.py "$OUT/eval/${run}_val" runs/cpu6/eval/readapt2
  $P docs/runs/paired.py "$OUT/eval/${run}_val_waymo" "$OUT/eval/new_waymo"
done > $D/zoom_paired.txt
cat $D/zoom_paired.txt
