"""The service object: one per app (``request.app.state.service``; routes get it through deps.service_of). It owns
what the endpoints do, in MLServer's shape: a route parses its request and answers in a few lines, the Service
does the work.

- its life: ``Service.create(settings)`` (checks the model, opens nothing yet), ``start()`` in the app's lifespan
  (opens the store, recovering from a crash; starts the render warm-up, then the reconstruction workers, in the
  background, and the TTL sweep), ``stop()``; ``not_ready()`` says why it cannot take work;
- scenes: ``create_scene`` (admission, the upload into a work folder (uploads.py), the record, the job, the
  optional wait), ``record`` / ``ready_record``, ``list_scenes``, ``delete_scene``, the files (``scene_file``,
  ``splat``, ``background``);
- renders: ``view_request`` (a render query to a runtime.views.ViewRequest and its ETag), ``render``,
  ``render_batch`` (the zip of frames, streamed);
- ``model_metadata`` for the Open Inference Protocol paths.

Blocking work runs off the event loop: the store's calls in threads, renders and scene loads in the render pool
(jobs.Renders), reconstructions in the worker processes (jobs.Reconstructions)."""

from __future__ import annotations

import asyncio
import errno
import hashlib
import json
import logging
import math
import shutil
import sys
import tempfile
import time
import zipfile
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from starlette.exceptions import HTTPException as StarletteHTTPException
from xyzcyl.common.wire import FORMATS, OUTPUTS, BatchIndex, FrameInfo, ViewError, ViewQuery
from xyzcyl.runtime import compile_notice
from xyzcyl.runtime.camera import CameraError, check_render_size
from xyzcyl.runtime.inference import ModelInfo, verify_model
from xyzcyl.runtime.views import ViewRequest, render_request, views_from_batch
from xyzcyl.runtime.views import request as request_of
from xyzcyl.runtime.warmup import LENS_MODELS

from .cache import BytesCache, SceneCache
from .errors import ApiError, Busy, Conflict, Invalid, NotFound, StorageFull
from .jobs import Job, Reconstructions, Renders, drive_info
from .metrics import Metrics
from .settings import Settings
from .store import SceneFailure, SceneRecord, Store, StoreFull, StoreUnavailable, new_scene_id, open_store
from .store.record import valid_id
from .uploads import RIG_PART_BYTES, ingest

_FAILED = object()   # Service._step: the step failed (its reason is the service's startup_error)
LENS_NICE = 5     # the lens compile process runs this much nicer than the renders (after ready: requests first)
log = logging.getLogger("xyzcyl.server")

NAME_TTL_S = 2.0        # resolve_scene: a name's scene is looked up again (a newer one of that name) this often
_DTYPES = {"float32": "FP32", "float16": "FP16", "int64": "INT64", "int32": "INT32", "uint8": "UINT8",
           "bool": "BOOL"}


@dataclass
class Service:
    """Everything the endpoints use, and what they do (module doc)."""

    settings: Settings
    info: ModelInfo
    store: Store
    metrics: Metrics
    renders: Renders
    reconstructions: Reconstructions
    scenes: SceneCache
    views: BytesCache
    ready: bool = False
    draining: bool = False
    startup_error: str | None = None
    started: float = field(default_factory=time.time)
    recovered: dict[str, int] = field(default_factory=dict)
    _tasks: list[asyncio.Task] = field(default_factory=list, repr=False)
    _names: dict[str, tuple[str, float]] = field(default_factory=dict, repr=False)   # resolve_scene's name -> id

    @classmethod
    def create(cls, settings: Settings) -> Service:
        """The service of ``settings``; raises runtime.inference.ModelError at once when the model folder is
        missing or altered. Nothing runs before ``start``."""
        info = verify_model(settings.model_dir())
        metrics = Metrics()
        store = open_store(settings)
        service = cls(settings=settings, info=info, store=store, metrics=metrics,
                      renders=Renders(settings, metrics),
                      reconstructions=Reconstructions(settings, store, metrics, Path(info.path)),
                      scenes=SceneCache(settings.scene_cache), views=BytesCache(settings.render_cache_bytes))
        metrics.watch_store(store)
        store.on_delete.append(service._forget)
        return service

    def _forget(self, sid: str) -> None:
        self.scenes.drop(sid)
        self.views.drop_owner(sid)

    # ------------------------------------------------------------------------------------------- its life
    async def start(self) -> None:
        """Open the store (recovering from a crash), then in the background: the warm-up and the reconstruction
        workers (``ready`` once they run), and the TTL sweep."""
        self.recovered = await asyncio.to_thread(self.store.open)
        if any(self.recovered[k] for k in ("interrupted", "files_missing", "orphans")):
            log.warning("store recovered: %s", self.recovered)
        self._tasks = [asyncio.create_task(self._start_workers(), name="start-workers"),
                       asyncio.create_task(self._sweep(), name="ttl-sweep")]

    async def stop(self) -> None:
        """Drain: not ready, the background tasks cancelled, the workers and the render pool stopped (the jobs
        still held are failed ``interrupted``)."""
        self.draining = True
        self.ready = False
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.reconstructions.stop()
        self.renders.stop()

    async def not_ready(self) -> str | None:
        """Why the service cannot take work now (None: it can): draining, loading (or its start-up error), or a
        store that cannot be reached (an s3:// store probes its bucket, at most every 2 s)."""
        if self.draining:
            return "draining"
        if not self.ready:
            return self.startup_error or "loading the model"
        return await asyncio.to_thread(self.store.health)

    async def _warm_up_renders(self, models: str) -> float:
        """The render warm-up (runtime.warmup.warm_render: "pinhole" or "lenses") in the render pool (its threads
        run ``compute_nice`` nicer, and numba's worker threads, started by the first parallel kernel, inherit
        that); the seconds. A failed warm-up render raises: the caller does not report ready over it."""
        return await asyncio.get_running_loop().run_in_executor(self.renders.pool, _warm_renders, models)

    async def _step(self, what: str, work: Awaitable):
        """``work``'s result, or _FAILED when it raised: the service is then not ready, ``what`` and the error its
        reason (logged at ERROR with the traceback)."""
        try:
            return await work
        except Exception as e:
            self.ready = False
            self.startup_error = f"{what}: {type(e).__name__}: {e}"
            log.error("%s; not ready", what, exc_info=e)
            return _FAILED

    async def _start_workers(self) -> None:
        t0 = time.perf_counter()
        renders = None
        if self.settings.warm_up:
            # before the workers start: on a cold numba cache this compiles the pinhole render kernels once, and
            # the workers then load them from the cache (compiling in both at once would take both cores twice as
            # long)
            renders = await self._step("the render warm-up failed", self._warm_up_renders("pinhole"))
            if renders is _FAILED:
                return
        workers = await self._step("the reconstruction workers did not start", self.reconstructions.start())
        if workers is _FAILED:
            return
        if self.settings.warm_up:
            log.info("warm-up took %.1f s (pinhole renders %.1f s, reconstruction workers %.1f s; numba compile "
                     "in the server process %.1f s)", time.perf_counter() - t0, renders, workers,
                     compile_notice.compile_seconds())
        self.ready = True
        log.info("model %s %s loaded; ready", self.info.name, self.info.version)
        if self.settings.warm_up:
            await self._warm_up_lenses()

    async def _warm_up_lenses(self) -> None:
        """After ready: the equirectangular and lens views (runtime.warmup.LENS_MODELS), whose projection kernels
        are compiled per camera model. The compile runs in a child process (``python -m xyzcyl.runtime.warmup
        --render-only --models lenses``, LENS_NICE steps nicer than the renders) into numba's cache: compiled in
        this process it held numba's compiler lock and a core for about a minute on a cold cache, and the first
        pinhole renders after ready took 2.8 s instead of 0.4 s. Then this process loads them (well under a second)
        through the same warm-up views; a request for one of them meanwhile compiles or loads it itself. A failure
        of that last step is the renderer's: not ready."""
        compiled, how = await self._compile_lenses()
        seconds = await self._step("the lens render warm-up failed", self._warm_up_renders("lenses"))
        if seconds is _FAILED:
            return
        log.info("lens warm-up took %.1f s (%s: compiled in a child process in %s, loaded here in %.1f s; numba "
                 "compile in the server process %.1f s)", compiled + seconds, ", ".join(LENS_MODELS), how, seconds,
                 compile_notice.compile_seconds())

    async def _compile_lenses(self) -> tuple[float, str]:
        """Run the lens warm-up in a nice child process (numba's cache is shared through NUMBA_CACHE_DIR or the
        package's __pycache__); (seconds, what happened). A child that fails is logged, not fatal: this process then
        compiles what it needs itself."""
        t0 = time.perf_counter()
        nice = min(19, self.settings.compute_nice + LENS_NICE)
        code = f"import os, runpy; os.nice({nice}); runpy.run_module('xyzcyl.runtime.warmup', run_name='__main__')"
        try:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-c", code, "--render-only", "--models", "lenses",
                stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
        except OSError as e:
            log.warning("the lens warm-up process did not start (%s); compiling in this process", e)
            return time.perf_counter() - t0, "no child process"
        try:
            _, err = await proc.communicate()
        except asyncio.CancelledError:      # the server stops: the child goes with it
            proc.kill()
            await proc.wait()
            raise
        took = time.perf_counter() - t0
        if proc.returncode != 0:
            log.warning("the lens warm-up process exited %s: %s", proc.returncode,
                        err.decode(errors="replace").strip()[-2000:])
            return took, f"a failed child process ({took:.1f} s)"
        return took, f"{took:.1f} s"

    async def _sweep(self) -> None:
        ttl = self.settings.scene_ttl_s
        if ttl is None:
            return
        while True:
            await asyncio.sleep(min(60.0, max(1.0, ttl / 4)))
            try:
                removed = await asyncio.to_thread(self.store.sweep)
            except StoreUnavailable:        # logged by the store; the next round tries again
                continue
            if removed:
                log.info("TTL removed %d scenes", len(removed))

    # ------------------------------------------------------------------------------------------- scenes
    async def record(self, sid: str) -> SceneRecord:
        """The scene's record; NotFound for an unknown or malformed id (never a path). Off the loop: an S3 store
        reads over the network."""
        rec = await asyncio.to_thread(self.store.get, sid)
        if rec is None:
            raise NotFound(f"no scene {sid!r}", "id")
        return rec

    async def ready_record(self, sid: str) -> SceneRecord:
        """The record of a ready scene; Conflict (409) while it is queued or running, or when it failed."""
        return _ready(await self.record(sid), "id")

    async def resolve_scene(self, ref: str, field: str = "scene_id") -> SceneRecord:
        """The ready scene that ``ref`` names, for the gRPC SensorsimService: a scene id, else a scene's name
        (POST /v1/scenes?name=): the newest ready scene of that name, else the newest of any state (a name found
        ready is remembered NAME_TTL_S seconds, so a simulator's renders do not list the store each time). NotFound
        when nothing is called so, Conflict when it is not ready (both naming ``field``)."""
        rec = await asyncio.to_thread(self.store.get, ref) if valid_id(ref) else None
        if rec is None and ref in self._names and time.monotonic() - self._names[ref][1] < NAME_TTL_S:
            rec = await asyncio.to_thread(self.store.get, self._names[ref][0])     # a simulator's every render
            rec = rec if rec is not None and rec.name == ref and rec.state == "ready" else None
        if rec is None:
            named = [r for r in await self._records() if r.name == ref]
            if not named:
                raise NotFound(f"no scene {ref[:200]!r}: neither a scene id nor a scene's name (get_available_scenes "
                               "lists them; POST /v1/scenes?name= names a scene)", field)
            rec = next((r for r in named if r.state == "ready"), named[0])
            if rec.state == "ready":
                self._names[ref] = (rec.id, time.monotonic())
        return _ready(rec, field)

    async def scene_names(self) -> list[str]:
        """What the gRPC SensorsimService lists: each ready scene's name, or its id when it has none, newest first,
        once each."""
        return list(dict.fromkeys(r.name or r.id for r in await self._records() if r.state == "ready"))

    async def _records(self) -> list[SceneRecord]:
        """Every record, newest first (off the loop: an S3 store reads over the network)."""
        page, _ = await asyncio.to_thread(self.store.list, 0, 1 << 30)
        return page

    async def create_scene(self, read_form: Callable[..., Awaitable[Any]], detail_stride: int | None,
                           wait: float | None, name: str | None = None,
                           keyframes: dict[str, float | None] | None = None,
                           stationary_actors: bool = False) -> SceneRecord:
        """POST /v1/scenes: admit (Busy while loading or with the queue full), read the multipart form with
        ``read_form`` (the request's ``form``) into a work folder (uploads.ingest: a rig, or a recorded drive), create
        the record (with its ``name``, checked by the route: store.name_error; a drive's frames and keyframes) and
        queue the job (detail_stride None: no detail layer); ``keyframes``: the query's keyframe_spacing and
        keyframe_gap (None: not given; Invalid naming the first given for a rig); ``stationary_actors``: a drive's
        stationary tracks become actors too (Invalid for a rig); with ``wait``, hold up to that many
        seconds (at most ``wait_max_s``) for the job to end. Returns the scene's record then (a failed one when it
        was deleted meanwhile)."""
        st = self.settings
        if not self.ready:
            raise Busy("the model is still loading; retry shortly", st.retry_after_s)
        if self.reconstructions.full():
            self.metrics.rejected.labels("reconstruct").inc()
            raise Busy(f"{self.reconstructions.pending} reconstructions are running or queued; retry later",
                       st.retry_after_s)
        n = 3 * st.max_cameras + 1                  # the parts of one rig: images, depth maps, ego masks, a sweep
        parts = max(n, st.max_drive_frames * n) + 8
        work = await asyncio.to_thread(self.store.work_dir)
        form = None
        try:
            try:
                form = await read_form(max_files=parts, max_fields=parts, max_part_size=RIG_PART_BYTES)
            except StarletteHTTPException as e:
                raise Invalid(f"the multipart body cannot be parsed: {e.detail}", "body") from None
            upload = await asyncio.to_thread(ingest, form, work, st, self.info.meta.get("input") or {})
            knobs = {k: v for k, v in (keyframes or {}).items() if v is not None}
            if upload.drive is None and (knobs or stationary_actors):
                first = next(iter(knobs)) if knobs else "stationary_actors"
                raise Invalid(f"{first}: goes with a drive upload (a 'drive' part; a rig is one timestamp)", first)
            sid = new_scene_id()
            rig = upload.rig
            cameras = [{"name": c.name, "width": c.width, "height": c.height, "model": c.model} for c in rig.cameras]
            fields = {"cameras": cameras, "detail": {"enabled": detail_stride is not None, "stride": detail_stride}}
            if name is not None:
                fields["name"] = name
            keys = None
            if upload.drive is not None:
                fields["drive"] = drive_info(upload.drive, knobs) | {"stationary_actors": stationary_actors}
                keys = fields["drive"]["keyframes"]
            try:
                await asyncio.to_thread(self.store.create, sid, fields)
            except StoreFull as e:
                raise StorageFull(str(e)) from None
            job = Job(sid=sid, work=work, detail_stride=detail_stride, input=upload.path, keyframes=keys,
                      stationary_actors=stationary_actors)
            try:
                self.reconstructions.submit(job)
            except Busy:
                self.store.delete(sid)
                raise
        except OSError as e:
            await asyncio.to_thread(shutil.rmtree, work, True)
            if e.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StorageFull(f"the store's disk is full ({e.strerror})") from None
            raise
        except BaseException:
            await asyncio.to_thread(shutil.rmtree, work, True)
            raise
        finally:
            if form is not None:
                await form.close()
        if wait:
            try:
                await asyncio.wait_for(asyncio.shield(job.done.wait()), min(wait, st.wait_max_s))
            except TimeoutError:
                pass
        return await asyncio.to_thread(self.store.get, sid) or SceneRecord(
            id=sid, name=name, state="failed", cameras=cameras,
            error=SceneFailure(code="deleted", message="the scene was deleted"))

    async def list_scenes(self, offset: int, limit: int) -> tuple[list[SceneRecord], int]:
        """A page of records, newest first, and the total count."""
        return await asyncio.to_thread(self.store.list, offset, limit)

    async def delete_scene(self, sid: str) -> None:
        await self.record(sid)
        await asyncio.to_thread(self.store.delete, sid)

    async def scene_file(self, sid: str, name: str) -> IO[bytes]:
        """A file of a ready scene's folder, opened (the scene counts as used); NotFound when it was deleted."""
        await asyncio.to_thread(self.store.touch, sid)
        return await asyncio.to_thread(self._open_scene_file, sid, name)

    def _open_scene_file(self, sid: str, name: str) -> IO[bytes]:
        try:
            return open(self.store.scene_dir(sid) / name, "rb")
        except (KeyError, FileNotFoundError):
            raise NotFound(f"scene {sid} was deleted", "id") from None

    async def splat(self, sid: str) -> bytes:
        """A ready scene's Gaussians as antimatter15's .splat (made from the loaded scene, in the render pool)."""
        await asyncio.to_thread(self.store.touch, sid)
        scene = await self.renders.run(self.load_scene, sid)
        # in the pool: a drive's tiled scene reads its Gaussians whole here (runtime.tiles)
        return await self.renders.run(self._reading, sid, lambda: scene.gaussians.splat_bytes())

    async def export(self, sid: str, fmt: str, time_s: float | None = None) -> tuple[IO[bytes], int]:
        """A ready scene in another tool's format (runtime.exports.FORMATS; the route checked ``fmt`` and ``time_s``
        with runtime.exports.check_request), built in the render pool into a work folder: (the file opened, its size
        in bytes). usdz: an AlpaSim scene artifact from the scene folder (runtime.usdz), whose scene id is the one the
        gRPC front end lists (the scene's name, else its id); the others from the loaded scene at ``time_s`` (a
        drive's actors then: runtime.exports.write_scene), glTF's root node so named. The file is gone once closed
        (unlinked while open), so nothing is left behind whether the download finishes or not."""
        from xyzcyl.runtime.exports import ExportError, write_scene
        from xyzcyl.runtime.gltf import GltfError
        from xyzcyl.runtime.spz import SpzError
        from xyzcyl.runtime.usdz import UsdzError, export_usdz

        rec = await self.ready_record(sid)
        await asyncio.to_thread(self.store.touch, sid)
        work = await asyncio.to_thread(self.store.work_dir)
        out = work / f"scene.{fmt}"

        def build() -> IO[bytes]:
            try:
                if fmt == "usdz":
                    export_usdz(self.store.scene_dir(sid), out, rec.name or rec.id)
                else:
                    self._reading(sid, write_scene, self.load_scene(sid), out, fmt, time_s, rec.name or rec.id)
                return open(out, "rb")
            except (KeyError, FileNotFoundError):
                raise NotFound(f"scene {sid} was deleted", "id") from None
            except (UsdzError, ExportError, GltfError, SpzError) as e:
                raise Conflict(f"scene {sid} cannot be exported as {fmt}: {e}", "id", code="not_exportable") from None
            finally:
                shutil.rmtree(work, ignore_errors=True)      # an open file outlives its name (POSIX)

        f = await self.renders.run(build)
        size = f.seek(0, 2)
        f.seek(0)
        return f, size

    async def background(self, sid: str, format: str) -> IO[bytes]:
        """A ready scene's background panorama file (png or exr), opened; NotFound ``no_background`` for a model
        without a background graph."""
        rec = await self.ready_record(sid)
        if not rec.background:
            raise NotFound(f"scene {sid} has no background (the model has no background graph)", "id",
                           code="no_background")
        return await self.scene_file(sid, "background.png" if format == "png" else "background.exr")

    async def actors(self, sid: str, time_s: float | None = None) -> dict:
        """A ready scene's actors (runtime.scene.Scene.actor_list: wire.ActorList's fields; their poses at
        ``time_s`` when given), from the loaded scene (in the render pool)."""
        await self.ready_record(sid)
        return await self.renders.run(lambda: self.load_scene(sid).actor_list(time_s))

    async def viewer_page(self, sid: str, camera: str | None, width: int | None, height: int | None,
                          base: str = "") -> str:
        """The web viewer's page of a ready scene (server/viewer: its data from the loaded scene, in the render
        pool), opening at input camera ``camera`` (default the rig's first), drawn at width x height pixels when
        given (one of them: the other from the camera's aspect ratio, as a render's). ApiError 503
        ``viewer_not_installed`` when the browser modules are missing (what to run); Invalid naming the field."""
        from .viewer import frames, missing, modules_dir, page, scene_data, splat_sources

        rec = await self.ready_record(sid)
        why = missing(modules_dir(self.settings))
        if why is not None:
            raise ApiError(why, None, code="viewer_not_installed", status=503)
        data = await self.renders.run(lambda: scene_data(self.load_scene(sid)))
        cams = {c["name"]: c for c in data["cameras"]}
        if camera is not None and camera not in cams:
            raise Invalid(f"camera: no camera {camera[:80]!r} in the scene's rig (cameras: {', '.join(cams)})",
                          "camera")
        cam = cams[camera or next(iter(cams))]
        if width is not None and height is None:
            height = max(1, round(width * cam["height"] / cam["width"]))
        elif height is not None and width is None:
            width = max(1, round(height * cam["width"] / cam["height"]))
        if width is not None:
            try:
                check_render_size(width, height, "width" if width >= height else "height",
                                  self.settings.max_render_side, self.settings.max_render_pixels)
            except CameraError as e:
                raise Invalid(str(e), e.field) from None
        url = f"{base}/v1/scenes/{sid}"
        data |= {"id": sid, "name": rec.name, "view": {"camera": cam["name"], "width": width, "height": height},
                 "frames": frames(), "splats": splat_sources(url),
                 "links": {"self": url, "render": f"{url}/render", "actors": f"{url}/actors"}}
        return page(base, sid, rec.name, data)

    def load_scene(self, sid: str):
        """The loaded runtime Scene of a ready scene (from the scene cache), in a worker thread."""
        from xyzcyl.runtime.scene import Scene, SceneError

        def load():
            try:
                return Scene.load(self.store.scene_dir(sid))
            except (KeyError, SceneError, FileNotFoundError):
                raise NotFound(f"scene {sid} was deleted", "id") from None

        return self.scenes.get(sid, load)

    def _rig(self, sid: str):
        """The scene's rig (calibration) from the loaded scene."""
        return self.load_scene(sid).rig

    async def scene_rig(self, sid: str):
        """A ready scene's rig (runtime.rig.Rig: calibration, ``extra`` with its ego_to_world), from the loaded scene
        (loaded in the render pool when it is not in the scene cache; Busy when the pool is full)."""
        return await self.renders.run(self._rig, sid)

    # ------------------------------------------------------------------------------------------- renders
    def check_size(self, camera, field: str = "width") -> None:
        """Invalid when a view is over the render limit (runtime.camera.check_render_size with this server's
        max_render_side / max_render_pixels: the runtime's limit unless lowered)."""
        st = self.settings
        w, h = camera.width, camera.height
        if field == "width":
            field = "width" if w >= h else "height"
        try:
            check_render_size(w, h, field, st.max_render_side, st.max_render_pixels)
        except CameraError as e:
            raise Invalid(str(e), e.field) from None

    def view_key(self, sid: str, req: ViewRequest) -> str:
        """The view's ETag: the scene, the model and the request."""
        h = hashlib.sha256(f"{sid}|{self.info.name}|{self.info.version}|{req.key()}".encode()).hexdigest()
        return f'"{h[:40]}"'

    async def view_request(self, sid: str, query: ViewQuery) -> tuple[ViewRequest, str]:
        """GET /v1/scenes/{id}/render's query as a ViewRequest of a ready scene (runtime.views.request: exactly one
        pose, optionally moved), and its ETag. Invalid naming the field otherwise."""
        await self.ready_record(sid)
        rig = await self.renders.run(self._rig, sid) if query.camera is not None else None
        try:
            req = request_of(query, rig)
            self.check_size(req.camera)
            if req.actors:
                await self.renders.run(self.check_actors, sid, [(req, "actors")])
        except ViewError as e:
            raise Invalid(str(e), e.field) from None
        return req, self.view_key(sid, req)

    def check_actors(self, sid: str, items: list[tuple[ViewRequest, str]]) -> None:
        """ViewError for a view's actor edits the scene cannot honour (runtime.scene.Scene.check_actors: unknown
        ids, poses beyond the drive), naming each request's field (``actors``, ``cameras[i].actors``)."""
        scene = self.load_scene(sid)
        for req, name in items:
            scene.check_actors(req.actors, req.time_s, name)

    async def render(self, sid: str, req: ViewRequest, key: str, force: bool = False) -> bytes:
        """The encoded view (from the render cache, else rendered in the render pool; Busy when it is full, unless
        ``force``: the later views of a batch that was admitted, as render_batch's frames)."""
        await asyncio.to_thread(self.store.touch, sid)
        return await self.renders.run(self._render_bytes, sid, req, key, force=force)

    def _render_bytes(self, sid: str, req: ViewRequest, key: str) -> bytes:
        hit = self.views.get(key)
        if hit is not None:
            self.metrics.render_cache.labels("hit").inc()
            return hit
        self.metrics.render_cache.labels("miss").inc()
        scene = self.load_scene(sid)
        t0 = time.perf_counter()
        data = self._reading(sid, render_request, scene, req)
        self.metrics.render_seconds.observe(time.perf_counter() - t0)
        self.views.put(key, data, owner=sid)
        return data

    def _reading(self, sid: str, fn, *args):
        """fn(*args) for a loaded scene that reads its tiles, chunks and camera layers as views need them
        (runtime.tiles, runtime.viewpoints, runtime.cameralayers): NotFound when the scene was deleted meanwhile and
        its files with it."""
        from xyzcyl.runtime.cameralayers import CameraLayerError
        from xyzcyl.runtime.tiles import TileError
        from xyzcyl.runtime.viewpoints import ViewpointError

        try:
            return fn(*args)
        except (TileError, ViewpointError, CameraLayerError):
            rec = self.store.get(sid)
            if rec is None or rec.state != "ready":
                self.scenes.drop(sid)
                raise NotFound(f"scene {sid} was deleted", "id") from None
            raise

    async def render_lidar(self, sid: str, req: Any) -> Any:
        """A simulated LiDAR sweep (runtime.lidarsim.LidarSweep) of ``req`` (runtime.lidarsim.LidarRequest, checked
        by its front end) in the render pool (Busy when it is full); not cached (a sweep's pose changes every
        call in a simulation)."""
        await asyncio.to_thread(self.store.touch, sid)
        return await self.renders.run(self._render_lidar, sid, req)

    def _render_lidar(self, sid: str, req: Any) -> Any:
        from xyzcyl.runtime.lidarsim import render_request as lidar_render

        scene = self.load_scene(sid)
        t0 = time.perf_counter()
        sweep = self._reading(sid, lidar_render, scene, req)
        self.metrics.render_seconds.observe(time.perf_counter() - t0)
        return sweep

    async def lidar_request(self, sid: str, model: str | None, pose: Any, end_pose: Any, time_s: float | None,
                            max_range: float | None, azimuth_step: float | None, format: str,
                            actors: str | None = None) -> Any:
        """GET /v1/scenes/{id}/lidar's query as a runtime.lidarsim.LidarRequest of a ready scene: the model (with its
        overrides), the LiDAR's pose (lidar -> the scene's frame, x forward, y left, z up) at the spin's start and
        end (end_pose None: still), the actor edits (JSON text, as GET render's ``actors``; checked against the
        scene). Invalid naming the query parameter otherwise."""
        from pydantic import TypeAdapter, ValidationError
        from xyzcyl.common.errors import FieldError
        from xyzcyl.common.poses import pose_matrix
        from xyzcyl.common.wire import ActorEdits, field_path
        from xyzcyl.runtime.camera import check_pose
        from xyzcyl.runtime.lidarsim import LidarRequest, lidar_model

        await self.ready_record(sid)
        try:
            m = lidar_model(model, max_range_m=max_range, azimuth_step_deg=azimuth_step,
                            fields={"azimuth_step_deg": "azimuth_step", "max_range_m": "max_range"})
            start = check_pose(pose_matrix(pose, "pose"), key="pose")
            end = start if end_pose is None else check_pose(pose_matrix(end_pose, "end_pose"), key="end_pose")
            if time_s is not None and not math.isfinite(time_s):
                raise ViewError("time", f"must be finite (got {time_s})")
            edits: tuple = ()
            if actors is not None:
                try:               # JSON text only (never a file name: that is the CLI's)
                    edits = TypeAdapter(ActorEdits).validate_python(actors)
                except ValidationError as e:
                    first = e.errors()[0]
                    raise ViewError(field_path(("actors", *first["loc"])), first["msg"]) from None
            req = LidarRequest(m, start, end, time_s, edits, format)
            if edits:
                await self.renders.run(self.check_actors, sid, [(req, "actors")])
        except FieldError as e:
            raise Invalid(str(e), e.field) from None
        return req

    async def render_batch(self, sid: str, doc: dict[str, Any], output: str | None, format: str | None,
                           quality: int | None) -> AsyncIterator[bytes]:
        """POST /v1/scenes/{id}/render's body ``doc`` ({"cameras": [...]} or a nerfstudio camera path) as a zip of
        frames and index.json (wire.BatchIndex), streamed frame by frame. ``output``, ``format``, ``quality``: the
        query's, which win over the body's. Everything is checked, and Busy raised when the render pool is full,
        before the first byte."""
        opts = {}
        for k, v, allowed in (("output", output, OUTPUTS), ("format", format, FORMATS)):
            val = v if v is not None else doc.get(k, "rgb" if k == "output" else "png")
            if val not in allowed:
                raise Invalid(f"{k}: one of {', '.join(allowed)}", k)
            opts[k] = val
        q = quality if quality is not None else doc.get("quality", 90)
        if isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 100:
            raise Invalid("quality: an integer in 1..100", "quality")
        rig = await self.renders.run(self._rig, sid)
        try:
            views = views_from_batch(doc, rig=rig, max_frames=self.settings.max_batch_frames)
            for i, (c, _, _) in enumerate(views):
                self.check_size(c, f"cameras[{i}]")
            reqs = [ViewRequest(camera=c, output=opts["output"], format=opts["format"], quality=q, time_s=t,
                                actors=edits) for c, t, edits in views]
            edited = [(r, f"cameras[{i}].actors") for i, r in enumerate(reqs) if r.actors]
            if edited:
                await self.renders.run(self.check_actors, sid, edited)
        except ViewError as e:
            raise Invalid(str(e), e.field) from None
        if self.renders.busy():
            await self.renders.run(lambda: None)     # raises Busy (503 + Retry-After) before anything is streamed
        await asyncio.to_thread(self.store.touch, sid)
        return self._frames(sid, reqs, opts["output"], opts["format"])

    async def _frames(self, sid: str, reqs: list[ViewRequest], output: str, format: str) -> AsyncIterator[bytes]:
        sink = _Sink()
        frames = []
        with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED) as zf:
            for i, req in enumerate(reqs):
                data = await self.renders.run(self._render_bytes, sid, req, self.view_key(sid, req), force=True)
                name = f"frame_{i:05d}{req.extension}"
                zf.writestr(name, data)
                cam = req.camera
                K = getattr(cam, "K", None)
                frames.append(FrameInfo(file=name, width=cam.width, height=cam.height,
                                        K=K.tolist() if K is not None else None,
                                        cam_to_ego=cam.cam_to_ego.tolist()))
                yield sink.take()
            index = BatchIndex(scene=sid, output=output, format=format, frames=frames)
            zf.writestr("index.json", json.dumps(index.model_dump(), indent=1))
        yield sink.take()

    # ------------------------------------------------------------------------------------------- the model
    def model_metadata(self, name: str) -> dict[str, Any]:
        """The Open Inference Protocol's model metadata (the encode graph's tensors); NotFound for another
        name."""
        info = self.info
        if name != info.name:
            raise NotFound(f"no model {name!r}; this server serves {info.name!r}", "name")
        graphs = info.meta.get("graphs", {})
        enc = graphs.get("encode", {})
        return {"name": info.name, "versions": [info.version], "platform": "onnxruntime_onnx",
                "inputs": _tensors(enc.get("inputs", [])), "outputs": _tensors(enc.get("outputs", [])),
                "parameters": {"graphs": sorted(graphs), "input": info.meta.get("input"),
                               "counts": info.meta.get("counts")}}


def _ready(rec: SceneRecord, field: str) -> SceneRecord:
    """``rec`` when it is ready; Conflict naming ``field`` while it is queued or running, or when it failed."""
    sid = rec.id
    if rec.state == "failed":
        message = rec.error.message if rec.error is not None else "unknown error"
        raise Conflict(f"scene {sid} failed: {message}", field, code="scene_failed")
    if rec.state != "ready":
        raise Conflict(f"scene {sid} is {rec.state}; poll GET /v1/scenes/{sid} until it is ready", field,
                       headers={"Retry-After": "1"})
    return rec


def _tensors(entries) -> list[dict]:
    out = []
    for e in entries:
        shape = [d if isinstance(d, int) else -1 for d in e.get("shape", [])]
        out.append({"name": e["name"], "datatype": _DTYPES.get(str(e.get("dtype")), str(e.get("dtype")).upper()),
                    "shape": shape})
    return out


def _warm_renders(models: str) -> float:
    """runtime.warmup.warm_render(models) in a temporary folder: the render path's kernels and encoders, in this
    process."""
    from xyzcyl.runtime.warmup import warm_render

    with tempfile.TemporaryDirectory(prefix="xyzcyl-warmup-") as tmp:
        return warm_render(tmp, models)


class _Sink:
    """A write-only file for zipfile (not seekable: zipfile then writes data descriptors) that hands out what
    was written so far."""

    def __init__(self):
        self.parts: list[bytes] = []

    def write(self, b) -> int:
        self.parts.append(bytes(b))
        return len(b)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out = b"".join(self.parts)
        self.parts.clear()
        return out


__all__ = ["Service"]
