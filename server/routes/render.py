"""Rendered views of a ready scene: GET one view from query parameters, POST a batch (a zip of frames, streamed).
What a render request means (camera, pose, size, output, format) is runtime.views.ViewRequest; this module only
reads it from HTTP."""

from __future__ import annotations

import asyncio
import hashlib
import json
import time
import zipfile
from typing import Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from xyzcyl.runtime.views import (
    ViewError,
    ViewRequest,
    camera_from_carla_pose,
    camera_from_opencv,
    camera_from_rig,
    cameras_from_batch,
    render_request,
)

from ..app import Service, service_of
from ..errors import Invalid, UnsupportedMedia
from ..params import known_query
from ..security import require_key
from .scenes import ERRORS, load_scene, ready_record

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["render"], dependencies=[Depends(require_key), Depends(known_query)])

_CARLA = ("x", "y", "z", "pitch", "yaw", "roll")
_MEDIA = {"png": "image/png", "jpeg": "image/jpeg", "exr": "image/x-exr"}


def check_size(service: Service, camera, field: str = "width") -> None:
    st = service.settings
    w, h = camera.width, camera.height
    if max(w, h) > st.max_render_side:
        raise Invalid(f"{field}: a view of {w}x{h} has a side over the limit of {st.max_render_side} pixels",
                      ("width" if w >= h else "height") if field == "width" else field)
    if w * h > st.max_render_pixels:
        raise Invalid(f"{field}: a view of {w}x{h} = {w * h} pixels is over the limit of {st.max_render_pixels}",
                      field)


def _numbers(text: str, field: str, n: int) -> list[float]:
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise Invalid(f"{field}: {n} comma-separated numbers expected", field) from None
    if len(vals) != n:
        raise Invalid(f"{field}: {n} comma-separated numbers expected, got {len(vals)}", field)
    return vals


def view_key(sid: str, service: Service, req: ViewRequest) -> str:
    h = hashlib.sha256(f"{sid}|{service.info.name}|{service.info.version}|{req.key()}".encode()).hexdigest()
    return f'"{h[:40]}"'


def _render_bytes(service: Service, sid: str, req: ViewRequest, key: str) -> bytes:
    hit = service.views.get(key)
    if hit is not None:
        service.metrics.render_cache.labels("hit").inc()
        return hit
    service.metrics.render_cache.labels("miss").inc()
    scene = load_scene(service, sid)
    t0 = time.perf_counter()
    data = render_request(scene, req)
    service.metrics.render_seconds.observe(time.perf_counter() - t0)
    service.views.put(key, data, owner=sid)
    return data


@router.get("/scenes/{scene_id}/render", response_class=Response, summary="render one view",
            responses={200: {"content": {m: {} for m in _MEDIA.values()}, "description": "the encoded view"},
                       304: {"description": "not modified (If-None-Match)"}, **ERRORS})
async def render_one(
    request: Request, scene_id: str,
    camera: str | None = Query(None, max_length=256, description="an input camera of the scene's rig"),
    cam_to_ego: str | None = Query(None, max_length=1024,
                                   description="16 comma-separated numbers, row-major 4x4, OpenCV camera -> ego"),
    fx: float | None = Query(None, gt=0, allow_inf_nan=False), fy: float | None = Query(None, gt=0, allow_inf_nan=False),
    cx: float | None = Query(None, allow_inf_nan=False), cy: float | None = Query(None, allow_inf_nan=False),
    fov: float | None = Query(None, gt=0, lt=180, description="horizontal field of view, degrees"),
    x: float | None = Query(None, allow_inf_nan=False, description="CARLA location, metres (vehicle frame)"),
    y: float | None = Query(None, allow_inf_nan=False), z: float | None = Query(None, allow_inf_nan=False),
    pitch: float | None = Query(None, allow_inf_nan=False, description="CARLA rotation, degrees"),
    yaw: float | None = Query(None, allow_inf_nan=False), roll: float | None = Query(None, allow_inf_nan=False),
    width: int | None = Query(None, ge=1, le=32768), height: int | None = Query(None, ge=1, le=32768),
    output: Literal["rgb", "depth", "alpha"] = "rgb",
    format: Literal["png", "jpeg", "exr"] = "png",
    quality: int = Query(90, ge=1, le=100, description="JPEG quality"),
):
    s = service_of(request)
    await ready_record(s, scene_id)
    carla = {k: v for k, v in zip(_CARLA, (x, y, z, pitch, yaw, roll)) if v is not None}
    modes = [m for m, on in (("camera", camera is not None), ("cam_to_ego", cam_to_ego is not None),
                             ("carla", bool(carla))) if on]
    if len(modes) != 1:
        raise Invalid("give exactly one pose: camera=NAME, cam_to_ego=16 numbers (+ fx/fy/cx/cy or fov), or "
                      f"CARLA x,y,z,pitch,yaw,roll (+ fov); got {' and '.join(modes) or 'none'}",
                      {"carla": next(iter(carla), "x")}.get(modes[1], modes[1]) if len(modes) > 1 else "camera")
    try:
        if camera is not None:
            cam = camera_from_rig(await s.renders.run(_rig, s, scene_id), camera, width, height)
        elif cam_to_ego is not None:
            if width is None or height is None:
                raise Invalid("width and height are required with cam_to_ego", "width" if width is None else "height")
            cam = camera_from_opencv(_numbers(cam_to_ego, "cam_to_ego", 16), width, height, fx=fx, fy=fy, cx=cx,
                                     cy=cy, fov=fov)
        else:
            missing = [k for k in _CARLA if k not in carla] + [k for k, v in (("fov", fov), ("width", width),
                                                                               ("height", height)) if v is None]
            if missing:
                raise Invalid(f"a CARLA pose needs x, y, z, pitch, yaw, roll, fov, width, height; missing "
                              f"{', '.join(missing)}", missing[0])
            cam = camera_from_carla_pose(x, y, z, pitch, yaw, roll, fov, width, height)
        check_size(s, cam)
        req = ViewRequest(camera=cam, output=output, format=format, quality=quality)
    except ViewError as e:
        raise Invalid(str(e), e.field) from None
    key = view_key(scene_id, s, req)
    headers = {"ETag": key, "Cache-Control": "private, max-age=86400"}
    if key in [t.strip() for t in request.headers.get("if-none-match", "").split(",")]:
        return Response(status_code=304, headers=headers)
    await asyncio.to_thread(s.store.touch, scene_id)
    data = await s.renders.run(_render_bytes, s, scene_id, req, key)
    return Response(data, media_type=req.media_type, headers=headers)


def _rig(s: Service, sid: str):
    """The scene's rig (calibration) from the loaded scene."""
    return load_scene(s, sid).rig


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


@router.post("/scenes/{scene_id}/render", response_class=StreamingResponse, summary="render a batch of views "
             "(a zip of frames, streamed)",
             responses={200: {"content": {"application/zip": {}},
                              "description": "frame_00000.png ... and index.json (each frame's camera)"}, **ERRORS},
             openapi_extra={"requestBody": {"required": True, "content": {"application/json": {"schema": {
                 "type": "object", "description": "{\"cameras\": [...]} (OpenCV K + cam_to_ego, CARLA sensors, "
                 "input camera names) or a nerfstudio camera_path.json; optional output, format, quality"}}}}})
async def render_batch(request: Request, scene_id: str,
                       output: Literal["rgb", "depth", "alpha"] | None = None,
                       format: Literal["png", "jpeg", "exr"] | None = None,
                       quality: int | None = Query(None, ge=1, le=100)):
    s = service_of(request)
    await ready_record(s, scene_id)
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("application/json"):
        raise UnsupportedMedia(f"POST .../render takes application/json, not {ctype or 'no content type'!r}",
                               "content-type")
    try:
        doc = json.loads(await request.body())
    except (ValueError, UnicodeDecodeError) as e:
        raise Invalid(f"body: not valid JSON ({e})", "body") from None
    if not isinstance(doc, dict):
        raise Invalid("body: a JSON object expected ({\"cameras\": [...]} or a nerfstudio camera path)", "body")
    opts = {}
    for k, v, allowed in (("output", output, ("rgb", "depth", "alpha")), ("format", format, ("png", "jpeg", "exr"))):
        val = v if v is not None else doc.get(k, "rgb" if k == "output" else "png")
        if val not in allowed:
            raise Invalid(f"{k}: one of {', '.join(allowed)}", k)
        opts[k] = val
    q = quality if quality is not None else doc.get("quality", 90)
    if isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 100:
        raise Invalid("quality: an integer in 1..100", "quality")
    rig = await s.renders.run(_rig, s, scene_id)
    try:
        cams = cameras_from_batch(doc, rig=rig, max_frames=s.settings.max_batch_frames)
        for i, c in enumerate(cams):
            check_size(s, c, f"cameras[{i}]")
        reqs = [ViewRequest(camera=c, output=opts["output"], format=opts["format"], quality=q) for c in cams]
    except ViewError as e:
        raise Invalid(str(e), e.field) from None
    if s.renders.busy():
        await s.renders.run(lambda: None)     # raises Busy (503 + Retry-After) before anything is streamed
    await asyncio.to_thread(s.store.touch, scene_id)

    async def frames():
        sink = _Sink()
        index = []
        with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED) as zf:
            for i, req in enumerate(reqs):
                data = await s.renders.run(_render_bytes, s, scene_id, req, view_key(scene_id, s, req), force=True)
                name = f"frame_{i:05d}{req.extension}"
                zf.writestr(name, data)
                cam = req.camera
                index.append({"file": name, "width": cam.width, "height": cam.height,
                              "K": getattr(cam, "K", None).tolist() if getattr(cam, "K", None) is not None else None,
                              "cam_to_ego": cam.cam_to_ego.tolist()})
                yield sink.take()
            zf.writestr("index.json", json.dumps({"scene": scene_id, "output": opts["output"],
                                                  "format": opts["format"], "frames": index}, indent=1))
        yield sink.take()

    return StreamingResponse(frames(), media_type="application/zip",
                             headers={"Content-Disposition": f'attachment; filename="{scene_id}-frames.zip"'})
