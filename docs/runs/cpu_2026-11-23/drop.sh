#!/usr/bin/env bash
# Stage 2d (issue 10, docs/results.md "Focal-aware depth"): v1.1.0 (the 1,000-step no-volume run of continue.sh)
# continued DROP_STEPS more steps on the 6-camera training data, with --camera-drop 0.5 ("drop": half the scenes
# lose 1-2 input cameras adjacent in azimuth, targets kept) and, as its control, the same run without the drop
# ("nodrop"; stopped at step 233 for the focal run and not reported). Same recipe as mixed.sh
# otherwise (warm restart lr 3e-4, warm-up 50, cosine; seed 2; 4 targets at half size, --camera-aug 0.5).
# "focal" is "drop" with the focal-aware depth head (--depth-focal-ref nuscenes: the head's depth scaled by each
# camera's normalised focal over the nuScenes front camera's; docs/results.md "Focal-aware depth"), so drop vs
# focal is that one change. "zoom" is "focal" with --lens-zoom 0.5 (narrower-lens crops of half the input
# cameras); it was trained with this command line and evaluated on data/val_waymo only:
#   RUNS=zoom bash docs/runs/cpu_2026-11-23/drop.sh   (reported: its data/val_waymo evaluation; it skipped real.py)
# The 5-camera (waymo) rig stays held out. Resumable: rerun after a kill.
#   RUNS="drop focal" bash docs/runs/cpu_2026-11-23/drop.sh   (runs side by side, then evals and real rigs)
#   EVAL_ONLY=1 RUNS="drop focal" bash docs/runs/cpu_2026-11-23/drop.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
D=docs/runs/cpu_2026-11-23
BASE=${BASE:-runs/cpu2b/render_no-volume/render.pt}
OUT=${OUT:-runs/cpu4}
RUNS=${RUNS-"drop nodrop"}
DROP_STEPS=${DROP_STEPS:-500}
declare -A DROP=([drop]=0.5 [nodrop]=0 [focal]=0.5 [zoom]=0.5)
declare -A EXTRA=([drop]="" [nodrop]="" [focal]="--depth-focal-ref nuscenes"
                  [zoom]="--depth-focal-ref nuscenes --lens-zoom 0.5")
mkdir -p "$OUT"
if [ -z "${EVAL_ONLY:-}" ]; then
  pids=""
  for run in $RUNS; do
    out="$OUT/render_$run"
    if [ -f "$out/render.pt" ]; then continue; fi
    resume=""
    if [ -f "$out/last.pt" ]; then resume="--resume"; fi
    # shellcheck disable=SC2086
    $X train --init "$BASE" --pixel-upsample 4 --ablation no-volume ${EXTRA[$run]} --data data/train \
      --camera-drop "${DROP[$run]}" \
      --val data/val --stage render --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 \
      --steps "$DROP_STEPS" --lr 3e-4 --warmup 50 --seed 2 --val-every 100 --val-scenes 4 --out "$out" \
      --threads 1 --quiet $resume >> "$out.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
fi
sha256sum "$OUT"/render_*/render.pt
for data in val val_waymo; do   # each run on the 6-camera set and the held-out 5-camera rig
  pids=""
  for run in $RUNS; do
    $X eval --checkpoint "$OUT/render_$run/render.pt" --data "data/$data" --setting ego-forward,ego-inward \
      --out "$OUT/eval/${run}_$data" --threads 1 --quiet > "$OUT/eval_${run}_$data.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
done
args=()
for run in $RUNS; do args+=(--checkpoint "$run=$OUT/render_$run/render.pt"); done
$P $D/real.py --out $D/real_drop --checkpoint "v1.1.0=$BASE" "${args[@]}"
