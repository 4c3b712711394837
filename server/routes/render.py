"""Rendered views of a ready scene: GET one view from query parameters, POST a batch (a zip of frames, streamed);
GET one simulated LiDAR sweep (runtime.lidarsim, docs/api.md "LiDAR").
The query is common.wire.ViewQuery (the one render view of every front end, FastAPI's query model here); the
Service (service.py) resolves it against the scene (runtime.views.request); this module only reads it from HTTP."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from xyzcyl.common.wire import ACTORS_TEXT_MAX, MEDIA_TYPES, Format, Output, ViewQuery

from ..deps import known_query, require_content_type, require_key, service_of
from ..errors import Invalid
from ..schemas import ERRORS, RENDER_BATCH

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["render"], dependencies=[Depends(require_key), Depends(known_query)])


@router.get("/scenes/{scene_id}/render", response_class=Response, summary="render one view",
            responses={200: {"content": {m: {} for m in MEDIA_TYPES.values()}, "description": "the encoded view"},
                       304: {"description": "not modified (If-None-Match)"}, **ERRORS})
async def render_one(request: Request, scene_id: str, query: Annotated[ViewQuery, Query()]):
    s = service_of(request)
    req, key = await s.view_request(scene_id, query)
    headers = {"ETag": key, "Cache-Control": "private, max-age=86400"}
    if key in [t.strip() for t in request.headers.get("if-none-match", "").split(",")]:
        return Response(status_code=304, headers=headers)
    return Response(await s.render(scene_id, req, key), media_type=req.media_type, headers=headers)


@router.post("/scenes/{scene_id}/render", response_class=StreamingResponse, summary="render a batch of views "
             "(a zip of frames, streamed)",
             responses={200: {"content": {"application/zip": {}},
                              "description": "frame_00000.png ... and index.json (each frame's camera)"}, **ERRORS},
             openapi_extra=RENDER_BATCH)
async def render_batch(request: Request, scene_id: str,
                       output: Output | None = None, format: Format | None = None,
                       quality: int | None = Query(None, ge=1, le=100)):
    s = service_of(request)
    await s.ready_record(scene_id)
    require_content_type(request, "application/json", "POST .../render")
    try:
        doc = json.loads(await request.body())
    except (ValueError, UnicodeDecodeError) as e:
        raise Invalid(f"body: not valid JSON ({e})", "body") from None
    if not isinstance(doc, dict):
        raise Invalid("body: a JSON object expected ({\"cameras\": [...]} or a nerfstudio camera path)", "body")
    frames = await s.render_batch(scene_id, doc, output, format, quality)
    return StreamingResponse(frames, media_type="application/zip",
                             headers={"Content-Disposition": f'attachment; filename="{scene_id}-frames.zip"'})


LIDAR_MEDIA = {"ply": "application/octet-stream", "npy": "application/octet-stream"}


@router.get("/scenes/{scene_id}/lidar", response_class=Response, summary="simulate one LiDAR sweep",
            responses={200: {"content": {"application/octet-stream": {}},
                             "description": "the sweep's points: a binary PLY (x, y, z, intensity, ring) or an .npy "
                                            "float32 [N, 4] (x, y, z, intensity); end-of-spin LiDAR frame, metres"},
                       **ERRORS})
async def render_lidar(request: Request, scene_id: str,
                       pose: str = Query(..., max_length=1024, description=(
                           "the LiDAR's pose at the spin's start: lidar -> the scene's frame, 16 numbers row-major "
                           "(LiDAR axes x forward, y left, z up)")),
                       end_pose: str | None = Query(None, max_length=1024, description=(
                           "its pose at the spin's end (default: pose; the points are in this frame)")),
                       model: str = Query("pandar128", max_length=32, description="pandar128, at128 or pandar64 "
                                                                                   "(nominal beam layouts)"),
                       time: float | None = Query(None, description="seconds on the rigs' clock: where a drive's "
                                                                    "moving objects are drawn"),
                       max_range: float | None = Query(None, description="metres (default: the model's)"),
                       azimuth_step: float | None = Query(None, description="degrees (default: the model's)"),
                       format: str = Query("ply", pattern="^(ply|npy)$", description="ply or npy"),
                       actors: str | None = Query(None, max_length=ACTORS_TEXT_MAX, description=(
                           "a drive scene's actors edited for this sweep: a JSON list of edits, as GET render's "
                           "actors (docs/api.md \"Actors\")"))):
    from xyzcyl.runtime.lidarsim import sweep_bytes

    s = service_of(request)
    req = await s.lidar_request(scene_id, model, pose, end_pose, time, max_range, azimuth_step, format, actors)
    sweep = await s.render_lidar(scene_id, req)
    headers = {"X-Lidar-Points": str(len(sweep)), "X-Lidar-Rays": str(sweep.stats["rays"]),
               "Content-Disposition": f'attachment; filename="{scene_id}-lidar.{format}"'}
    data = await asyncio.to_thread(sweep_bytes, sweep, format)
    return Response(data, media_type=LIDAR_MEDIA[format], headers=headers)


__all__ = ["router"]
