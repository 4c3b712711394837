"""runtime.numba_cache: numba's on-disk cache, safe for several processes and per-model closures (issue 35 item 1:
an f-theta / equirectangular render loaded another camera model's projection kernel from the cache)."""

from __future__ import annotations

import multiprocessing as mp
import pickle
import re
from pathlib import Path

import pytest
from numba.core.caching import IndexDataCacheFile
from xyzcyl.runtime import numba_cache
from xyzcyl.runtime.numba_cache import CheckedFunctionCache, CheckedIndexDataCacheFile

STAMP = ("source", 1)


def _files(tmp_path: Path, cls=CheckedIndexDataCacheFile, stamp=STAMP):
    return cls(cache_path=str(tmp_path), filename_base="f-1.py311", source_stamp=stamp)


def _point_key_at_others_data(cache, key_a, key_b) -> None:
    """What a lost race leaves (two processes picked the same data number): key_b's index entry names key_a's
    data file."""
    overloads = cache._load_index()
    overloads[key_b] = overloads[key_a]
    cache._save_index(overloads)


@pytest.mark.parametrize("cls", [IndexDataCacheFile, CheckedIndexDataCacheFile])
def test_an_index_entry_naming_another_keys_data_is_a_miss(tmp_path, cls):
    cache = _files(tmp_path, cls)
    cache.save("pinhole", "pinhole code")
    cache.save("ftheta", "ftheta code")
    _point_key_at_others_data(cache, "pinhole", "ftheta")
    got = cache.load("ftheta")
    if cls is IndexDataCacheFile:
        assert got == "pinhole code"            # numba's own: the other model's code, the IndexError
    else:
        assert got is None                      # ours: a miss, so the kernel compiles again
        assert cache.load("pinhole") == "pinhole code"


def test_data_of_another_source_stamp_is_a_miss(tmp_path):
    """After a source change numba restarts the numbering over the stale data files: a reader between a writer's
    index write and its data write found the stale file under the new key."""
    _files(tmp_path, stamp=("old", 0)).save("k", "old code")
    cache = _files(tmp_path)
    old = cache._load_data(cache._data_name(1))
    cache._save_index({"k": cache._data_name(1)})        # the new index, the old data file still in place
    assert old[2] == "old code" and cache.load("k") is None
    cache.save("k", "new code")
    assert cache.load("k") == "new code"


def test_unreadable_or_numba_format_data_is_a_miss(tmp_path):
    cache = _files(tmp_path)
    cache.save("k", "code")
    path = Path(cache._data_path(cache._data_name(1)))
    path.write_bytes(pickle.dumps("numba's own format: the bare payload"))
    assert cache.load("k") is None
    path.write_bytes(b"\x80cut")
    assert cache.load("k") is None
    path.unlink()
    assert cache.load("k") is None


def test_save_writes_the_data_before_the_index_names_it(tmp_path, monkeypatch):
    cache = _files(tmp_path)
    seen = []
    real = CheckedIndexDataCacheFile._save_index

    def spy(self, overloads):
        seen.extend((k, Path(self._data_path(n)).exists()) for k, n in overloads.items())
        real(self, overloads)

    monkeypatch.setattr(CheckedIndexDataCacheFile, "_save_index", spy)
    cache.save("a", 1)
    cache.save("b", 2)
    assert seen and all(exists for _, exists in seen)


def _writer(path: str, worker: int, count: int, barrier) -> None:
    cache = CheckedIndexDataCacheFile(cache_path=path, filename_base="f-1.py311", source_stamp=STAMP)
    barrier.wait()
    for k in range(count):
        cache.save(f"w{worker}k{k}", f"data of w{worker}k{k}")


def test_processes_saving_at_once_lose_nothing_and_mix_nothing(tmp_path):
    """Six processes add entries to one index at once (the server and its reconstruction workers compiling at
    start-up): every entry survives and loads its own data."""
    ctx = mp.get_context("fork")
    workers, count = 6, 25
    barrier = ctx.Barrier(workers)
    procs = [ctx.Process(target=_writer, args=(str(tmp_path), w, count, barrier)) for w in range(workers)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)                           # bounded: a stuck writer fails the test, not the suite
        assert p.exitcode == 0
    cache = _files(tmp_path)
    assert len(cache._load_index()) == workers * count
    for w in range(workers):
        for k in range(count):
            assert cache.load(f"w{w}k{k}") == f"data of w{w}k{k}"


def test_the_stamp_covers_the_kernels_sources_and_what_they_import():
    """lensmap's kernels compile runtime/lenses.py's distortion terms into themselves, and kernels.py compiles
    lensmap's; trace.py's read model_export/data/classes.py's constants: an edit of any of them must invalidate the
    kernels that hold it (numba's own stamp, the defining file alone, did not). The detail layer's edits leave the
    renderer's kernels alone."""
    root = Path(numba_cache.__file__).resolve().parent.parent

    def paths(module: str) -> set[str]:
        return {p for p, _, _ in numba_cache.source_stamp(root / module)}

    kernels = paths("runtime/render/kernels.py")
    assert {"runtime/render/kernels.py", "runtime/render/lensmap.py", "runtime/lenses.py"} <= kernels
    assert "runtime/detail.py" not in kernels and "runtime/render/core.py" not in kernels
    assert {"runtime/detail.py", "runtime/rotations.py"} <= paths("runtime/scene.py")     # scene imports detail
    assert "model_export/data/classes.py" in paths("model_export/data/trace.py")
    assert "server/service.py" not in paths("runtime/views.py")


def test_every_cached_kernel_uses_the_checked_cache():
    from xyzcyl.runtime import detail, scene, views
    from xyzcyl.runtime.render import kernels, lensmap

    for k in range(5):
        assert isinstance(kernels.precull_counts(k)._cache, CheckedFunctionCache)
        assert isinstance(kernels.project_kernel(k)._cache, CheckedFunctionCache)
        assert all(isinstance(f._cache, CheckedFunctionCache) for f in kernels._chunk_functions(k))
    for mod in (kernels, lensmap, scene, detail, views):
        cached = [v for v in vars(mod).values() if hasattr(v, "_cache") and v._cache.__class__.__name__ != "NullCache"]
        assert cached and all(isinstance(f._cache, CheckedFunctionCache) for f in cached), mod.__name__


def test_no_module_caches_through_numba_directly():
    """numba.njit(cache=True) / from numba import njit would bypass the checked cache."""
    root = Path(numba_cache.__file__).resolve().parent.parent
    offenders = []
    for pkg in ("runtime", "model_export", "server", "common"):
        for p in (root / pkg).rglob("*.py"):
            text = p.read_text()
            if p.name != "numba_cache.py" and re.search(r"numba\.njit\(|from numba import [^\n]*\bnjit\b", text):
                offenders.append(str(p.relative_to(root)))
    assert not offenders
