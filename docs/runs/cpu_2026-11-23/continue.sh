#!/usr/bin/env bash
# Stage 2b (issue 10, docs/results.md "Longer runs"): every stage-2 run of run.sh continued for CONT_STEPS more
# steps from its own render.pt, with one recipe for all (warm restart: AdamW lr 3e-4, warm-up 50, cosine; data order
# seed 1, so the scenes come in a new order; same targets, sizes and real-camera effects as stage 2). A run of
# 500 + 500 steps. Resumable like run.sh: rerun after a kill.
#   CONT="full no-volume" bash docs/runs/cpu_2026-11-23/continue.sh    (after run.sh; runs of CONT side by side)
#   EVAL_ONLY=1 CONT="full no-volume" bash docs/runs/cpu_2026-11-23/continue.sh    (only the evaluations)
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
RUNS=${RUNS:-runs/cpu2}
OUT=${OUT:-runs/cpu2b}
CONT=${CONT-"full no-volume no-background"}   # CONT="" with POST=1: only the post block
CONT_STEPS=${CONT_STEPS:-500}
TARGETS=${TARGETS:-4}
declare -A EXTRA=([full]="--pixel-upsample 4" [no-rgb]="--pixel-upsample 4 --ablation no-rgb"
                  [k2]="--pixel-upsample 2" [no-volume]="--pixel-upsample 4 --ablation no-volume"
                  [no-pixel]="--pixel-upsample 4 --ablation no-pixel"
                  [no-background]="--pixel-upsample 4 --ablation no-background")
mkdir -p "$OUT"
if [ -z "${EVAL_ONLY:-}" ]; then
  pids=""
  for run in $CONT; do
    out="$OUT/render_$run"
    if [ -f "$out/render.pt" ]; then continue; fi
    resume=""
    if [ -f "$out/last.pt" ]; then resume="--resume"; fi
    # shellcheck disable=SC2086
    $X train --init "$RUNS/render_$run/render.pt" ${EXTRA[$run]} --data data/train --val data/val --stage render \
      --setting both --targets "$TARGETS" --target-scale 0.5 --camera-aug 0.5 --steps "$CONT_STEPS" --lr 3e-4 \
      --warmup 50 --seed 1 --val-every 100 --val-scenes 4 --out "$out" --threads 1 --quiet $resume \
      > "$out.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
fi
n=$(echo $CONT | wc -w)
pids=""
for run in $CONT; do   # side by side, the two cores shared among them
  $X eval --checkpoint "$OUT/render_$run/render.pt" --data data/val --setting ego-forward,ego-inward \
    --out "$OUT/eval/$run" --threads $(( n > 1 ? 1 : 2 )) --quiet > "$OUT/eval_$run.log" 2>&1 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done
sha256sum "$OUT"/render_*/render.pt

# after CONT="full no-volume" (and no-background): the shipped model (no-volume, 1000 steps) on the other rigs and
# the real rigs, the ego-car diagnostic, tables and pictures (docs/results.md "Longer runs")
if [ -n "${POST:-}" ]; then
  P=${P:-.venv/bin/python}
  D=docs/runs/cpu_2026-11-23
  SHIP=$OUT/render_no-volume/render.pt
  for r in waymo argoverse ring8; do
    $X eval --checkpoint "$SHIP" --data "data/val_$r" --setting ego-forward,ego-inward --out "$OUT/eval/rig_$r" \
      --threads 1 --quiet
  done
  $X eval --baseline unproject --checkpoint "$SHIP" --data data/val --setting ego-forward,ego-inward \
    --out "$OUT/eval/unproject" --threads 1 --quiet     # the unprojection baseline with the shipped depth head
  $P docs/runs/table.py "XYZCylinder (cpu, no volume, 1000 steps), 6 cameras=$OUT/eval/no-volume" \
    "5 cameras (waymo)=$OUT/eval/rig_waymo" "7 cameras (argoverse)=$OUT/eval/rig_argoverse" \
    "8 cameras (ring8.json)=$OUT/eval/rig_ring8" > $D/table_rigs_1000.md
  $P docs/runs/table.py "full, 1000 steps=$OUT/eval/full" "no volume, 1000 steps (shipped v1.1.0)=$OUT/eval/no-volume" \
    "no background, 1000 steps=$OUT/eval/no-background" "full, 500 steps (v1.0.0)=$RUNS/eval/full" \
    "no volume, 500 steps=$RUNS/eval/no-volume" "$OUT/eval/unproject" > $D/table_1000.md
  for pair in "full no-volume" "full no-background" "no-volume no-background" "no-volume unproject"; do
    set -- $pair
    $P docs/runs/paired.py "$OUT/eval/$1" "$OUT/eval/$2"
  done > $D/paired_1000.txt
  $P docs/runs/paired.py "$OUT/eval/no-volume" "$RUNS/eval/full" >> $D/paired_1000.txt
  $P docs/runs/paired.py "$OUT/eval/full" "$RUNS/eval/full" >> $D/paired_1000.txt
  $P $D/real.py --out $D/real_1000 --checkpoint "full 500=$RUNS/render_full/render.pt" \
    --checkpoint "full 1000=$OUT/render_full/render.pt" --checkpoint "no volume 1000=$SHIP"
  # tried: stage 1 fine-tuned 300 steps on labels that keep the (never seen) ego car occupied
  if [ ! -f "$OUT/occ_ego/occ.pt" ]; then
    $X train --init "$RUNS/occ/occ.pt" --occupancy-labels surface+ego --voxel-size 1.6 --data data/train --val data/val \
      --stage occ --steps 300 --lr 3e-4 --warmup 30 --seed 1 --val-every 150 --val-scenes 8 --out "$OUT/occ_ego" \
      --threads 1 --quiet $( [ -f "$OUT/occ_ego/last.pt" ] && echo --resume ) > "$OUT/occ_ego.log" 2>&1
  fi
  $P $D/ego.py --checkpoint "full 500=$RUNS/render_full/render.pt" --checkpoint "full 1000=$OUT/render_full/render.pt" \
    --checkpoint "no volume 1000=$SHIP" --occ "stage 1, surface=$RUNS/occ/occ.pt" \
    --occ "stage 1 + 300 steps surface+ego=$OUT/occ_ego/occ.pt" --scenes 10 --out $D/ego.json
  $P docs/runs/compare.py data/val $D/compare_1000.jpg --model "full 500 (v1.0.0)=$RUNS/render_full" \
    --model "full 1000=$OUT/render_full" --model "no volume 1000 (v1.1.0)=$OUT/render_no-volume"
  # the 5-camera rig with and without the mirrored completion, through the shipped ONNX model (export it first:
  # xyzcyl export --checkpoint $SHIP --out models/xyzcyl-cpu-v1 --version 1.1.0 ...; docs/results.md)
  $P $D/waymo_completion.py --model models/xyzcyl-cpu-v1 --out $D/waymo_completion
fi
