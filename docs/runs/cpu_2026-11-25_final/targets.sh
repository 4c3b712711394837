#!/usr/bin/env bash
# Issue 10's targets measured for the shipped 1.3.0 (docs/results.md "Issue 10: the targets, for 1.3.0"): the
# held-out 7- and 8-camera rigs (the 5-camera rig has runs/cpu6/eval/readapt2_waymo), 1.2.0 on the same three rigs
# (paired: where 1.3.0 lost on the 5-camera rig), and the unprojection baselines on the 50 validation scenes (1.3.0's
# depth head, and the ground-truth-depth oracle). Two evaluations side by side, one thread each. Reruns skip what
# exists.
#   bash docs/runs/cpu_2026-11-25_final/targets.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu7}
NEW=${NEW:-runs/cpu6/render_readapt2/render.pt}   # 1.3.0
OLD=${OLD:-runs/cpu5/base_1.2.0.pt}               # 1.2.0 (xyzcyl import-model of the 1.2.0 folder)
mkdir -p "$OUT/eval"
# the held-out rigs of run.sh (never trained on): scenes 0-9 of the validation seed
declare -A RIGS=([waymo]=waymo [argoverse]=argoverse [ring8]=docs/runs/cpu_2026-11-23/ring8.json)
for r in waymo argoverse ring8; do
  [ -f "data/val_$r/index.json" ] || $X data synth --out "data/val_$r" --scenes 10 --seed 1 --rig "${RIGS[$r]}" \
    --voxels 1.6 --quiet
done
ev() {  # ev NAME ARGS...: one evaluation unless its report exists
  local name=$1; shift
  if ! ls "$OUT/eval/$name"/*.json > /dev/null 2>&1; then
    $X eval "$@" --setting ego-forward,ego-inward --out "$OUT/eval/$name" --threads 1 --quiet > "$OUT/eval_$name.log" 2>&1
  fi
}
jobs=(
  "new_argoverse --checkpoint $NEW --data data/val_argoverse"
  "new_ring8 --checkpoint $NEW --data data/val_ring8"
  "old_waymo --checkpoint $OLD --data data/val_waymo"
  "old_argoverse --checkpoint $OLD --data data/val_argoverse"
  "old_ring8 --checkpoint $OLD --data data/val_ring8"
  "unproject --baseline unproject --checkpoint $NEW --data data/val"
  "oracle --baseline unproject-gt-depth --data data/val"
  "oracle_waymo --baseline unproject-gt-depth --data data/val_waymo"
)
i=0
for j in "${jobs[@]}"; do   # two at a time
  # shellcheck disable=SC2086
  ev $j &
  i=$((i + 1))
  if (( i % 2 == 0 )); then wait; fi
done
wait
echo done
