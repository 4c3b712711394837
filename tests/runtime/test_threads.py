"""numpy's BLAS on one thread wherever the runtime reconstructs (runtime.threads): its waiting threads took the cores
from the reconstruction's own (docs/results.md "Speed, session of 2026-12-02 (night)")."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow   # the session's ONNX export (tests/conftest.py)

CHILD = r"""
import json, sys
import numpy
from threadpoolctl import threadpool_info
def blas():
    return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
before = blas()
from xyzcyl.runtime.inference import Reconstructor
Reconstructor.load(sys.argv[1], threads=1)
after = blas()
Reconstructor.load(sys.argv[1], threads=1)      # a second load: nothing more to do, nothing undone
print(json.dumps({"before": before, "after": after, "again": blas()}))
"""


def test_reconstructor_load_runs_numpys_blas_on_one_thread(tiny_export):
    # a fresh process with a 2-thread BLAS pool (the variable OpenBLAS reads at start), so the change is visible on
    # a machine of any core count
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", CHILD, str(tiny_export.dir)], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["before"] and all(n == 2 for n in got["before"]), got
    assert got["after"] == got["again"] == [1] * len(got["before"]), got
