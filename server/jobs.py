"""The work behind the endpoints, off the event loop and bounded:

- ``Reconstructions``: ``reconstruct_workers`` worker processes, each a one-process pool that loads the model
  once (runtime.inference.Reconstructor) and turns an upload folder into a scene folder. Jobs wait in a queue of
  ``reconstruct_queue``; beyond it ``submit`` refuses (the endpoint answers 503 + Retry-After at once). A worker
  that dies (a crash, the out-of-memory killer) or runs past ``reconstruct_timeout_s`` fails its job only: its
  process is replaced and the server goes on. A job is one rig, or a recorded drive (its keyframes reconstructed
  and fused in the one worker, under the same timeout).
- ``Renders``: a thread pool of ``render_threads`` (the numba kernels release the GIL) with at most
  ``render_queue`` renders waiting; beyond it ``run`` raises Busy (503 + Retry-After).

Each worker process runs ``_worker_init`` once and then ``_worker_reconstruct`` per job; they return typed results
(``WorkerStarted``; ``Reconstructed`` or ``ReconstructFailed``: plain dataclasses), never exceptions, so nothing
depends on pickling error types. With ``warm_up`` (the setting), ``_worker_init`` also
runs one tiny reconstruction (runtime.warmup's rig: two small pinhole cameras and a LiDAR sweep, through
``_worker_reconstruct``: the LiDAR path, the detail layer, the scene's files) after loading the model, so the
worker's numba kernels are compiled or loaded from numba's cache before the server reports ready.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import logging
import multiprocessing
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import Busy

log = logging.getLogger("xyzcyl.server")


# -------------------------------------------------------------------------------------- what the workers answer

@dataclass(frozen=True)
class Reconstructed:
    """A finished reconstruction: the scene folder is written; its metadata for the record."""

    model: dict[str, Any]            # name, version, model_json_sha256
    counts: dict[str, int]
    timings: dict[str, float]        # seconds per stage, "total" the reconstruction's
    bbox: dict[str, list[float]] | None
    gaussians: int
    background: bool
    lifting_cached: bool             # the rig's lifting inputs came from the worker's cache
    pid: int                         # the worker process

    @classmethod
    def of(cls, scene) -> Reconstructed:
        """What a runtime.scene.Scene's record says of it (its scene.json's model, counts, timings, bbox), made in
        this process."""
        meta = scene.to_json()
        return cls(model=meta["model"], counts=meta["counts"], timings=meta["timings"], bbox=meta["bbox"],
                   gaussians=meta["gaussians"]["count"], background=meta["background"] is not None,
                   lifting_cached=meta["lifting_cached"], pid=os.getpid())

    def record_fields(self, queued_s: float, worker_s: float) -> dict[str, Any]:
        """The fields the store's ``commit`` marks the record ready with: the timings gain ``queued`` (the wait
        for a worker) and ``worker_total`` (the reconstruction and writing the folder)."""
        return {"model": self.model, "counts": self.counts,
                "timings": {**self.timings, "queued": queued_s, "worker_total": worker_s}, "bbox": self.bbox,
                "gaussians": self.gaussians, "background": self.background}


@dataclass(frozen=True)
class ReconstructFailed:
    """A reconstruction that failed: ``code`` is the record's error code (``invalid_input``: the rig or an image
    cannot be used; ``storage_full``; ``error``: anything else) and ``message`` says why."""

    code: str
    message: str


@dataclass(frozen=True)
class WorkerStarted:
    """A worker's answer once it has loaded the model (and, with ``warm_up``, run its warm-up reconstruction):
    its pid and the warm-up's seconds or error (both None without a warm-up)."""

    pid: int
    warm_up_s: float | None = None
    warm_up_error: str | None = None


def drive_info(drive, knobs: dict[str, float], keys: list[int] | None = None) -> dict[str, Any]:
    """A scene record's ``drive`` (wire.DriveInfo) of a runtime.drive.Drive: its keyframes ``keys``, else as `xyzcyl
    reconstruct` picks them with ``knobs``' keyframe_spacing / keyframe_gap (the defaults for those not given)."""
    from xyzcyl.common.wire import DriveInfo
    from xyzcyl.runtime.drive import DEFAULT_MAX_GAP_S, DEFAULT_SPACING_M, pick_keyframes

    spacing = knobs.get("keyframe_spacing", DEFAULT_SPACING_M)
    gap = knobs.get("keyframe_gap", DEFAULT_MAX_GAP_S)
    t0 = drive.frames[0].timestamp_s
    return DriveInfo(frames=len(drive), keyframes=pick_keyframes(drive, spacing, gap) if keys is None else keys,
                     keyframe_spacing=spacing, keyframe_gap=gap, timestamp_s=t0,
                     duration_s=round(drive.frames[-1].timestamp_s - t0, 6), tracks=len(drive.tracks)).model_dump()


# -------------------------------------------------------------------------------------- in the worker process

_RECONSTRUCTOR = None
_WARMED = (None, None)      # (warm-up seconds, error) of this worker process


def _exit_with_parent(ppid: int, every_s: float = 1.0) -> None:
    """Exit when the server process is gone (kill -9, out-of-memory killer): nothing else would stop this worker,
    which would hold its memory forever. The parent's death re-parents the worker, so getppid() changes."""
    while True:
        time.sleep(every_s)
        if os.getppid() != ppid:
            os._exit(0)


def lower_priority(nice: int) -> None:
    """Make the calling thread (and the threads it starts later: onnxruntime's, numba's) ``nice`` steps nicer than
    now. Linux nice values are per thread, so the server's event loop keeps its priority."""
    if nice <= 0:
        return
    try:
        import threading

        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (OSError, AttributeError):      # not permitted, or not a POSIX system: run at the same priority
        pass


def _worker_init(model_dir: str, threads: int | None, server_pid: int | None = None, nice: int = 0,
                 warm_up: bool = False) -> None:
    global _RECONSTRUCTOR, _WARMED
    import threading

    # the server's pid as the server saw it: it may have died while this process was still starting. Started before
    # the priority drops (a thread inherits its creator's nice value): niced, the watchdog can wait for a core on a
    # busy machine (a CI run on a slow day found a worker still alive 5 s after the server's kill -9)
    threading.Thread(target=_exit_with_parent, args=(server_pid or os.getppid(),), name="exit-with-parent",
                     daemon=True).start()
    # then, before anything else starts threads: every thread started later inherits it (numpy's OpenBLAS pool
    # starts at the import below, onnxruntime's and numba's when the model loads)
    lower_priority(nice)

    from xyzcyl.runtime.inference import Reconstructor

    # verify=False: create_app already checked every file's sha256 (hashing 27 MB again per worker start is waste)
    _RECONSTRUCTOR = Reconstructor.load(model_dir, threads=threads, verify=False)
    if warm_up:
        _WARMED = _worker_warm_up()


def _worker_warm_up() -> tuple[float | None, str | None]:
    """One tiny reconstruction through ``_worker_reconstruct`` (runtime.warmup's rig, in a temporary folder):
    (seconds, None), or (None, the error) when it failed (the worker still serves; its first job then pays for the
    kernels)."""
    import tempfile

    from xyzcyl.runtime.inference import DEFAULT_DETAIL
    from xyzcyl.runtime.warmup import write_rig

    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="xyzcyl-warmup-") as tmp:
            rig = write_rig(Path(tmp) / "rig")
            result = _worker_reconstruct(str(rig / "rig.json"), str(Path(tmp) / "scene"), DEFAULT_DETAIL.stride)
    except Exception as e:      # noqa: BLE001 - reported to the server, never fatal to the worker
        return None, f"{type(e).__name__}: {e}"
    if isinstance(result, ReconstructFailed):
        return None, f"{result.code}: {result.message}"
    return time.perf_counter() - t0, None


def _worker_ping() -> WorkerStarted:
    """Answered once _worker_init has finished."""
    return WorkerStarted(os.getpid(), *_WARMED)


def _worker_reconstruct(rig_json: str, out_dir: str, detail_stride: int | None,
                        keyframes: list[int] | None = None,
                        stationary_actors: bool = False) -> Reconstructed | ReconstructFailed:
    """The scene of ``rig_json`` written to ``out_dir``, or why not. detail_stride: the detail layer's stride (the
    runtime's other detail settings stay at their defaults), None for no detail layer. ``keyframes``: ``rig_json``
    is an uploaded drive's drive.json and these are its keyframes (the scene folder `xyzcyl reconstruct DRIVE_JSON`
    writes: runtime.drive.save_drive_scene), with its stationary tracks as actors when ``stationary_actors``."""
    import errno
    from dataclasses import replace

    from xyzcyl.runtime.detail import DetailError
    from xyzcyl.runtime.drive import DriveError, load_drive, save_drive_scene
    from xyzcyl.runtime.inference import DEFAULT_DETAIL, InferenceError
    from xyzcyl.runtime.lidar import LidarError, has_lidar, load_lidar
    from xyzcyl.runtime.rig import RigError, load_rig
    from xyzcyl.runtime.scene import SceneError

    try:
        detail = None if detail_stride is None else replace(DEFAULT_DETAIL, stride=detail_stride)
        if keyframes is not None:
            scene, _ = save_drive_scene(_RECONSTRUCTOR, load_drive(rig_json), keyframes, out_dir, detail=detail,
                                        stationary_actors=stationary_actors)
        else:
            rig = load_rig(rig_json)
            pts = load_lidar(rig) if has_lidar(rig) else None
            scene = _RECONSTRUCTOR.reconstruct(rig, lidar=None if pts is None else pts.points, detail=detail)
            if pts is not None:     # the points left out (a non-finite coordinate) are counted, never silent
                scene.counts.update(pts.counts())
            scene.save(out_dir)
        return Reconstructed.of(scene)
    except DriveError as e:         # its ``where`` names the work folder: the field and the message only
        return ReconstructFailed("invalid_input", f"drive: {e.field}: {e.message}")
    except (RigError, InferenceError, SceneError, LidarError, DetailError) as e:
        return ReconstructFailed("invalid_input", str(e))
    except OSError as e:
        if e.errno in (errno.ENOSPC, errno.EDQUOT):
            return ReconstructFailed("storage_full", f"the store's disk is full ({e.strerror})")
        return ReconstructFailed("error", f"{type(e).__name__}: {e}")
    except MemoryError:
        return ReconstructFailed("error", "out of memory")
    except Exception as e:      # noqa: BLE001 - reported as the job's failure, never raised into the server
        return ReconstructFailed("error", f"{type(e).__name__}: {e}")


# -------------------------------------------------------------------------------------- in the server process


@dataclass
class Job:
    sid: str
    work: Path                         # upload folder: rig.json + images (removed when the job ends)
    detail_stride: int | None          # the detail layer's stride (POST ?detail_stride=), None: no detail layer
    input: str = "rig.json"            # the file of ``work`` to reconstruct: rig.json, or a drive's drive.json
    keyframes: list[int] | None = None     # a drive's keyframes (None: one rig)
    stationary_actors: bool = False        # a drive's stationary tracks become actors too (POST ?stationary_actors=)
    submitted: float = field(default_factory=time.perf_counter)
    done: asyncio.Event = field(default_factory=asyncio.Event)


class _Worker:
    """One worker process (a single-process pool, so a crash breaks only this worker's job)."""

    def __init__(self, model_dir: str, threads: int | None, nice: int = 0, warm_up: bool = False):
        self.args = (model_dir, threads)
        self.nice = nice
        self.pool = self._new(warm_up)

    def _new(self, warm_up: bool = False) -> cf.ProcessPoolExecutor:
        """A one-process pool; ``warm_up``: its process runs the warm-up reconstruction after loading the model
        (at server start only: a replacement starts when the next job is submitted, and that job would wait for it;
        the kernels are in numba's cache by then)."""
        return cf.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init,
                                      initargs=(*self.args, os.getpid(), self.nice, warm_up))

    def pids(self) -> list[int]:
        return [p.pid for p in (self.pool._processes or {}).values()]

    def replace(self) -> None:
        """Kill the process (if alive) and start a fresh pool."""
        for p in list((self.pool._processes or {}).values()):
            try:
                p.kill()
            except (OSError, AttributeError):
                pass
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = self._new()

    def shutdown(self) -> None:
        """Stop the worker process and wait for the pool to close its pipes and semaphores (without the wait, the
        resource tracker reports them as leaked at exit)."""
        for p in list((self.pool._processes or {}).values()):
            p.terminate()
        self.pool.shutdown(wait=True, cancel_futures=True)


class Reconstructions:
    def __init__(self, settings, store, metrics, model_dir: Path):
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self.model_dir = str(model_dir)
        self.capacity = settings.reconstruct_workers + settings.reconstruct_queue
        self.workers: list[_Worker] = []
        self.queue: asyncio.Queue[Job] | None = None
        self.running = 0
        self.jobs: dict[str, Job] = {}
        self._tasks: list[asyncio.Task] = []
        self.on_done: list[Callable[[str], None]] = []

    async def start(self) -> float:
        """Start the worker processes and wait until each has loaded the model and, with ``warm_up``, run its
        warm-up reconstruction (readiness). With ``warm_up`` the first worker starts alone and the others after it:
        on a cold numba cache it compiles the kernels and the others load them. Returns the seconds it took."""
        t0 = time.perf_counter()
        self.queue = asyncio.Queue()
        loop = asyncio.get_running_loop()
        warm = self.settings.warm_up
        self.workers = []
        for i in range(self.settings.reconstruct_workers):
            w = _Worker(self.model_dir, self.settings.ort_threads, self.settings.compute_nice, warm)
            self.workers.append(w)
            if warm and i == 0:
                self._started(await loop.run_in_executor(w.pool, _worker_ping))
        rest = self.workers[1:] if warm else self.workers
        for answer in await asyncio.gather(*(loop.run_in_executor(w.pool, _worker_ping) for w in rest)):
            self._started(answer)
        self._tasks = [asyncio.create_task(self._consume(w), name=f"reconstruct-{i}")
                       for i, w in enumerate(self.workers)]
        return time.perf_counter() - t0

    @staticmethod
    def _started(answer: WorkerStarted) -> None:
        if answer.warm_up_error is not None:
            log.error("reconstruction worker %d: the warm-up reconstruction failed (%s); its first job compiles "
                      "or loads the kernels instead", answer.pid, answer.warm_up_error)
        elif answer.warm_up_s is not None:
            log.info("reconstruction worker %d: warm-up reconstruction took %.1f s", answer.pid, answer.warm_up_s)

    async def stop(self) -> None:
        """Stop the consumers and the workers; the jobs this process still held (queued or running) are failed
        with code ``interrupted`` at once (a shared store's other replicas need not wait for a timeout)."""
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for w in self.workers:
            w.shutdown()
        left = list(self.jobs.values())
        if self.queue is not None:
            while not self.queue.empty():
                job = self.queue.get_nowait()
                if job not in left:
                    left.append(job)
        for job in left:
            try:
                await asyncio.to_thread(self.store.fail, job.sid, "interrupted", "the server stopped while this "
                                        "reconstruction was queued or running; post the rig again")
            except OSError:
                log.warning("could not mark %s interrupted", job.sid)
            shutil.rmtree(job.work, ignore_errors=True)
            job.done.set()

    @property
    def pending(self) -> int:
        return (self.queue.qsize() if self.queue is not None else 0) + self.running

    def full(self) -> bool:
        return self.pending >= self.capacity

    def submit(self, job: Job) -> None:
        """Queue a job, or raise Busy when the queue is full (the caller answers 503 at once)."""
        if self.queue is None or self.full():
            raise Busy(f"{self.pending} reconstructions are running or queued (the limit is {self.capacity}); "
                       "retry later", self.settings.retry_after_s)
        self.jobs[job.sid] = job
        self.queue.put_nowait(job)
        self.metrics.queue_depth.labels("reconstruct").set(self.pending)

    async def _consume(self, worker: _Worker) -> None:
        loop = asyncio.get_running_loop()
        while True:
            job = await self.queue.get()
            self.running += 1
            self.metrics.queue_depth.labels("reconstruct").set(self.pending)
            try:
                await self._run(loop, worker, job)
            except Exception:
                log.exception("reconstruction %s", job.sid)
                try:        # the store may be unwritable too (a full disk): this consumer must go on regardless
                    await asyncio.to_thread(self.store.fail, job.sid, "internal",
                                            "the reconstruction failed unexpectedly")
                except Exception:
                    log.exception("could not mark %s failed", job.sid)
            finally:
                self.running -= 1
                self.metrics.queue_depth.labels("reconstruct").set(self.pending)
                shutil.rmtree(job.work, ignore_errors=True)
                self.jobs.pop(job.sid, None)
                job.done.set()
                for cb in self.on_done:
                    cb(job.sid)

    async def _run(self, loop, worker: _Worker, job: Job) -> None:
        if await asyncio.to_thread(self.store.update, job.sid, state="running") is None:
            return                      # deleted while queued
        out = job.work / "scene"
        t0 = time.perf_counter()
        fut = loop.run_in_executor(worker.pool, _worker_reconstruct, str(job.work / job.input), str(out),
                                   job.detail_stride, job.keyframes, job.stationary_actors)
        try:
            result = await asyncio.wait_for(fut, self.settings.reconstruct_timeout_s)
        except TimeoutError:
            worker.replace()
            await self._failed(job, "timeout", "the reconstruction ran longer than "
                               f"{self.settings.reconstruct_timeout_s} s and was stopped")
            return
        except cf.process.BrokenProcessPool:
            worker.replace()
            await self._failed(job, "worker_crashed", "the reconstruction worker died (crash or out of memory); "
                               "the job was not finished")
            return
        seconds = time.perf_counter() - t0
        if isinstance(result, ReconstructFailed):
            await self._failed(job, result.code, result.message)
            return
        from .store import StoreFull

        try:
            rec = await asyncio.to_thread(self.store.commit, job.sid, out,
                                          **result.record_fields(t0 - job.submitted, seconds))
        except StoreFull as e:
            await self._failed(job, "storage_full", str(e))
            return
        if rec is not None:
            self.metrics.reconstructions.labels("ready").inc()
            self.metrics.reconstruct_seconds.observe(seconds)

    async def _failed(self, job: Job, code: str, message: str) -> None:
        self.metrics.reconstructions.labels(code).inc()
        try:
            await asyncio.to_thread(self.store.fail, job.sid, code, message)
        except OSError as e:       # a full disk: the record stays failed in memory (interrupted after a restart)
            log.warning("could not write the failure of %s (%s): %s", job.sid, code, e)


def render_threads(asked: int) -> int:
    """The render pool's threads: ``asked`` (Settings.render_threads), or 1 where numba has no thread-safe threading
    layer (runtime.numba_cache.threadsafe: its workqueue layer aborts the process when two renders run kernels at
    once), with a warning in the log."""
    from xyzcyl.runtime.numba_cache import threadsafe

    if asked > 1 and not threadsafe():
        log.warning("render_threads %d -> 1: numba has no thread-safe threading layer here (its workqueue layer "
                    "aborts when two threads run kernels at once); install libgomp1 or `pip install tbb`", asked)
        return 1
    return asked


class Renders:
    """A bounded thread pool for renders and other CPU work of the request path."""

    def __init__(self, settings, metrics):
        self.settings = settings
        self.metrics = metrics
        self.threads = render_threads(settings.render_threads)
        self.limit = self.threads + settings.render_queue
        self.inflight = 0
        # renders run nicer than the event loop (compute_nice): health and admission are answered at once under load
        self.pool = cf.ThreadPoolExecutor(self.threads, thread_name_prefix="render",
                                          initializer=lower_priority, initargs=(settings.compute_nice,))

    def busy(self) -> bool:
        return self.inflight >= self.limit

    async def run(self, fn: Callable[..., Any], *args: Any, force: bool = False) -> Any:
        """fn(*args) in the pool; Busy (503) when the pool and its queue are full, unless ``force`` (the later
        frames of a batch that was admitted)."""
        if self.busy() and not force:
            self.metrics.rejected.labels("render_queue").inc()
            raise Busy(f"{self.inflight} renders are running or queued (the limit is {self.limit}); retry later",
                       self.settings.retry_after_s)
        self.inflight += 1
        self.metrics.queue_depth.labels("render").set(self.inflight)
        try:
            return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)
        finally:
            self.inflight -= 1
            self.metrics.queue_depth.labels("render").set(self.inflight)

    def stop(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


__all__ = ["Job", "ReconstructFailed", "Reconstructed", "Reconstructions", "Renders", "WorkerStarted"]
