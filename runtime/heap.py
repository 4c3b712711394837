"""The C heap (glibc's malloc) of an xyzcyl process: freed memory kept for the next arrays, handed back on demand.

A reconstruction allocates and frees hundreds of arrays of 2-250 MB (a camera's maps, its cells, the fusion's
copies). With glibc's defaults each one above its mmap threshold (at most 32 MB) is a fresh mapping, which the
kernel zeroes page by page on first touch and unmaps on free, and each thread's arena grows and shrinks its own
heaps: a warm PandaSet frame spent 0.1-1.1 s of system time (11-13 % of its CPU samples in the kernel's page
clearing) and its time varied by as much from run to run. With every allocation from one heap (``arena_max`` 1)
that keeps what was freed (mmap threshold 1 GiB, trim threshold 2 GiB), the same frame faults in almost no page
after the first: 1.67 -> 1.50 s warm, at a lower peak (2.19 -> 1.97 GB; docs/results.md "Speed, session of
2026-12-02 (night)"). Where a process must give memory back (a drive's fusion between keyframes), ``release_heap``
does (malloc_trim).

``keep_freed_memory`` must run before the process starts threads that allocate (numpy's BLAS pool starts when numpy
is imported): the `xyzcyl` command calls it first thing (cli.entry), and it puts the same settings in
GLIBC_TUNABLES so that the processes it starts (the service's workers, a drive's keyframe workers) start with them.
A process that embeds the runtime can call it before importing numpy, or set GLIBC_TUNABLES itself. Nothing
happens on a C library other than glibc, or with XYZCYL_MALLOC=default."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys

# glibc's mallopt parameters (malloc.h) and the tunables that set the same at a process's start
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
SETTINGS = ((M_MMAP_THRESHOLD, "glibc.malloc.mmap_threshold", 1 << 30),     # a fresh mapping only above 1 GiB
            (M_TRIM_THRESHOLD, "glibc.malloc.trim_threshold", 1 << 31),     # the heap's top given back above 2 GiB
            (M_ARENA_MAX, "glibc.malloc.arena_max", 1))                     # every thread on the one heap
_DONE: list[bool] = []


@functools.cache
def _libc():
    """glibc, or None (another platform or C library: musl has no mallopt tunables of these names)."""
    if sys.platform != "linux":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version.restype = ctypes.c_char_p
        libc.gnu_get_libc_version()
        return libc
    except (OSError, AttributeError):
        return None


def tunables(existing: str | None) -> str:
    """GLIBC_TUNABLES with SETTINGS added to ``existing`` (a setting already there is kept as it is)."""
    items = [s for s in (existing or "").split(":") if s]
    names = {s.split("=", 1)[0] for s in items}
    items += [f"{name}={value}" for _, name, value in SETTINGS if name not in names]
    return ":".join(items)


def keep_freed_memory() -> bool:
    """Set glibc's malloc to keep freed memory for reuse in this process (SETTINGS, by mallopt) and in the processes
    it starts (GLIBC_TUNABLES); once. False (nothing done): not glibc, or XYZCYL_MALLOC=default."""
    if _DONE:
        return _DONE[0]
    libc = _libc()
    ok = libc is not None and os.environ.get("XYZCYL_MALLOC", "").lower() != "default"
    if ok:
        set_here = {name.split(".")[-1] for name in (os.environ.get("GLIBC_TUNABLES") or "").split(":")}
        for param, name, value in SETTINGS:
            if name.split(".")[-1] not in set_here:     # one the user set at the start stays
                libc.mallopt(param, value)
        os.environ["GLIBC_TUNABLES"] = tunables(os.environ.get("GLIBC_TUNABLES"))
    _DONE.append(ok)
    return ok


class _Mallinfo2(ctypes.Structure):
    """glibc's struct mallinfo2 (malloc.h, glibc >= 2.33): sizes in bytes."""
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]


def heap_free_bytes() -> int | None:
    """Bytes the C heap holds free (glibc's mallinfo2 fordblks: freed, kept for the next allocations), or None (no
    glibc, or one older than 2.33)."""
    libc = _libc()
    fn = getattr(libc, "mallinfo2", None) if libc is not None else None
    if fn is None:
        return None
    fn.restype = _Mallinfo2
    return int(fn().fordblks)


def release_heap(above: int = 0) -> bool:
    """Hand the C heap's free memory back to the system (glibc's malloc_trim; nothing elsewhere) when it holds more
    than ``above`` bytes free (0: always; heap_free_bytes; where that cannot be read, always). A drive's fusion frees
    arrays of every size, keyframe after keyframe; glibc keeps what was freed for the next allocations and its mmap
    threshold rises with every large block freed, so without this the process held ~1.3 GB it no longer used (20
    PandaSet keyframes: peak 6.6 GB, 5.3 GB with it: docs/results.md "Split cells"). But each page handed back is
    a fresh page to fault in and zero again at the next keyframe: ``above`` keeps that much for reuse. True when it
    trimmed."""
    libc = _libc()
    if libc is None:
        return False
    if above > 0:
        free = heap_free_bytes()
        if free is not None and free <= above:
            return False
    libc.malloc_trim(0)
    return True


__all__ = ["SETTINGS", "heap_free_bytes", "keep_freed_memory", "release_heap", "tunables"]
