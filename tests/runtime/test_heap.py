"""The C heap kept for reuse (runtime.heap): the `xyzcyl` command's processes allocate from freed memory instead
of fresh pages the kernel zeroes; the settings reach the processes they start; XYZCYL_MALLOC=default and a user's
own GLIBC_TUNABLES win."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from xyzcyl.runtime.heap import _libc, tunables

GLIBC = pytest.mark.skipif(_libc() is None, reason="glibc only (mallopt, GLIBC_TUNABLES)")

CHILD = r"""
import json, os, resource, subprocess, sys
from xyzcyl.runtime.heap import keep_freed_memory
ok = keep_freed_memory() if sys.argv[1] == "keep" else None
import numpy as np

def faults(nbytes):
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(nbytes // 8)
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0

faults(100 << 20)                       # the first one is fresh either way
child = subprocess.run([sys.executable, "-c", "import os; print(os.environ.get('GLIBC_TUNABLES', ''))"],
                       capture_output=True, text=True, check=True).stdout.strip()
print(json.dumps({"ok": ok, "faults": max(faults(100 << 20) for _ in range(3)), "child": child}))
"""


def _run(mode: str, **env) -> dict:
    e = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "XYZCYL_MALLOC")} | env
    out = subprocess.run([sys.executable, "-c", CHILD, mode], env=e, capture_output=True, text=True, timeout=120,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_tunables_add_the_settings_and_keep_the_users():
    got = tunables("glibc.malloc.arena_max=4:glibc.cpu.hwcaps=-AVX512F")
    assert got.split(":")[:2] == ["glibc.malloc.arena_max=4", "glibc.cpu.hwcaps=-AVX512F"]
    assert "glibc.malloc.mmap_threshold=1073741824" in got and "glibc.malloc.trim_threshold=2147483648" in got
    assert got.count("arena_max") == 1
    assert tunables(None) == ("glibc.malloc.mmap_threshold=1073741824:glibc.malloc.trim_threshold=2147483648:"
                              "glibc.malloc.arena_max=1")


@GLIBC
def test_a_freed_array_is_reused_without_fresh_pages():
    kept, default = _run("keep"), _run("none")
    # glibc's default maps 100 MB afresh each time: at least one fault per 2 MB (transparent huge pages; 4 KB pages
    # make 25,600); kept, the heap hands the freed block back: a few faults at most (numpy's and Python's own)
    assert default["faults"] >= 50, default
    assert kept["ok"] is True and kept["faults"] <= 5, kept
    # and the processes it starts begin with the same settings (the service's workers, a drive's keyframe workers)
    assert kept["child"] == tunables(None)


@GLIBC
def test_xyzcyl_malloc_default_leaves_the_heap_as_it_is():
    got = _run("keep", XYZCYL_MALLOC="default")
    assert got["ok"] is False and got["faults"] >= 50 and got["child"] == ""


TRIM_CHILD = r"""
import json
from xyzcyl.runtime.heap import heap_free_bytes, keep_freed_memory, release_heap
keep_freed_memory()
import numpy as np
a = np.ones((300 << 20) // 8)
b = np.ones(1000)                       # keeps the freed block below the heap's top: only malloc_trim gives it back
del a
free = heap_free_bytes()
kept = release_heap(1 << 30)            # 300 MB free, under the bound: kept
after_kept = heap_free_bytes()
trimmed = release_heap(100 << 20)       # over this bound: handed back
print(json.dumps({"free": free, "kept": kept, "after_kept": after_kept, "trimmed": trimmed}))
"""


@GLIBC
def test_release_heap_keeps_free_memory_under_its_bound_and_trims_above():
    out = subprocess.run([sys.executable, "-c", TRIM_CHILD], capture_output=True, text=True, timeout=120, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    if got["free"] is None:
        pytest.skip("glibc without mallinfo2 (< 2.33): release_heap always trims")
    assert got["free"] >= 300 << 20, got                # the freed array is held by the heap
    assert got["kept"] is False and got["after_kept"] == got["free"], got
    assert got["trimmed"] is True, got
