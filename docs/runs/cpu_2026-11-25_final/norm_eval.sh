#!/usr/bin/env bash
# Measures norm_chain.sh's stage-2 model ("final") next to the shipped 1.3.1 ("base"), as every shipped model was:
# `xyzcyl eval` on the 50 validation scenes and the held-out 5-camera rig (10 scenes), paired per scene
# (docs/runs/paired.py); the real rigs' depth against LiDAR as posted and at x0.5 / x1.5 exposure plus the synthetic
# pseudo-LiDAR scenes (exposure_eval.sh); real input-view PSNR and LiDAR-input figures (real_lidar_models.py).
# Two evaluations at a time, one thread each. Reruns skip what exists.
#   bash docs/runs/cpu_2026-11-25_final/norm_eval.sh
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu8}
CK=${CK:-$OUT/render_norm/render.pt}
D=docs/runs/cpu_2026-11-25_final
mkdir -p "$OUT/eval"
$X data synth --out data/val_waymo --scenes 10 --seed 1 --rig waymo --voxels 1.6 --quiet
ev() {  # ev NAME ARGS...: one evaluation unless its report exists
  local name=$1; shift
  if ! ls "$OUT/eval/$name"/*.json > /dev/null 2>&1; then
    $X eval "$@" --setting ego-forward,ego-inward --out "$OUT/eval/$name" --threads 1 --quiet > "$OUT/eval_$name.log" 2>&1
  fi
}
ev base --checkpoint "$OUT/shipped.pt" --data data/val &
ev final --checkpoint "$CK" --data data/val &
wait
ev base_waymo --checkpoint "$OUT/shipped.pt" --data data/val_waymo &
ev final_waymo --checkpoint "$CK" --data data/val_waymo &
wait
{
  echo "final (norm_chain.sh) - base (1.3.1), 50 validation scenes:"
  $P docs/runs/paired.py "$OUT/eval/final" "$OUT/eval/base"
  echo "final - base, held-out 5-camera rig (10 scenes):"
  $P docs/runs/paired.py "$OUT/eval/final_waymo" "$OUT/eval/base_waymo"
} > "$D/paired_norm.txt"
OUT=$OUT MODELS="final" CK=$CK KINDS="none,exposure_0.5,exposure_1.5" bash $D/exposure_eval.sh > /dev/null
[ -f "$D/real_runtime_norm.json" ] || \
  $P docs/runs/cpu_2026-11-25/real_lidar_models.py models/xyzcyl-cpu-v1 "$OUT/m_final" > "$D/real_runtime_norm.json"
$P $D/exposure_table.py "$OUT" base ctrl ctrl_s6 photo photo_s6 norm norm_s6 final
