"""The render warm-up (runtime.warmup.warm_render, what `xyzcyl serve` runs before it reports ready) reaches the
numba kernels a drive's views use beyond a one-rig scene: the PLY readers of runs and rows, the large-subset gather,
several sets drawn as one, a layer drawn behind another over its open tiles, the moving objects' move. Measured
before: a freshly warmed service compiled 1.4 s of these on its first drive view. In a fresh process (its
dispatchers hold no signature until called), each has one after warm_render."""

from __future__ import annotations

import json
import os
import subprocess
import sys

CHECK = r"""
import json, sys, tempfile
from xyzcyl.runtime.render import gaussians as G, kernels as K
from xyzcyl.runtime.warmup import warm_render
kernels = {"open_slots": K.open_slots, "covered_tiles": K.covered_tiles, "offset_slots": K.offset_slots,
           "_rigid_kernel": G._rigid_kernel, "_unpack_kernel": G._unpack_kernel, "put_rows": G.put_rows}
before = {k: len(d.signatures) for k, d in kernels.items()}
with tempfile.TemporaryDirectory() as tmp:
    warm_render(tmp, "pinhole")
print(json.dumps({"before": before, "after": {k: len(d.signatures) for k, d in kernels.items()}}))
"""


def test_warm_render_reaches_the_drive_view_kernels():
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=600,
                         env=dict(os.environ))
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert not any(got["before"].values()), got           # a fresh process: nothing called yet
    missing = [k for k, n in got["after"].items() if n == 0]
    assert not missing, f"warm_render does not reach {missing}"
