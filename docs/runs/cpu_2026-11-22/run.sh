#!/usr/bin/env bash
# The first cpu-preset training run (docs/results.md): data, stage 1, four stage-2 runs (full model and the
# three ablations, same data, steps and schedule), evaluation of each plus the unprojection baselines.
# Resumable: rerun the script after a kill; finished data and training steps are skipped, started training
# resumes from its last checkpoint (evaluations are redone).
#   bash docs/runs/cpu_2026-11-22/run.sh            (from the repository root, after the README's set-up)
# Environment knobs (defaults = the recorded run): OCC_STEPS, REN_STEPS, TARGETS, THREADS, RUNS, EVAL.
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
RUNS=${RUNS:-runs/cpu1}
EVAL=${EVAL:-$RUNS/eval}
OCC_STEPS=${OCC_STEPS:-1000}
REN_STEPS=${REN_STEPS:-600}
TARGETS=${TARGETS:-4}
THREADS=${THREADS:-2}

$X data synth --out data/train --scenes 200 --seed 0 --voxels 1.6 --quiet   # training set (seed 0)
$X data synth --out data/val --scenes 50 --seed 1 --voxels 1.6 --quiet      # disjoint validation set (seed 1)

stage() {  # stage OUT STAGE_PT THREADS ARGS...: train unless OUT/STAGE_PT exists; resume if OUT/last.pt does
  local out=$1 done=$2 threads=$3; shift 3
  if [ -f "$out/$done" ]; then return; fi
  if [ -f "$out/last.pt" ]; then set -- "$@" --resume; fi
  $X train "$@" --out "$out" --threads "$threads" --quiet > "$out.log" 2>&1
}
mkdir -p $RUNS

# stage 1 (occupancy) on a 1.6 m grid: 50 x 50 x 10 voxels
stage $RUNS/occ occ.pt $THREADS --preset cpu --voxel-size 1.6 --data data/train --val data/val --stage occ \
  --steps $OCC_STEPS --lr 1e-3 --val-every 250 --val-scenes 8

# stage 2: the full model and the three ablations from the same stage-1 weights, side by side (one thread each),
# so all four get the same steps, schedule and data order; targets from both settings at half size
pids=""
for abl in none no-volume no-pixel no-background; do
  stage $RUNS/render_$abl render.pt 1 --preset cpu --voxel-size 1.6 --ablation $abl --init $RUNS/occ/occ.pt \
    --data data/train --val data/val --stage render --setting both --targets $TARGETS --target-scale 0.5 \
    --steps $REN_STEPS --lr 1e-3 --val-every 100 --val-scenes 4 &
  pids="$pids $!"
done
for p in $pids; do wait "$p"; done     # set -e: stop here if any run failed (its log: $RUNS/render_<abl>.log)

# (recorded run: these evaluations ran two at a time with --threads 1; the metrics do not depend on it beyond
# float round-off)
for abl in none no-volume no-pixel no-background; do
  $X eval --checkpoint $RUNS/render_$abl/render.pt --data data/val --setting ego-forward,ego-inward --out $EVAL \
    --threads $THREADS --quiet
done
$X eval --checkpoint $RUNS/render_none/render.pt --data data/val --setting ego-forward,ego-inward --out $EVAL \
  --gt-occupancy --threads $THREADS --quiet
$X eval --baseline unproject --checkpoint $RUNS/render_none/render.pt --data data/val \
  --setting ego-forward,ego-inward --out $EVAL --threads $THREADS --quiet
$X eval --baseline unproject-gt-depth --data data/val --setting ego-forward,ego-inward --out $EVAL \
  --threads $THREADS --quiet
sha256sum $RUNS/occ/occ.pt $RUNS/render_*/render.pt

D=docs/runs/cpu_2026-11-22
P=${P:-.venv/bin/python}
$P docs/runs/table.py $EVAL > $D/table.md
$P docs/runs/curves.py $D/render_curves.png "full model=$RUNS/render_none" "no volume=$RUNS/render_no-volume" \
  "no pixel=$RUNS/render_no-pixel" "no separate background=$RUNS/render_no-background"
$P docs/runs/compare.py data/val $D/compare.jpg --model "full=$RUNS/render_none" --gt-occupancy full \
  --model "no volume=$RUNS/render_no-volume" --model "no pixel=$RUNS/render_no-pixel" \
  --model "no separate bg=$RUNS/render_no-background"
