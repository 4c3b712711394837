#!/usr/bin/env bash
# The standardised-input model (docs/results.md "Input standardisation"), from the shipped 1.3.1:
#   1. stage depth with --input-norm standardize (photo_ab.sh's ctrl recipe and data: 600 steps, seed 5; seed 6
#      again for the A/B's spread), then exposure_eval.sh measures it like the photo A/B;
#   2. stage render from it (readapt.sh's recipe, its two 300-step runs as one of 600 steps) on run.sh's
#      training set (data/train, seed 0, 200 scenes), so the render modules fit the new features.
# Resumable: rerun after a kill.
#   bash docs/runs/cpu_2026-11-25_final/norm_chain.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
OUT=${OUT:-runs/cpu8}
mkdir -p "$OUT" data
[ -f "$OUT/shipped.pt" ] || $X import-model models/xyzcyl-cpu-v1 --out "$OUT/shipped.pt"
$X data synth --out data/tex_ctrl120 --scenes 120 --seed 8 --near-cars 0.5 --targets ego-forward --voxels 1.6 --quiet
$X data synth --out data/train --scenes 200 --seed 0 --voxels 0.8,1.6 --quiet
$X data synth --out data/val --scenes 50 --seed 1 --voxels 0.8,1.6 --quiet
for seed in 5 6; do
  run=norm; [ "$seed" = 5 ] || run=norm_s$seed
  out="$OUT/depth_$run"
  [ -f "$out/depth.pt" ] && continue
  resume=""
  [ -f "$out/last.pt" ] && resume="--resume"
  # shellcheck disable=SC2086
  $X train --stage depth --init "$OUT/shipped.pt" --data data/tex_ctrl120 --input-norm standardize --camera-aug 0.5 \
    --steps 600 --lr 1e-3 --warmup 50 --seed "$seed" --out "$out" --threads 1 --quiet $resume > "$out.log" 2>&1
done
OUT=$OUT MODELS="norm norm_s6" KINDS="none,exposure_0.5,exposure_1.5" bash docs/runs/cpu_2026-11-25_final/exposure_eval.sh
out="$OUT/render_norm"
if [ ! -f "$out/render.pt" ]; then
  resume=""
  [ -f "$out/last.pt" ] && resume="--resume"
  # shellcheck disable=SC2086
  $X train --init "$OUT/depth_norm/depth.pt" --data data/train --camera-drop 0.5 --val data/val --stage render \
    --setting both --targets 4 --target-scale 0.5 --camera-aug 0.5 --steps 600 --lr 3e-4 --warmup 30 --seed 6 \
    --val-every 300 --val-scenes 4 --out "$out" --threads "${THREADS:-2}" --quiet $resume > "$out.log" 2>&1
fi
sha256sum "$OUT"/depth_norm*/depth.pt "$out/render.pt"
