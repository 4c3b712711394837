#!/usr/bin/env bash
# Measures depth_ab.sh's runs next to 1.3.0: each checkpoint exported, appearance_probe.py on the real rigs (the
# "none" rows are the real-rig AbsRel; the exposure rows show how far brightness still moves the depth), and
# `xyzcyl lidar-eval` on the synthetic pseudo-LiDAR sets of near_eval.sh (5 + 5 scenes). Then exposure_table.py.
#   MODELS="ctrl expo" bash docs/runs/cpu_2026-11-25_final/exposure_eval.sh
# KINDS="none,exposure_0.5,exposure_1.5" probes only what the table reads (default: every kind of the probe).
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu7}
D=docs/runs/cpu_2026-11-25_final
mkdir -p "$OUT/probe" "$OUT/lidar"
for model in ${MODELS:-base ctrl expo}; do
  if [ "$model" = base ]; then dir=models/xyzcyl-cpu-v1; else dir=$OUT/m_$model; fi
  ck=$OUT/depth_$model/depth.pt
  [ -n "${CK:-}" ] && ck=$CK
  if [ "$model" != base ] && [ ! -f "$dir/model.json" ]; then
    $X export --checkpoint "$ck" --out "$dir" --version "0.0.0-$model" --force --quiet
  fi
  [ -f "$OUT/probe/$model.json" ] || $P $D/appearance_probe.py --model "$dir" --json "$OUT/probe/$model.json" \
    ${KINDS:+--kinds "$KINDS"} > /dev/null
  for set in lidar_val5 lidar_val5_pandaset lidar_val5_near lidar_val5_near_pandaset; do
    for s in data/$set/scene_*; do
      f="$OUT/lidar/${model}_${set}_$(basename "$s").json"
      [ -f "$f" ] || $X lidar-eval "$s/rig_lidar.json" --model "$dir" --json "$f" --quiet > /dev/null
    done
  done
done
$P $D/exposure_table.py "$OUT" ${MODELS:-base ctrl expo}
