"""runtime.compile_notice: a process that compiles an xyzcyl numba kernel says so once on stderr; one that loads
it from numba's cache says nothing. Subprocesses, each with its own NUMBA_CACHE_DIR (a fresh empty folder: numba
must compile), so the test does not depend on the tree's __pycache__ state. The kernel is runtime.detail._quat
(a small serial function: compiles in about a second)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

NOTICE = "xyzcyl: compiling numba kernels ("
DONE = re.compile(r"^xyzcyl: numba compile took (\d+\.\d) s \(cached", re.M)

# imports the kernel's module the way every user does (through xyzcyl.runtime.render, which installs the notice),
# compiles it twice with two signatures (two compiles, one line), and checks the result
SCRIPT = """
import numpy as np
from xyzcyl.runtime import compile_notice
from xyzcyl.runtime.detail import _quat
q = np.empty(4)
_quat(np.eye(3), q)
_quat(np.eye(3, dtype=np.float32), np.empty(4, np.float32))
assert np.allclose(q, [1, 0, 0, 0]), q
print("said", compile_notice.said())
"""


def _run(cache) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    return subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True,
                          timeout=120, check=False)


def test_compile_notice_once_when_compiling_silent_when_cached(tmp_path):
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    cold = _run(cache)
    assert cold.returncode == 0, cold.stderr
    lines = [ln for ln in cold.stderr.splitlines() if NOTICE in ln]
    assert len(lines) == 1, cold.stderr
    assert str(cache) in lines[0], lines[0]
    assert "said True" in cold.stdout
    took = DONE.findall(cold.stderr)                     # the measured total, once, at exit
    assert len(took) == 1 and 0.0 < float(took[0]) < 120.0, cold.stderr
    assert cold.stderr.index(NOTICE) < cold.stderr.index("numba compile took")
    assert any(cache.rglob("*.nbi")), "numba wrote no cache index"

    warm = _run(cache)
    assert warm.returncode == 0, warm.stderr
    assert NOTICE not in warm.stderr and not DONE.search(warm.stderr), warm.stderr
    assert "said False" in warm.stdout


def test_compile_notice_sink_and_idempotent(tmp_path):
    """install(sink) twice: still one listener, the line goes to the sink (the server's log), not stderr."""
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    script = SCRIPT.replace("from xyzcyl.runtime.detail import _quat", """
got = []
compile_notice.install(got.append)
compile_notice.install(got.append)
from xyzcyl.runtime.detail import _quat""") + "print('sink', len(got), got[0] if got else '')\n"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    r = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120,
                       check=False)
    assert r.returncode == 0, r.stderr
    assert NOTICE not in r.stderr and not DONE.search(r.stderr), r.stderr     # a sink: no exit line on stderr
    assert f"sink 1 {NOTICE}" in r.stdout, r.stdout
