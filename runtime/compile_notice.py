"""Lines on stderr when numba compiles xyzcyl kernels, so a cold start is never silent, and never exaggerated.

The numba kernels (runtime/render/kernels.py, runtime/scene.py, runtime/detail.py, ...) are cached on disk
(runtime/numba_cache.py): the first process after an install (or after a kernel's source changed, or on another
CPU model) compiles the kernels its work needs, later processes load them from the cache in well under a second.
How long a compile takes depends on what is compiled (a pinhole render's kernels about 20-40 s on 2 busy cores, a
reconstruction's more, one small kernel a second or two), so the notice promises no duration; it measures it.
``install()`` registers a listener for numba's ``numba:compile`` event (numba.core.event), which numba fires only
when it really compiles (numba/core/dispatcher.py: a signature loaded from the cache returns before the event).
On the first compile of an xyzcyl function in this process it says::

    xyzcyl: compiling numba kernels (first use after an install or an update; cached in <folder> for later runs)

and when the process exits (stderr only), with the seconds it spent compiling xyzcyl kernels::

    xyzcyl: numba compile took 23.4 s (cached: later runs load the kernels in under a second)

``compile_seconds()`` is that total so far (the server puts it in its warm-up log lines).
runtime/render/__init__.py installs it, so every kernel user (the renderer, runtime.scene, runtime.detail) has it
without torch or a server. The server passes a logging function instead (``install(log.info)``): the first line
then goes through its log and the exit line is not printed. docs/renderer.md, "numba compile cache".
"""

from __future__ import annotations

import atexit
import sys
import threading
import time
from collections.abc import Callable

PREFIX = "xyzcyl."             # the functions announced: those defined in the xyzcyl package's modules
_lock = threading.Lock()
_listener = None               # the registered numba Listener (None: not installed)
_sink: Callable[[str], None] | None = None
_said = False
_depth = 0                     # nesting of xyzcyl compiles in progress (a kernel compiles the kernels it calls)
_started = 0.0                 # perf_counter at the outermost compile's start
_seconds = 0.0                 # the seconds spent in outermost xyzcyl compiles so far


def _stderr(message: str) -> None:
    try:
        print(message, file=sys.stderr, flush=True)
    except (OSError, ValueError):      # a closed or broken stderr must never fail a render
        pass


def cache_dir(dispatcher=None) -> str:
    """Where the compiled kernels are written: NUMBA_CACHE_DIR when set; else the __pycache__ folders next to the
    sources (one per package folder: "the __pycache__ folders under <runtime>"), or the dispatcher's own cache
    folder when numba chose another one (its user-wide folder, where the sources' folders are not writable)."""
    from pathlib import Path

    from numba.core import config

    if config.CACHE_DIR:
        return str(config.CACHE_DIR)
    package = Path(__file__).resolve().parent
    path = getattr(getattr(dispatcher, "_cache", None), "_cache_path", None)
    if path is None:
        return f"the __pycache__ folders under {package} (or numba's user-wide cache)"
    p = Path(path).resolve()
    if p.name == "__pycache__" and (p.parent == package or package in p.parents):
        return f"the __pycache__ folders under {package}"
    return str(path)


def message(dispatcher=None) -> str:
    return (f"xyzcyl: compiling numba kernels (first use after an install or an update; cached in "
            f"{cache_dir(dispatcher)} for later runs)")


def done_message(seconds: float) -> str:
    return f"xyzcyl: numba compile took {seconds:.1f} s (cached: later runs load the kernels in under a second)"


def _is_ours(dispatcher) -> bool:
    module = getattr(getattr(dispatcher, "py_func", None), "__module__", None) or ""
    return module.startswith(PREFIX)


def _on_end(dispatcher) -> None:
    global _depth, _seconds
    if not _is_ours(dispatcher):
        return
    with _lock:
        _depth = max(0, _depth - 1)
        if _depth == 0:
            _seconds += time.perf_counter() - _started


def _on_compile(dispatcher) -> None:
    global _said, _depth, _started
    if not _is_ours(dispatcher):
        return
    with _lock:
        if _depth == 0:
            _started = time.perf_counter()
        _depth += 1
        if _said:
            return
        _said = True
        sink = _sink
    text = message(dispatcher)
    if sink is None:
        _stderr(text)
    else:
        try:
            sink(text)
        except Exception:       # noqa: BLE001 - a failing log handler must not fail the compile
            _stderr(text)


def install(sink: Callable[[str], None] | None = None) -> None:
    """Register the listener (idempotent: once per process, later calls only change the sink). ``sink``: called
    with the line instead of printing it to stderr (e.g. a logger's ``info``); None keeps the current one."""
    global _listener, _sink
    from numba.core import event

    with _lock:
        if sink is not None:
            _sink = sink
        if _listener is not None:
            return

        class _CompileListener(event.Listener):
            def on_start(self, ev):
                try:
                    data = ev.data if isinstance(ev.data, dict) else {}
                    _on_compile(data.get("dispatcher"))
                except Exception:       # noqa: BLE001, S110 - never fail numba's compile over a notice
                    pass

            def on_end(self, ev):
                try:
                    data = ev.data if isinstance(ev.data, dict) else {}
                    _on_end(data.get("dispatcher"))
                except Exception:       # noqa: BLE001, S110 - never fail numba's compile over a notice
                    pass

        _listener = _CompileListener()
        event.register("numba:compile", _listener)
        atexit.register(_say_total)


def _say_total() -> None:
    """At exit, when this process compiled and prints to stderr (no sink): the measured compile time."""
    if _said and _sink is None and _seconds > 0:
        _stderr(done_message(_seconds))


def compile_seconds() -> float:
    """Seconds this process has spent compiling xyzcyl kernels (outermost compiles; 0.0 when all were loaded)."""
    with _lock:
        return _seconds + (time.perf_counter() - _started if _depth else 0.0)


def said() -> bool:
    """Whether this process announced a compile (tests; the server's warm-up log)."""
    return _said


__all__ = ["cache_dir", "compile_seconds", "done_message", "install", "message", "said"]
