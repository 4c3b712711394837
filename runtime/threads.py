"""The runtime's threads: numpy's BLAS on one thread, and a thread map for the steps that numpy, OpenCV and numba
run outside the GIL.

numpy's BLAS on one thread in the runtime's processes:
numpy's OpenBLAS starts a pool of one thread per core and, after each call, lets its threads busy-wait for the next
one. The runtime's BLAS calls are small products ([N, 3] rays by a rotation, a camera's projections) between
numba kernels, onnxruntime and OpenCV, which run their own threads on the same cores; the waiting BLAS threads took
the cores from them: on the 2-core machine a PandaSet frame's reconstruction spent ~0.5 of its ~3.2 CPU-seconds in
OpenBLAS's thread server (perf), and with one BLAS thread it ran 10-20 % faster with the same bits (docs/results.md
"Speed, session of 2026-12-02 (night)"). threadpoolctl sets the limit on the BLAS numpy loaded (any vendor)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable

_LOCK = threading.Lock()
_DONE = False


def one_blas_thread() -> None:
    """Limit numpy's BLAS to one thread in this process, once (later calls do nothing): Reconstructor.load, the CLI
    and the server call it. A BLAS numpy did not load (none found) is left as it is."""
    global _DONE
    with _LOCK:
        if _DONE:
            return
        import numpy  # noqa: F401 - loads numpy's BLAS, which threadpoolctl finds among the loaded libraries
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")
        _DONE = True


def in_threads(fn: Callable, items: Iterable, threads: int) -> list:
    """[fn(item) for item in items], in order, on ``threads`` threads (1, or fewer than two items: in this one).
    For work that releases the GIL (numpy's loops on large arrays, OpenCV, nogil numba kernels); an exception of fn
    is raised here."""
    items = list(items)
    if threads <= 1 or len(items) < 2:
        return [fn(it) for it in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(threads, len(items)), thread_name_prefix="xyzcyl") as pool:
        return list(pool.map(fn, items))


__all__ = ["in_threads", "one_blas_thread"]
