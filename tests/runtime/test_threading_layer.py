"""numba's threading layer (runtime.numba_cache.threadsafe): where only its workqueue layer loads (a slim container
image has no libgomp1 and no tbb wheel), two threads that launch parallel kernels at once abort the whole process.
A drive made its next keyframe in a thread while it fused the last one, and the service renders in a pool of
threads: both run one at a time there instead. The workqueue case is made here with NUMBA_THREADING_LAYER."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest
from xyzcyl.testing import SHIPPED_MODEL

# a small drive of three keyframes (the example rig at three poses), made in a child process whose numba has only
# the workqueue layer: every keyframe is made in the thread that fuses (before, the next one was made in a thread
# beside it, and the first time both launched a kernel together numba aborted the process: "Numba workqueue
# threading layer is terminating: Concurrent access has been detected"; when they meet is a matter of timing)
CHILD = r"""
import sys, threading
import numpy as np
from xyzcyl.runtime.numba_cache import threadsafe
assert not threadsafe(), "the workqueue layer is not thread-safe"
from xyzcyl.runtime import drive as D
from xyzcyl.runtime.detail import DetailOptions
from xyzcyl.runtime.drive import load_drive, reconstruct_drive
made_in = []
make = D.make_keyframe
def recorded(*a, **k):
    made_in.append(threading.current_thread().name)
    return make(*a, **k)
D.make_keyframe = recorded
from xyzcyl.runtime.inference import Reconstructor
from xyzcyl.testing.drives import pose, write_drive
from pathlib import Path
E = np.array(pose(7, 3, 20))
poses = [(E @ np.array(pose(x, 0.0))).tolist() for x in (0.0, 1.5, 3.0)]
drive = load_drive(write_drive(Path(sys.argv[1]), poses, [0.0, 0.3, 0.6]))
said = []
scene = reconstruct_drive(Reconstructor.load(sys.argv[2], threads=2), drive, detail=DetailOptions(stride=8),
                          keyframes=[0, 1, 2], workers=0, progress=said.append)
assert any("one at a time" in m for m in said), said
assert "frame 2: encode" in said, said
assert made_in == [threading.main_thread().name] * 3, made_in
print("keyframes", scene.counts["keyframes"])
"""


def test_a_drive_under_numbas_workqueue_layer_makes_its_keyframes_one_at_a_time(tmp_path):
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    p = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path), str(SHIPPED_MODEL)], env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "keyframes 3" in p.stdout


def test_threadsafe_tells_the_layer_numba_loaded():
    probe = "from xyzcyl.runtime.numba_cache import threadsafe; import numba; print(threadsafe(), numba.threading_layer())"
    for layer in ("workqueue", "default"):
        env = {**os.environ, "NUMBA_THREADING_LAYER": layer}
        out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                             timeout=120).stdout.split()
        assert out[0] == str(out[1] in ("tbb", "omp")), out
        if layer == "workqueue":
            assert out == ["False", "workqueue"]


@pytest.mark.parametrize("safe", [True, False])
def test_the_render_pool_has_one_thread_without_a_threadsafe_layer(monkeypatch, caplog, safe):
    from xyzcyl.runtime import numba_cache
    from xyzcyl.server.jobs import render_threads

    monkeypatch.setattr(numba_cache, "threadsafe", lambda: safe)
    with caplog.at_level(logging.WARNING, logger="xyzcyl.server"):
        assert render_threads(4) == (4 if safe else 1)
        assert render_threads(1) == 1
    assert ("render_threads 4 -> 1" in caplog.text) is not safe
