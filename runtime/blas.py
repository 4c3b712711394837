"""numpy's BLAS on one thread in the runtime's processes.

numpy's OpenBLAS starts a pool of one thread per core and, after each call, lets its threads busy-wait for the next
one. The runtime's BLAS calls are small products ([N, 3] rays by a rotation, a camera's projections) between
numba kernels, onnxruntime and OpenCV, which run their own threads on the same cores; the waiting BLAS threads took
the cores from them: on the 2-core machine a PandaSet frame's reconstruction spent ~0.5 of its ~3.2 CPU-seconds in
OpenBLAS's thread server (perf), and with one BLAS thread it ran 10-20 % faster with the same bits (docs/results.md
"Speed, session of 2026-12-02 (night)"). threadpoolctl sets the limit on the BLAS numpy loaded (any vendor)."""

from __future__ import annotations

import threading

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


__all__ = ["one_blas_thread"]
