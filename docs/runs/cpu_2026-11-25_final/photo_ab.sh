#!/usr/bin/env bash
# Photo textures A/B (docs/results.md "Real photo textures"): the depth head trained alone (stage depth, the
# depth_stage.sh recipe: 600 steps, lr 1e-3, --camera-aug 0.5) from the shipped 1.3.1 (recovered with import-model),
# on the same 120 scenes of seed 8 (cars beside the ego in half of them; ego-forward targets, which stage depth does
# not read but the loader needs), without (ctrl) and with (photo) --photo-textures 0.7: real facade / road /
# sidewalk tiles cut from the CC0 street panoramas. Two training seeds per arm (5 and 6), one thread each, side by
# side. Then exposure_eval.sh measures each (real rigs' AbsRel against LiDAR as posted and at x0.5 / x1.5
# exposure, synthetic pseudo-LiDAR scenes) and exposure_table.py prints the table. Resumable.
#   bash docs/runs/cpu_2026-11-25_final/photo_ab.sh
# (The runs of 2026-11-25 used the first 120 scene folders of a 240-scene ctrl set of the same seed and config:
# scene i depends only on (seed, i), so they are these files byte for byte.)
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu8}
D=docs/runs/cpu_2026-11-25_final
mkdir -p "$OUT" data
[ -f "$OUT/shipped.pt" ] || $X import-model models/xyzcyl-cpu-v1 --out "$OUT/shipped.pt"
declare -A PT=([ctrl]=0 [photo]=0.7)
declare -A DATA=([ctrl]=data/tex_ctrl120 [photo]=data/tex_photo)
for arm in ctrl photo; do
  $X data synth --out "${DATA[$arm]}" --scenes 120 --seed 8 --near-cars 0.5 --photo-textures "${PT[$arm]}" \
    --targets ego-forward --voxels 1.6 --quiet
done
models=""
for seed in 5 6; do
  pids=""
  for arm in ctrl photo; do
    run=$arm; [ "$seed" = 5 ] || run=${arm}_s$seed
    models="$models $run"
    out="$OUT/depth_$run"
    [ -f "$out/depth.pt" ] && continue
    resume=""
    [ -f "$out/last.pt" ] && resume="--resume"
    # shellcheck disable=SC2086
    $X train --stage depth --init "$OUT/shipped.pt" --data "${DATA[$arm]}" --camera-aug 0.5 --steps 600 --lr 1e-3 \
      --warmup 50 --seed "$seed" --out "$out" --threads 1 --quiet $resume > "$out.log" 2>&1 &
    pids="$pids $!"
  done
  for p in $pids; do wait "$p"; done
done
sha256sum "$OUT"/depth_*/depth.pt
# shellcheck disable=SC2086
OUT=$OUT MODELS="base$models" KINDS="none,exposure_0.5,exposure_1.5" bash $D/exposure_eval.sh
