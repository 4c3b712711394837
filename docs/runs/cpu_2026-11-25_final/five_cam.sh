#!/usr/bin/env bash
# Where 1.3.0 lost 0.46 dB on the held-out 5-camera rig's ego-forward views (docs/results.md "Issue 10: the
# targets, for 1.3.0"): each link of its chain, and the depth_ab.sh runs, on data/val_waymo (10 scenes), paired
# against 1.2.0 (old_waymo of targets.sh) and 1.3.0 (new_waymo: runs/cpu6/eval/readapt2_waymo copied); then
# per_camera.py. Two evaluations at a time, one thread each; reruns skip what exists.
#   bash docs/runs/cpu_2026-11-25_final/five_cam.sh   (after targets.sh and depth_ab.sh)
set -euo pipefail
X=${X:-.venv/bin/xyzcyl}
P=${P:-.venv/bin/python}
OUT=${OUT:-runs/cpu7}
D=docs/runs/cpu_2026-11-25_final
[ -d "$OUT/eval/new_waymo" ] || cp -r runs/cpu6/eval/readapt2_waymo "$OUT/eval/new_waymo"
declare -A CK=([depthstage]=runs/cpu6/depth_stage/depth.pt [readapt]=runs/cpu6/render_readapt/render.pt
               [depth_ctrl]=$OUT/depth_ctrl/depth.pt [depth_zoom]=$OUT/depth_zoom/depth.pt)
i=0
for m in depthstage readapt depth_ctrl depth_zoom; do
  e="$OUT/eval/${m}_waymo"
  if ! ls "$e"/*.json > /dev/null 2>&1; then
    $X eval --checkpoint "${CK[$m]}" --data data/val_waymo --setting ego-forward,ego-inward --out "$e" --threads 1 \
      --quiet > "$e.log" 2>&1 &
    i=$((i + 1))
    if (( i % 2 == 0 )); then wait; fi
  fi
done
wait
{
  for m in depthstage readapt new; do $P docs/runs/paired.py "$OUT/eval/${m}_waymo" "$OUT/eval/old_waymo"; done
  for m in depth_ctrl depth_zoom; do $P docs/runs/paired.py "$OUT/eval/${m}_waymo" "$OUT/eval/new_waymo"; done
  $P docs/runs/paired.py "$OUT/eval/depth_zoom_waymo" "$OUT/eval/depth_ctrl_waymo"
} > $D/paired_5cam.txt
$P $D/per_camera.py "$OUT/eval/new_waymo" "$OUT/eval/old_waymo" runs/cpu6/eval/readapt2 runs/cpu6/eval/base \
  > $D/per_camera.md
cat $D/paired_5cam.txt $D/per_camera.md
