"""numba's on-disk cache made safe for several processes and for kernels specialised by closure: ``njit``.

Every cached xyzcyl kernel is compiled through this module's ``njit`` (numba's own, with ``cache=True`` served by
``CheckedFunctionCache`` instead of numba's ``FunctionCache``). Why (docs/renderer.md "numba compile cache"):

numba keeps one index file per function (``<qualname>-<line>.pyXY.nbi``: key -> data file) and numbers its data
files 1, 2, ... in the order entries are added. Every compiled signature of a function, and every variant of a
closure (the renderer compiles its projection once per camera model: kernels.project_kernel(model)), shares that
index. numba's ``save`` reads the index, picks the first free number, writes the index, and only then writes the
data file; its ``load`` trusts the index. So

- two processes that compile two entries of one function at once (``xyzcyl serve``: the warm-up renders in the
  server process while the reconstruction workers compile the detail layer's renders; the test suite's servers)
  can both pick number 2; one index entry then names the other's machine code, and
- a reader that reads the index between a writer's index write and its data write, or after the source changed
  (numba then restarts the numbering, over the stale files), loads whatever the data file held before.

Loaded under the wrong key, the projection kernel of one camera model ran another model's culls: the pre-count
that sizes the outputs came from a narrower model, the projection wrote past it, and f-theta and equirectangular
renders failed with an IndexError in a long-running server (or, with another pairing, could draw wrong pixels).

``CheckedIndexDataCacheFile`` fixes both: a writer holds an exclusive lock on ``<index>.lock`` across its
read-modify-write of the index, writes the data file before the index names it, and stores the key and the source
stamp inside the data; a reader accepts data only when both match (anything else, a stale or foreign file, is a
miss: the kernel compiles again and overwrites it). Readers take no lock, so a read-only cache still loads.

What the cache cannot tell apart is two functions of one qualified name: numba names machine code by the qualified
name and a per-process counter, so closures specialised per configuration must carry the configuration in their
name (runtime.render.kernels.per_model), or two of them compiled in two processes share a symbol and one process
that loads both runs one's code for the other.

The source stamp is also wider than numba's (which is the defining file's mtime and size only, so a kernel whose
callee in another file changed loaded stale code): it covers the kernel's module and what it imports from the
package, following the modules that define numba code themselves (``source_files``).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import re
from pathlib import Path

import numba
from numba.core.caching import FunctionCache, IndexDataCacheFile

_ROOT = Path(__file__).resolve().parent.parent      # the xyzcyl package root (runtime/, model_export/, ...)
_PACKAGES = ("runtime", "model_export")             # the folders whose modules define numba code


def _module_file(base: Path, level: int, module: str | None, name: str | None = None) -> Path | None:
    """The package file a relative import ``from <level dots><module> import <name>`` in a file of ``base`` names
    (a module file, or a package's __init__.py), None when it is not one of ours."""
    folder = base
    for _ in range(level - 1):
        folder = folder.parent
    parts = [*(module.split(".") if module else []), *([name] if name else [])]
    for k in range(len(parts), 0, -1):
        p = folder.joinpath(*parts[:k])
        for cand in (p.with_suffix(".py"), p / "__init__.py"):
            if cand.is_file():
                return cand
    return None


# a "from X import a, b" statement (X relative, or xyzcyl.*), its names possibly in parentheses over several lines;
# read with a regular expression, not ast: parsing every kernel module at import took 0.24 s of each process's start
# (0.03 s now); it also counts an import written in a docstring, which only widens a stamp (never narrows it)
_FROM_IMPORT = re.compile(r"^[ \t]*from[ \t]+(\.+[\w.]*|xyzcyl\.[\w.]+)[ \t]+import[ \t]+(\([^)]*\)|[^\n#]+)", re.M)


@functools.cache
def _imports(path: Path) -> tuple[tuple[Path, ...], bool]:
    """(the package modules ``path`` imports (relative or ``xyzcyl.`` imports), whether it defines numba code)."""
    try:
        text = path.read_text()
    except OSError:                  # removed while we look: it defines nothing any more
        return (), False
    out: set[Path] = set()
    for source, names in _FROM_IMPORT.findall(text):
        if source.startswith("."):
            module = source.lstrip(".")
            level, base = len(source) - len(module), path
        else:
            level, module, base = 1, source.split(".", 1)[1], _ROOT / "_"       # relative to the package root
        for name in names.strip("()").replace("\n", " ").split(","):
            name = name.split(" as ")[0].strip()
            if name:
                f = _module_file(base.parent, level, module or None, name)
                if f is not None:
                    out.add(f)
    return tuple(sorted(out)), "njit" in text


@functools.cache
def source_files(module: Path) -> tuple[Path, ...]:
    """The sources a kernel of ``module`` (a .py file) may hold code or constants of: the module, the package
    modules it imports, and, through every imported module that defines numba functions itself, theirs in turn
    (numba compiles a callee from another module into its caller and freezes the globals it reads: kernels.py's
    kernels hold lensmap.py's lens code, which holds runtime/lenses.py's distortion terms). Modules without numba
    code are not followed further, so an edit of the detail layer does not recompile the renderer."""
    seen: set[Path] = set()
    todo = [Path(module).resolve()]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        imported, has_numba = _imports(p)
        if has_numba or p == Path(module).resolve():
            todo.extend(imported)
    return tuple(sorted(seen))


def source_stamp(module: Path) -> tuple:
    """((path relative to the package root, mtime_ns, size), ...) of source_files(module): an edit of any of them
    invalidates the module's cached kernels."""
    stamp = []
    for p in source_files(module):
        try:
            st = p.stat()
        except OSError:
            continue
        rel = p.relative_to(_ROOT) if _ROOT in p.parents else p
        stamp.append((str(rel), st.st_mtime_ns, st.st_size))
    return tuple(stamp)


class CheckedIndexDataCacheFile(IndexDataCacheFile):
    """numba's index + data files with a locked, data-first save and a load that checks what it read (see the
    module docstring)."""

    def save(self, key, data):
        with self._locked():
            overloads = self._load_index()
            name = overloads.get(key)
            if name is None:
                used = set(overloads.values())
                number = 1
                while self._data_name(number) in used:
                    number += 1
                name = self._data_name(number)
            self._save_data(name, (key, self._source_stamp, data))     # before any index names it
            if overloads.get(key) != name:
                overloads[key] = name
                self._save_index(overloads)

    def load(self, key):
        name = self._load_index().get(key)
        if name is None:
            return None
        try:
            stored = self._load_data(name)
        except Exception:            # removed, cut short or not ours (numba's own format): a miss, compile again
            return None
        if not (isinstance(stored, tuple) and len(stored) == 3 and stored[0] == key
                and stored[1] == self._source_stamp):
            return None
        return stored[2]

    @contextlib.contextmanager
    def _locked(self):
        """An exclusive lock on ``<index>.lock`` (fcntl, so it is released when the process dies)."""
        with open(self._index_path + ".lock", "a+b") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)


class CheckedFunctionCache(FunctionCache):
    """numba's FunctionCache (same folder, same file names) with CheckedIndexDataCacheFile and source_stamp()."""

    def __init__(self, py_func):
        super().__init__(py_func)
        import inspect

        module = Path(inspect.getsourcefile(py_func) or self._impl.locator._py_file)
        self._cache_file = CheckedIndexDataCacheFile(cache_path=self._cache_path,
                                                     filename_base=self._impl.filename_base,
                                                     source_stamp=(self._impl.locator.get_source_stamp(),
                                                                   source_stamp(module)))


def njit(*args, **options):
    """numba.njit; with ``cache=True`` the compiled code is cached through CheckedFunctionCache. Use as numba's:
    ``@njit``, ``@njit(cache=True, parallel=True)``, ``njit(cache=True)(f)``."""
    cache = options.pop("cache", False)

    def wrap(func):
        dispatcher = numba.njit(**options)(func)
        if cache:
            dispatcher._cache = CheckedFunctionCache(dispatcher.py_func)   # what enable_caching() sets
        return dispatcher

    if args and callable(args[0]) and len(args) == 1 and not options:
        return wrap(args[0])
    if args:
        raise TypeError("njit: pass options by keyword (njit(cache=True, ...)); signatures are not supported")
    return wrap


THREADSAFE_LAYERS = ("tbb", "omp")      # numba threading layers that let several threads launch parallel kernels


@functools.cache
def threadsafe() -> bool:
    """Whether numba's threading layer lets two threads run parallel kernels at once: TBB or OpenMP (GNU's libgomp).
    Where neither loads (a slim container image has no libgomp1; no tbb wheel) numba falls back to its workqueue
    layer, which aborts the whole process the moment two threads launch parallel kernels together. Those that would
    (runtime.drive's keyframe made ahead in a thread, the service's render pool) run one at a time instead when this
    is False. Starts numba's threads (what the first parallel kernel does anyway)."""
    try:
        from numba.np.ufunc import parallel

        parallel._launch_threads()
        return numba.threading_layer() in THREADSAFE_LAYERS
    except Exception:       # numba's internals moved, or no layer loads: assume the worst
        return False


__all__ = ["CheckedFunctionCache", "CheckedIndexDataCacheFile", "THREADSAFE_LAYERS", "njit", "source_files",
           "source_stamp", "threadsafe"]
