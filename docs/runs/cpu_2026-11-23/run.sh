#!/usr/bin/env bash
# The second cpu-preset run (issue 10, docs/results.md): the RGB path, the 112x1024 pixel lattice, surface
# occupancy labels; the full model beside its ablations under one step budget, the baselines, the other rigs
# and the real rigs. Resumable: rerun after a kill; finished data and stages are skipped, started stages
# resume from their last checkpoint (evaluations are redone).
#   bash docs/runs/cpu_2026-11-23/run.sh            (from the repository root, after the README's set-up)
# Knobs (defaults = the recorded run): OCC_STEPS, REN_STEPS, TARGETS, RUNS, EVAL, STAGE2 (the stage-2 runs).
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
D=docs/runs/cpu_2026-11-23
RUNS=${RUNS:-runs/cpu2}
EVAL=${EVAL:-$RUNS/eval}
OCC_STEPS=${OCC_STEPS:-1000}
REN_STEPS=${REN_STEPS:-500}
TARGETS=${TARGETS:-4}
VOXEL=${VOXEL:-1.6}
STAGE2=${STAGE2:-"full no-rgb k2 no-volume no-pixel no-background"}

$X data synth --out data/train --scenes 200 --seed 0 --voxels 0.8,1.6 --quiet   # training set (seed 0)
$X data synth --out data/val --scenes 50 --seed 1 --voxels 0.8,1.6 --quiet      # disjoint validation set (seed 1)
# other rigs, never trained on: 5 (waymo), 7 (argoverse) and 8 cameras (ring8.json: 60 deg every 45 deg)
declare -A RIGS=([waymo]=waymo [argoverse]=argoverse [ring8]=$D/ring8.json)
for r in "${!RIGS[@]}"; do
  $X data synth --out "data/val_$r" --scenes 10 --seed 1 --rig "${RIGS[$r]}" --voxels 1.6 --quiet
done

stage() {  # stage OUT STAGE_PT THREADS ARGS...: train unless OUT/STAGE_PT exists; resume if OUT/last.pt does
  local out=$1 done=$2 threads=$3; shift 3
  if [ -f "$out/$done" ]; then return; fi
  if [ -f "$out/last.pt" ]; then set -- "$@" --resume; fi
  $X train "$@" --out "$out" --threads "$threads" --quiet > "$out.log" 2>&1
}
mkdir -p "$RUNS"

# stage 1 (occupancy, with the RGB channels) on surface labels: only voxels an input camera sees are occupied
stage "$RUNS/occ" occ.pt 2 --preset cpu --voxel-size "$VOXEL" --occupancy-labels surface --data data/train \
  --val data/val --stage occ --steps "$OCC_STEPS" --lr 1e-3 --val-every 250 --val-scenes 8

# stage 2, side by side (one thread each) from the same stage-1 weights, same data order and schedule, inputs with
# real-camera effects at strength 0.5 (per-camera exposure, white balance, vignetting, blur, noise, JPEG):
#   full      = RGB path, pixel lattice k_o = 4 (112x1024);  no-rgb = the same without the RGB path;
#   k2        = RGB path at k_o = 2 (56x512, the first model's lattice); no-volume = full without the volume branch
# (recorded run: the first four side by side, the full model at nice -10, the others at nice -6, to finish it first;
#  no-pixel afterwards, alone, with 2 threads; no-background in the next session, alone, 1 thread; STAGE2 lists all six)
declare -A EXTRA=([full]="--pixel-upsample 4" [no-rgb]="--pixel-upsample 4 --ablation no-rgb"
                  [k2]="--pixel-upsample 2" [no-volume]="--pixel-upsample 4 --ablation no-volume"
                  [no-pixel]="--pixel-upsample 4 --ablation no-pixel"
                  [no-background]="--pixel-upsample 4 --ablation no-background")
pids=""
for run in $STAGE2; do
  # shellcheck disable=SC2086
  stage "$RUNS/render_$run" render.pt 1 --init "$RUNS/occ/occ.pt" ${EXTRA[$run]} --data data/train --val data/val \
    --stage render --setting both --targets "$TARGETS" --target-scale 0.5 --camera-aug 0.5 --steps "$REN_STEPS" \
    --lr 1e-3 \
    --val-every 100 --val-scenes 4 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done   # set -e: stop here if a run failed (its log: $RUNS/render_<run>.log)

for run in $STAGE2; do
  $X eval --checkpoint "$RUNS/render_$run/render.pt" --data data/val --setting ego-forward,ego-inward \
    --out "$EVAL/$run" --threads 2 --quiet
done
$X eval --baseline unproject --checkpoint "$RUNS/render_full/render.pt" --data data/val \
  --setting ego-forward,ego-inward --out "$EVAL/unproject" --threads 2 --quiet
$X eval --baseline unproject-gt-depth --data data/val --setting ego-forward,ego-inward \
  --out "$EVAL/unproject-gt-depth" --threads 2 --quiet
for r in "${!RIGS[@]}"; do
  $X eval --checkpoint "$RUNS/render_full/render.pt" --data "data/val_$r" --setting ego-forward,ego-inward \
    --out "$EVAL/rig_$r" --threads 2 --quiet
done
sha256sum "$RUNS/occ/occ.pt" "$RUNS"/render_*/render.pt

# the real rigs at their own input cameras, and the probe of where the colour was lost
$P $D/real.py --out $D/real --checkpoint full="$RUNS/render_full/render.pt" \
  --checkpoint no-rgb="$RUNS/render_no-rgb/render.pt"
$P $D/probe.py data/train data/val > $D/probe.json

# tables and pictures (docs/results.md)
$P docs/runs/table.py "$EVAL/full" "XYZCylinder (cpu, k_o 2: 56x512)=$EVAL/k2" "$EVAL/no-rgb" "$EVAL/no-volume" "$EVAL/no-pixel" "$EVAL/no-background" \
  "$EVAL/unproject" "$EVAL/unproject-gt-depth" > $D/table.md
$P docs/runs/table.py "XYZCylinder (cpu), 6 cameras=$EVAL/full" "5 cameras (waymo)=$EVAL/rig_waymo" \
  "7 cameras (argoverse)=$EVAL/rig_argoverse" "8 cameras (ring8.json)=$EVAL/rig_ring8" > $D/table_rigs.md
$P docs/runs/curves.py $D/render_curves.png "full=$RUNS/render_full" "no RGB=$RUNS/render_no-rgb" \
  "k_o 2 (56x512)=$RUNS/render_k2" "no volume=$RUNS/render_no-volume"
$P docs/runs/compare.py data/val $D/compare.jpg --model "full=$RUNS/render_full" --model "no RGB=$RUNS/render_no-rgb" \
  --model "k_o 2 (56x512)=$RUNS/render_k2" --model "no volume=$RUNS/render_no-volume"

# the 5-camera rig with the paper's mirrored completion (5 -> 8), through the shipped ONNX model (runtime path)
$P $D/waymo_completion.py --model models/xyzcyl-cpu-v1 --out $D/waymo_completion
