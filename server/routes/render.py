"""Rendered views of a ready scene: GET one view from query parameters, POST a batch (a zip of frames, streamed).
The query is common.wire.ViewQuery (the one render view of every front end, FastAPI's query model here); the
Service (service.py) resolves it against the scene (runtime.views.request); this module only reads it from HTTP."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from xyzcyl.common.wire import MEDIA_TYPES, Format, Output, ViewQuery

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


__all__ = ["router"]
