"""The SensorsimService over gRPC (grpc.aio), beside the HTTP routes: the same Service (scenes, store, render pool,
render cache, limits, metrics) and the same API keys. `xyzcyl serve --grpc-port N` starts it in the app's lifespan
(app.py); docs/simulators.md says what AlpaSim and CARLA's NuRec integration call and what they get.

Like a route, each method parses its request and answers in a few lines: frames.py turns the protocol's messages
into a runtime ViewRequest (its camera made directly from the protocol's intrinsics and pose, its time the middle of
the exposure), rendered by the HTTP routes' one render path (Service.render -> runtime.views.render_request);
get_available_trajectories answers the scene's frames (runtime.scene.Scene.timeline: a drive's every frame, a
one-rig scene its one). render_lidar answers a simulated sweep (frames.lidar_request -> Service.render_lidar ->
runtime.lidarsim; docs/simulators.md "LiDAR"). Errors become status codes, the message naming the field:

    UNAUTHENTICATED      API keys set and no valid ``authorization: Bearer KEY`` or ``x-api-key: KEY`` metadata
    INVALID_ARGUMENT     a bad request field (frames.py's ViewError, the render limits), a lens the renderer cannot
                         draw yet (field ``camera_intrinsics.<param>``)
    NOT_FOUND            an unknown scene (neither an id nor a name)
    FAILED_PRECONDITION  a scene that is queued, running or failed
    RESOURCE_EXHAUSTED   the render pool and its queue are full (HTTP's 503), the store is full
    UNAVAILABLE          the server is draining, or the store cannot be reached
    UNIMPLEMENTED        render_aggregated
    INTERNAL             anything else (logged)

CARLA's NuRec integration speaks a variant of the protocol (docs/simulators.md "CARLA's variant"): its extra
fields (``trajectory_idx``) are unknown fields here and ignored, its ``shut_down`` is answered (the server keeps
serving), and its empty OpenCV pinhole message reads as a pinhole without focal length (INVALID_ARGUMENT naming it).

The field is also sent as the trailing metadata ``xyzcyl-field``. batch_render_rgb answers every item once, in
order, echoing its camera_name: an item that fails has success false and ``error_message`` "<CODE>: <field>:
<message>" (the call itself fails only for UNAUTHENTICATED, RESOURCE_EXHAUSTED or UNAVAILABLE, before any item
is rendered). A batch is admitted whole, as HTTP's (RESOURCE_EXHAUSTED when the pool is full), and its items are
rendered one after the other, as HTTP's frames: one render already keeps every core busy (numba), and six renders
at once in the pool took 0.31 s where one after the other took 0.20 s (6 x 512x320, 2 cores;
benchmarks/grpc_bench.py)."""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import Awaitable, Callable
from typing import Any

import grpc
from xyzcyl.common.errors import FieldError
from xyzcyl.common.wire import ViewError

from ..deps import key_matches
from ..errors import ApiError, Busy, Conflict, Invalid, NotFound
from ..service import Service
from ..store import StoreUnavailable
from . import common_pb2, frames, sensorsim_pb2, sensorsim_pb2_grpc

log = logging.getLogger("xyzcyl.server")

API_VERSION = (0, 1, 0)          # this server's SensorsimService: get_version's grpc_api_version
GRACE_S = 5.0                    # calls in flight may finish this long when the server stops
StatusCode = grpc.StatusCode
_BY_STATUS = {401: StatusCode.UNAUTHENTICATED, 404: StatusCode.NOT_FOUND, 409: StatusCode.FAILED_PRECONDITION,
              413: StatusCode.INVALID_ARGUMENT, 415: StatusCode.INVALID_ARGUMENT, 422: StatusCode.INVALID_ARGUMENT,
              503: StatusCode.RESOURCE_EXHAUSTED, 507: StatusCode.RESOURCE_EXHAUSTED}
_UNIMPLEMENTED = {
    "render_aggregated": "call batch_render_rgb (cameras) and render_lidar instead",
}


class Failure(Exception):
    """A call's answer other than OK: a status code, a message and the field at fault."""

    def __init__(self, code: StatusCode, message: str, field: str | None = None):
        super().__init__(message)
        self.code, self.message, self.field = code, message, field


def failure(e: BaseException) -> Failure:
    """The status an exception answers with (module docstring)."""
    if isinstance(e, Failure):
        return e
    if isinstance(e, ApiError):     # its message may not start with its field, as FieldError's always do
        named = e.field is None or e.message.startswith(f"{e.field}:")
        return Failure(_BY_STATUS.get(e.status, StatusCode.INTERNAL),
                       e.message if named else f"{e.field}: {e.message}", e.field)
    if isinstance(e, FieldError):           # ViewError (frames.py), a runtime camera or lens refusal
        return Failure(StatusCode.INVALID_ARGUMENT, str(e), e.field)
    if isinstance(e, StoreUnavailable):
        return Failure(StatusCode.UNAVAILABLE, str(e))
    log.error("unexpected error in a gRPC call", exc_info=e)
    return Failure(StatusCode.INTERNAL, "an unexpected error occurred; it was logged")


class SensorsimServicer(sensorsim_pb2_grpc.SensorsimServiceServicer):
    """The SensorsimService of one Service (module docstring)."""

    def __init__(self, service: Service):
        self.service = service
        self.settings = service.settings
        self.metrics = service.metrics

    # -- every call: the key, the errors, the metrics ------------------------------------------------------------
    async def _answer(self, method: str, context: grpc.aio.ServicerContext, work: Callable[[], Awaitable[Any]],
                      open_call: bool = False) -> Any:
        t0 = time.perf_counter()
        code = StatusCode.OK
        try:
            try:
                if self.service.draining:
                    raise Failure(StatusCode.UNAVAILABLE, "the server is shutting down")
                if not open_call:
                    self._authorize(context)
                return await work()
            except asyncio.CancelledError:
                code = StatusCode.CANCELLED
                raise
            except Exception as e:          # noqa: BLE001 - every error becomes a status (failure())
                f = failure(e)
                code = f.code
            await context.abort(f.code, f.message, trailing_metadata=(("xyzcyl-field", f.field),) if f.field else ())
        finally:
            self.metrics.grpc_requests.labels(method, code.name).inc()
            self.metrics.grpc_latency.labels(method).observe(time.perf_counter() - t0)

    def _authorize(self, context: grpc.aio.ServicerContext) -> None:
        keys = self.settings.api_keys
        if not keys:
            return
        md = {k.lower(): v for k, v in (context.invocation_metadata() or ()) if isinstance(v, str)}
        given = md.get("x-api-key")
        if given is None:
            scheme, _, token = md.get("authorization", "").partition(" ")
            given = token.strip() if scheme.lower() == "bearer" else None
        if not given or not key_matches(given, keys):
            raise Failure(StatusCode.UNAUTHENTICATED, "a valid API key is required (metadata authorization: Bearer "
                                                      "KEY or x-api-key: KEY)")

    # -- the scene catalogue -----------------------------------------------------------------------------------
    async def get_version(self, request, context):
        async def work():
            from .. import __version__

            info = self.service.info
            major, minor, patch = API_VERSION
            return common_pb2.VersionId(
                version_id=f"xyzcyl {__version__} ({info.name} {info.version})",
                git_hash=os.environ.get("XYZCYL_GIT_HASH", ""),
                grpc_api_version=common_pb2.VersionId.APIVersion(major=major, minor=minor, patch=patch))
        return await self._answer("get_version", context, work, open_call=True)

    async def get_available_scenes(self, request, context):
        async def work():
            return common_pb2.AvailableScenesReturn(scene_ids=await self.service.scene_names())
        return await self._answer("get_available_scenes", context, work)

    async def get_available_cameras(self, request, context):
        async def work():
            rec = await self.service.resolve_scene(request.scene_id)
            rig = await self.service.scene_rig(rec.id)
            return sensorsim_pb2.AvailableCamerasReturn(available_cameras=frames.available_cameras(rig))
        return await self._answer("get_available_cameras", context, work)

    async def get_available_trajectories(self, request, context):
        async def work():
            rec = await self.service.resolve_scene(request.scene_id)
            scene = await self.service.renders.run(self.service.load_scene, rec.id)
            times, poses = scene.timeline()
            return sensorsim_pb2.AvailableTrajectoriesReturn(available_trajectories=[
                sensorsim_pb2.AvailableTrajectoriesReturn.AvailableTrajectory(
                    trajectory=frames.trajectory_message(times, poses))])
        return await self._answer("get_available_trajectories", context, work)

    async def get_available_ego_masks(self, request, context):
        async def work():
            return sensorsim_pb2.AvailableEgoMasksReturn()      # none: an empty answer is a valid one
        return await self._answer("get_available_ego_masks", context, work)

    # -- renders -------------------------------------------------------------------------------------------------
    async def _render(self, req: sensorsim_pb2.RGBRenderRequest, prefix: str, rigs: dict[str, Any],
                      force: bool) -> bytes:
        """One RGBRenderRequest through the one render path: the scene (``rigs`` caches each scene's id and rig
        for the call), frames.view_request -> Service.render (render cache, render pool)."""
        field = f"{prefix}scene_id"
        if not req.scene_id:
            raise ViewError(field, "is empty: give a scene's name or id (get_available_scenes)")
        if req.scene_id not in rigs:
            rec = await self.service.resolve_scene(req.scene_id, field)
            rigs[req.scene_id] = (rec.id, await self.service.scene_rig(rec.id))
        sid, rig = rigs[req.scene_id]
        view = frames.view_request(req, frames.scene_ego_to_world(rig), prefix)
        self.service.check_size(view.camera, f"{prefix}resolution_w")
        if view.actors:         # the scene's refusals (unknown track ids, poses kilometres away) named as the proto's
            try:
                await self.service.renders.run(self.service.check_actors, sid, [(view, f"{prefix}dynamic_objects")])
            except ViewError as e:
                raise ViewError(frames.rename_actor_field(e.field), e.message) from None
        return await self.service.render(sid, view, self.service.view_key(sid, view), force=force)

    async def render_rgb(self, request, context):
        async def work():
            return sensorsim_pb2.RGBRenderReturn(image_bytes=await self._render(request, "", {}, force=False))
        return await self._answer("render_rgb", context, work)

    async def batch_render_rgb(self, request, context):
        async def work():
            items = list(request.items)
            if not items:
                raise Invalid("items: is empty (one item per camera)", "items")
            if len(items) > self.settings.max_batch_frames:
                raise Invalid(f"items: {len(items)} items, more than the {self.settings.max_batch_frames} allowed "
                              "in one call", "items")
            if self.service.renders.busy():          # admitted whole, as HTTP's batch: its renders then queue
                self.service.metrics.rejected.labels("render_queue").inc()
                raise Busy(f"{self.service.renders.inflight} renders are running or queued; retry later",
                           self.settings.retry_after_s)
            rigs: dict[str, Any] = {}
            # the scenes first, once each (a NOT_FOUND or not-ready scene fails its items, not the call)
            for sid in dict.fromkeys(it.request.scene_id for it in items if it.request.scene_id):
                try:
                    rec = await self.service.resolve_scene(sid)
                    rigs[sid] = (rec.id, await self.service.scene_rig(rec.id))
                except (NotFound, Conflict) as e:
                    rigs[sid] = e
            results = [await self._item(it, i, rigs) for i, it in enumerate(items)]     # in turn (docstring)
            return sensorsim_pb2.BatchRGBRenderReturn(items=results)
        return await self._answer("batch_render_rgb", context, work)

    async def _item(self, it: sensorsim_pb2.BatchRGBRenderRequestItem, i: int,
                    rigs: dict[str, Any]) -> sensorsim_pb2.BatchRGBRenderReturnItem:
        try:
            got = rigs.get(it.request.scene_id)
            if isinstance(got, ApiError):            # its scene: unknown or not ready (named in this item's terms)
                raise ApiError(got.message, f"items[{i}].request.{got.field}", status=got.status)
            data = await self._render(it.request, f"items[{i}].request.", rigs, force=True)
        except Exception as e:              # noqa: BLE001 - an item's failure is its answer (module docstring)
            f = failure(e)
            return sensorsim_pb2.BatchRGBRenderReturnItem(camera_name=it.camera_name, success=False,
                                                          error_message=f"{f.code.name}: {f.message}")
        return sensorsim_pb2.BatchRGBRenderReturnItem(camera_name=it.camera_name, success=True,
                                                      result=sensorsim_pb2.RGBRenderReturn(image_bytes=data))

    # -- CARLA's variant of the protocol ---------------------------------------------------------------------------
    async def shut_down(self, request, context):
        """CARLA's NuRec example asks its renderer to stop when it is done: answered (Empty), and logged; xyzcyl
        keeps serving (it is a service shared by its HTTP and gRPC clients: stop it as a process, SIGTERM)."""
        async def work():
            log.info("gRPC shut_down asked by a client (CARLA's protocol): answered; the server keeps serving "
                     "(stop it with SIGTERM)")
            return common_pb2.Empty()
        return await self._answer("shut_down", context, work)

    # -- what is not implemented -----------------------------------------------------------------------------------
    async def _unimplemented(self, method: str, context):
        async def work():
            raise Failure(StatusCode.UNIMPLEMENTED, f"{method}: {_UNIMPLEMENTED[method]} (docs/simulators.md)")
        return await self._answer(method, context, work)

    async def render_lidar(self, request, context):
        """A simulated LiDAR sweep (runtime.lidarsim; docs/simulators.md "LiDAR"): frames.lidar_request ->
        Service.render_lidar (render pool; not cached) -> frames.lidar_return."""
        async def work():
            if not request.scene_id:
                raise ViewError("scene_id", "is empty: give a scene's name or id (get_available_scenes)")
            rec = await self.service.resolve_scene(request.scene_id)
            rig = await self.service.scene_rig(rec.id)
            req = frames.lidar_request(request, frames.scene_ego_to_world(rig))
            if req.actors:
                try:
                    await self.service.renders.run(self.service.check_actors, rec.id, [(req, "dynamic_objects")])
                except ViewError as e:
                    raise ViewError(frames.rename_actor_field(e.field), e.message) from None
            sweep = await self.service.render_lidar(rec.id, req)
            return frames.lidar_return(sweep)
        return await self._answer("render_lidar", context, work)

    async def render_aggregated(self, request, context):
        return await self._unimplemented("render_aggregated", context)


async def start(service: Service) -> tuple[grpc.aio.Server, int]:
    """A started grpc.aio server answering the SensorsimService of ``service`` on settings.host and
    settings.grpc_port (0: a free port), and the port it listens on. Raises OSError when it cannot bind."""
    st = service.settings
    server = grpc.aio.server()
    sensorsim_pb2_grpc.add_SensorsimServiceServicer_to_server(SensorsimServicer(service), server)
    host = f"[{st.host}]" if ":" in st.host else st.host
    try:
        port = server.add_insecure_port(f"{host}:{st.grpc_port}")
    except RuntimeError as e:
        raise OSError(f"--grpc-port: cannot listen on {st.host}:{st.grpc_port} ({e})") from None
    if port == 0:
        raise OSError(f"--grpc-port: cannot listen on {st.host}:{st.grpc_port}")
    await server.start()
    log.info("SensorsimService (gRPC) listening on %s:%d", st.host, port)
    return server, port


async def stop(server: grpc.aio.Server) -> None:
    """Stop taking calls; those in flight may finish for GRACE_S seconds."""
    await server.stop(GRACE_S)


__all__ = ["API_VERSION", "SensorsimServicer", "failure", "start", "stop"]
