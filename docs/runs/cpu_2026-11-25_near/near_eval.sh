#!/usr/bin/env bash
# The A/B of near_train.sh and depth_only.sh measured (docs/results.md "Cars beside the ego"), for the shipped
# 1.2.0 ("base"), the two runs (near, ctrl), the two depth-head-only runs (dnear, dctrl), readapt.sh's run
# (readapt) and readapt2 (300 more such steps: readapt.sh with INIT=runs/cpu6/render_readapt/render.pt
# OUT=runs/cpu6/render_readapt2). Measured: depth against LiDAR on the real rigs (`xyzcyl lidar-eval`, no LiDAR
# input), the same check on 5+5 synthetic scenes of seed 1 with pseudo-LiDAR (synth_lidar.py) without and with
# cars beside the ego, input-view PSNR on the real rigs (real_lidar_models.py), and `xyzcyl eval` on the 50
# validation scenes (both settings). MODELS="..." picks some.
#   bash docs/runs/cpu_2026-11-25_near/near_eval.sh   (then near_table.py)
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu6}
REAL=${REAL:-../shared/data/real}
D=docs/runs/cpu_2026-11-25_near
L=docs/runs/cpu_2026-11-25
mkdir -p "$OUT/lidar" "$OUT/eval"
for set in lidar_val5_near lidar_val5_near_pandaset; do
  if [ ! -d "data/$set" ]; then
    rig=nuscenes; [ "$set" = lidar_val5_near_pandaset ] && rig=pandaset
    $X data synth --out "data/$set" --rig $rig --scenes 5 --seed 1 --targets "" --near-cars 1 --quiet
    $P $L/synth_lidar.py "data/$set"
  fi
done
for set in lidar_val5 lidar_val5_pandaset; do   # lidar_runs.sh's sets
  if [ ! -d "data/$set" ]; then
    rig=nuscenes; [ "$set" = lidar_val5_pandaset ] && rig=pandaset
    $X data synth --out "data/$set" --rig $rig --scenes 5 --seed 1 --targets "" --quiet
    $P $L/synth_lidar.py "data/$set"
  fi
done
MODELS=${MODELS:-"base near ctrl dnear dctrl"}
declare -A CK=([base]=runs/cpu5/base_1.2.0.pt [near]=$OUT/render_near/render.pt [ctrl]=$OUT/render_ctrl/render.pt
               [dnear]=$OUT/depth_near.pt [dctrl]=$OUT/depth_ctrl.pt [readapt]=$OUT/render_readapt/render.pt
               [readapt2]=$OUT/render_readapt2/render.pt)
declare -A DIR=([base]=models/xyzcyl-cpu-v1)
for model in $MODELS; do
  [ "$model" = base ] && continue
  DIR[$model]=$OUT/m_$model
  if [ ! -f "$OUT/m_$model/model.json" ]; then
    $X export --checkpoint "${CK[$model]}" --out "$OUT/m_$model" --version "0.0.0-$model" --force --quiet
  fi
done
for model in $MODELS; do
  for rig in nuscenes_ca9a282c pandaset_002_00; do
    $X lidar-eval "$REAL/$rig/rig.json" --model "${DIR[$model]}" --json "$OUT/lidar/${model}_$rig.json" \
      --picture "$OUT/lidar/${model}_$rig.jpg" --quiet > /dev/null
  done
  for set in lidar_val5 lidar_val5_pandaset lidar_val5_near lidar_val5_near_pandaset; do
    for s in data/$set/scene_*; do
      $X lidar-eval "$s/rig_lidar.json" --model "${DIR[$model]}" --json "$OUT/lidar/${model}_${set}_$(basename "$s").json" \
        --quiet > /dev/null
    done
  done
done
# shellcheck disable=SC2046
$P $L/real_lidar_models.py $(for m in $MODELS; do echo "${DIR[$m]}"; done) > "$OUT/real_lidar_models.json"
# merged into the record (a run of some MODELS keeps the others' entries)
$P -c "import json, pathlib; p = pathlib.Path('$D/real_lidar_models.json'); d = json.loads(p.read_text()) if p.is_file() else {}
d.update(json.load(open('$OUT/real_lidar_models.json'))); p.write_text(json.dumps(d, indent=1) + '\n')"
pids=""
for model in $MODELS; do
  if ! ls "$OUT/eval/$model"/*.json > /dev/null 2>&1; then
    $X eval --checkpoint "${CK[$model]}" --data data/val --setting ego-forward,ego-inward --out "$OUT/eval/$model" \
      --threads 1 --quiet > "$OUT/eval_$model.log" 2>&1 &
    pids="$pids $!"
  fi
  if [ "$(echo $pids | wc -w)" -ge 2 ]; then for p in $pids; do wait "$p"; done; pids=""; fi   # two at a time
done
for p in $pids; do wait "$p"; done
echo done
