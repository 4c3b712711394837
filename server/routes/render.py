"""Rendered views of a ready scene: GET one view from query parameters, POST a batch (a zip of frames, streamed).
What a render request means (camera, pose, size, output, format) is runtime.views.ViewRequest, made by the
Service (service.py); this module only reads it from HTTP."""

from __future__ import annotations

import json
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from xyzcyl.common.poses import MOVE_FIELDS
from xyzcyl.runtime.camera import render_limit

from ..deps import known_query, require_content_type, require_key, service_of
from ..errors import Invalid
from ..schemas import ERRORS, RENDER_BATCH, RenderQuery

_SIZE = (f"pixels; at most {render_limit()}, or the server's lower max_render_side / max_render_pixels "
         "settings")

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["render"], dependencies=[Depends(require_key), Depends(known_query)])

_MEDIA = {"png": "image/png", "jpeg": "image/jpeg", "exr": "image/x-exr"}
# the camera move's fields (common.poses.CameraMove, the one definition: names, units, bounds)
_MOVE = {f.name: f for f in MOVE_FIELDS}


def _move(name: str):
    """The query parameter of the move's field ``name``; its values are checked by CameraMove (422 naming it)."""
    return Query(None, description=f"{_MOVE[name].describe()}; with camera or cam_to_ego")


def render_query(
    camera: str | None = Query(None, max_length=256, description="an input camera of the scene's rig (its pose, K "
                               "and lens; with distortion: that lens instead; moved by forward, left, up, yaw)"),
    cam_to_ego: str | None = Query(None, max_length=1024,
                                   description="16 comma-separated numbers, row-major 4x4, OpenCV camera -> ego"),
    fx: float | None = Query(None, gt=0, allow_inf_nan=False), fy: float | None = Query(None, gt=0, allow_inf_nan=False),
    cx: float | None = Query(None, allow_inf_nan=False), cy: float | None = Query(None, allow_inf_nan=False),
    fov: float | None = Query(None, gt=0, lt=180, description="horizontal field of view, degrees"),
    distortion: str | None = Query(None, max_length=4096, description="the camera's lens as JSON, as rig.json writes "
                                   "it: an OpenCV coefficient list, or {\"model\": \"opencv\" | \"opencv_fisheye\" | "
                                   "\"ftheta\", ...} (docs/conventions.md, Lens models); with cam_to_ego, or with "
                                   "camera: that camera's pose and K through this lens"),
    x: float | None = Query(None, allow_inf_nan=False, description="CARLA location, metres (vehicle frame)"),
    y: float | None = Query(None, allow_inf_nan=False), z: float | None = Query(None, allow_inf_nan=False),
    pitch: float | None = Query(None, allow_inf_nan=False, description="CARLA rotation, degrees"),
    yaw: float | None = Query(None, allow_inf_nan=False,
                              description=f"with camera or cam_to_ego: the {_MOVE['yaw'].describe()}; otherwise the "
                                          "CARLA rotation's yaw, degrees (CARLA's axes: turning right)"),
    roll: float | None = Query(None, allow_inf_nan=False),
    forward: float | None = _move("forward"), left: float | None = _move("left"), up: float | None = _move("up"),
    width: int | None = Query(None, ge=1, description=_SIZE), height: int | None = Query(None, ge=1, description=_SIZE),
    output: Literal["rgb", "depth", "alpha"] = "rgb",
    format: Literal["png", "jpeg", "exr"] = "png",
    quality: int = Query(90, ge=1, le=100, description="JPEG quality"),
) -> RenderQuery:
    """GET .../render's query parameters (declared here for FastAPI and the OpenAPI document) as a RenderQuery."""
    return RenderQuery(**locals())      # every parameter, by its name


@router.get("/scenes/{scene_id}/render", response_class=Response, summary="render one view",
            responses={200: {"content": {m: {} for m in _MEDIA.values()}, "description": "the encoded view"},
                       304: {"description": "not modified (If-None-Match)"}, **ERRORS})
async def render_one(request: Request, scene_id: str, query: Annotated[RenderQuery, Depends(render_query)]):
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
                       output: Literal["rgb", "depth", "alpha"] | None = None,
                       format: Literal["png", "jpeg", "exr"] | None = None,
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


__all__ = ["render_query", "router"]
