#!/usr/bin/env bash
# LiDAR as the depth input, checked on the points it did not use: `xyzcyl lidar-eval --holdout 0.5` (a random half
# of each real sweep is the depth input, the other half is checked) with the shipped model, on both real rigs.
#   bash docs/runs/cpu_2026-11-25/lidar_holdout.sh   (writes OUT=runs/lidar/holdout_*.json|jpg; about 1 min)
set -euo pipefail
OUT=${OUT:-runs/lidar}
REAL=${REAL:-../shared/data/real}
mkdir -p "$OUT"
for rig in nuscenes_ca9a282c pandaset_002_00; do
  .venv/bin/xyzcyl lidar-eval "$REAL/$rig/rig.json" --holdout 0.5 --json "$OUT/holdout_$rig.json" \
    --picture "$OUT/holdout_$rig.jpg" --quiet > /dev/null
  # the same half-sweep check without LiDAR input: the baseline on exactly the checked points
  .venv/bin/python - "$REAL/$rig/rig.json" "$OUT/holdout_none_$rig.json" <<'PY'
import json, sys
import numpy as np
from xyzcyl.runtime.inference import Reconstructor, default_model_dir
from xyzcyl.runtime.lidar import camera_depths, load_lidar, summarise
from xyzcyl.runtime.rig import load_rig
rig = load_rig(sys.argv[1])
pts = load_lidar(rig).points
pick = np.random.default_rng(0).random(len(pts)) < 0.5      # lidar-eval --holdout's rule
scene = Reconstructor.load(default_model_dir()).reconstruct(rig, depths=[None] * len(rig))
json.dump(summarise(camera_depths(scene, pts[~pick])), open(sys.argv[2], "w"), indent=1)
PY
done
echo done
