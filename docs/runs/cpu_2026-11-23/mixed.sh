#!/usr/bin/env bash
# Stage 2c (issue 10, docs/results.md "Mixed rigs"): the 1,000-step runs of continue.sh continued for MIX_STEPS
# more steps on mixed rigs: the nuScenes-like training set plus 100 PandaSet-like (6 cameras, seed 3) and 100
# ONCE-like (6 cameras at 90 deg, seed 4) scenes, and half the scenes lose 1-2 adjacent input cameras
# (--camera-drop 0.5: a rig with a blind side). The 5-camera (waymo), 7-camera (argoverse) and 8-camera (ring8)
# rigs stay held out: never trained on. Same recipe as continue.sh otherwise (warm restart lr 3e-4, warm-up 50,
# cosine; seed 2). Resumable: rerun after a kill.
#   MIX="full no-volume" bash docs/runs/cpu_2026-11-23/mixed.sh          (runs of MIX side by side, then evals)
#   EVAL_ONLY=1 MIX="full no-volume" bash docs/runs/cpu_2026-11-23/mixed.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
RUNS=${RUNS:-runs/cpu2b}
OUT=${OUT:-runs/cpu3}
MIX=${MIX-"full no-volume"}
MIX_STEPS=${MIX_STEPS:-300}
declare -A EXTRA=([full]="" [no-volume]="--ablation no-volume")
mkdir -p "$OUT"
$X data synth --out data/train_pandaset --scenes 100 --seed 3 --rig pandaset --voxels 1.6 --quiet
$X data synth --out data/train_once --scenes 100 --seed 4 --rig once --voxels 1.6 --quiet
if [ -z "${EVAL_ONLY:-}" ]; then
  pids=""
  for run in $MIX; do
    out="$OUT/render_$run"
    if [ -f "$out/render.pt" ]; then continue; fi
    resume=""
    if [ -f "$out/last.pt" ]; then resume="--resume"; fi
    # shellcheck disable=SC2086
    $X train --init "$RUNS/render_$run/render.pt" --pixel-upsample 4 ${EXTRA[$run]} --data data/train \
      --data data/train_pandaset --data data/train_once --camera-drop 0.5 --val data/val --stage render \
      --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 --steps "$MIX_STEPS" --lr 3e-4 --warmup 50 \
      --seed 2 --val-every 100 --val-scenes 4 --out "$out" --threads 1 --quiet $resume > "$out.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
fi
sha256sum "$OUT"/render_*/render.pt
n=$(echo $MIX | wc -w)
for data in val val_waymo val_argoverse val_ring8; do   # each run on the 6-camera set and the held-out rigs
  pids=""
  for run in $MIX; do
    $X eval --checkpoint "$OUT/render_$run/render.pt" --data "data/$data" --setting ego-forward,ego-inward \
      --out "$OUT/eval/${run}_$data" --threads $(( n > 1 ? 1 : 2 )) --quiet > "$OUT/eval_${run}_$data.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
done
