#!/usr/bin/env bash
# After mixed.sh: tables, paired differences, real rigs and pictures of the mixed-rig runs against 1.1.0
# (docs/results.md "Mixed rigs").   bash docs/runs/cpu_2026-11-23/mixed_post.sh
set -euo pipefail
P=${P:-.venv/bin/python}
D=docs/runs/cpu_2026-11-23
OUT=${OUT:-runs/cpu3}
PREV=${PREV:-runs/cpu2b}
$P docs/runs/table.py "mixed rigs, full=$OUT/eval/full_val" "mixed rigs, no volume=$OUT/eval/no-volume_val" \
  "6 cameras only, no volume (v1.1.0)=$PREV/eval/no-volume" "6 cameras only, full=$PREV/eval/full" > $D/table_mixed.md
rows=()
for r in waymo argoverse ring8; do
  rows+=("mixed, full, $r=$OUT/eval/full_val_$r" "mixed, no volume, $r=$OUT/eval/no-volume_val_$r"
         "v1.1.0, $r=$PREV/eval/rig_$r")
done
$P docs/runs/table.py "${rows[@]}" > $D/table_rigs_mixed.md
{
  for d in val val_waymo val_argoverse val_ring8; do
    $P docs/runs/paired.py "$OUT/eval/full_$d" "$OUT/eval/no-volume_$d"
  done
  $P docs/runs/paired.py "$OUT/eval/no-volume_val" "$PREV/eval/no-volume"
  $P docs/runs/paired.py "$OUT/eval/full_val" "$PREV/eval/full"
  for r in waymo argoverse ring8; do
    $P docs/runs/paired.py "$OUT/eval/no-volume_val_$r" "$PREV/eval/rig_$r"
  done
} > $D/paired_mixed.txt
$P $D/real.py --out $D/real_mixed --checkpoint "v1.1.0=$PREV/render_no-volume/render.pt" \
  --checkpoint "mixed full=$OUT/render_full/render.pt" --checkpoint "mixed no volume=$OUT/render_no-volume/render.pt"
gap() { echo "$1=$2_val,$2_val_waymo,$2_val_argoverse,$2_val_ring8"; }
$P $D/rig_gap.py --json $D/rig_gap_mixed.json \
  "v1.1.0=$PREV/eval/no-volume,$PREV/eval/rig_waymo,$PREV/eval/rig_argoverse,$PREV/eval/rig_ring8" \
  "$(gap "mixed, no volume" "$OUT/eval/no-volume")" "$(gap "mixed, full" "$OUT/eval/full")" > $D/rig_gap_mixed.md
# the picture: the 5-camera rig (held out) and the 6-camera rig, v1.1.0 against the mixed-rig runs
for d in val_waymo val; do
  $P docs/runs/compare.py "data/$d" "$D/compare_mixed_$d.jpg" --model "v1.1.0=$PREV/render_no-volume" \
    --model "mixed no volume=$OUT/render_no-volume" --model "mixed full=$OUT/render_full" --scenes 0,1
done
