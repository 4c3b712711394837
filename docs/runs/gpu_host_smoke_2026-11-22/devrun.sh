#!/usr/bin/env bash
# One GPU-host call: data on 16 cores, then both training stages of the cpu preset (CPU torch + numba renderer).
set -u
T0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
mkdir -p /tmp/shim/xyzcyl; for p in runtime model_export server clients; do ln -sfn "$PWD/$p" /tmp/shim/xyzcyl/$p; done
export PYTHONPATH=/tmp/shim:/tmp/site NUMBA_CACHE_DIR=/tmp/nb PYTHONUNBUFFERED=1
X="python3 -m xyzcyl.clients.cli"
nproc; python3 -c "import torch, numba; print('torch', torch.__version__, 'numba', numba.__version__)"
log() { echo "[$(( $(date +%s) - T0 ))s] $*"; }
log synth train
timeout 170 $X data synth --out /tmp/d/train --scenes ${NTRAIN:-240} --rig nuscenes --height 224 --width 400 --targets ego-forward,ego-inward --seed 0 --quiet || log "synth train exit $?"
log synth val
$X data synth --out /tmp/d/val --scenes ${NVAL:-12} --rig nuscenes --height 224 --width 400 --targets ego-forward,ego-inward --seed 1 --quiet || exit 1
log train occ
timeout -s TERM ${OCC_S:-120} $X train --preset cpu --data /tmp/d/train --stage occ --out /tmp/r/occ --steps ${OCC_STEPS:-400} --threads 16 --ckpt-every 50 --quiet
ls /tmp/r/occ
OCC=/tmp/r/occ/occ.pt; [ -f $OCC ] || OCC=/tmp/r/occ/last.pt
log train render from $OCC
timeout -s TERM ${REN_S:-240} $X train --data /tmp/d/train --val /tmp/d/val --val-scenes 6 --stage render --init $OCC --out /tmp/r/render --steps ${REN_STEPS:-600} --threads 16 --ckpt-every 50 --val-every 0 --quiet
log done
ls -la /tmp/r/render
mkdir -p $OUT/occ $OUT/render
cp /tmp/r/occ/*.csv /tmp/r/occ/*.png $OUT/occ/ 2>/dev/null
cp /tmp/r/render/*.csv /tmp/r/render/*.png $OUT/render/ 2>/dev/null
for f in /tmp/r/render/render.pt /tmp/r/render/last.pt; do [ -f $f ] && { cp $f $OUT/render/; break; }; done
ls -la $OUT/*
