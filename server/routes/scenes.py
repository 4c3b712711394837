"""/v1/scenes: post a rig or a recorded drive (multipart), list, inspect, delete; download the Gaussians and the
background. Each route parses its request and answers; the Service (service.py) does the work."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse
from xyzcyl.common.wire import (
    DETAIL_STRIDE_MAX,
    DETAIL_STRIDE_MIN,
    ActorList,
    SceneInfo,
    SceneList,
    detail_stride_error,
    keyframe_error,
)
from xyzcyl.runtime.drive import DEFAULT_MAX_GAP_S, DEFAULT_SPACING_M
from xyzcyl.runtime.exports import FORMATS as EXPORT_FORMATS
from xyzcyl.runtime.exports import MEDIA_TYPES
from xyzcyl.runtime.inference import DEFAULT_DETAIL

from ..deps import known_query, require_content_type, require_key, service_of
from ..errors import Invalid, scene_failure
from ..schemas import ERRORS, SCENE_UPLOAD, scene_info, scene_list
from ..store import name_error

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["scenes"], dependencies=[Depends(require_key), Depends(known_query)])

_CHUNK = 1 << 20
_IMMUTABLE = "private, max-age=86400"


def _detail_stride(request: Request, detail: bool, detail_stride: int | None) -> int | None:
    """The detail layer's stride for the job (None: off), from POST /v1/scenes' query (types and range checked by
    FastAPI)."""
    for name in ("detail", "detail_stride"):
        if len(request.query_params.getlist(name)) > 1:
            raise Invalid(f"{name}: given more than once", name)
    why = detail_stride_error(detail_stride, detail)
    if why is not None:
        raise Invalid(f"detail_stride: {why}", "detail_stride")
    if not detail:
        return None
    return DEFAULT_DETAIL.stride if detail_stride is None else detail_stride


@router.post("/scenes", status_code=202, response_model=SceneInfo, summary="reconstruct a rig or a recorded drive",
             responses={201: {"model": SceneInfo, "description": "ready (with ?wait)"}, **ERRORS},
             openapi_extra=SCENE_UPLOAD)
async def create_scene(request: Request,
                       wait: float | None = Query(None, ge=0, le=3600,
                                                  description="hold up to this many seconds for the result"),
                       detail_stride: int | None = Query(None, ge=DETAIL_STRIDE_MIN, le=DETAIL_STRIDE_MAX,
                                                         description="detail layer: input pixels per detail "
                                                                     "Gaussian along each axis (default "
                                                                     f"{DEFAULT_DETAIL.stride})"),
                       detail: bool = Query(True, description="false: no detail layer (the model's Gaussians "
                                                              "only)"),
                       name: str | None = Query(None, max_length=200,
                                                description="the scene's name, e.g. a simulator's scene id (AlpaSim's "
                                                            "clipgt-...): the gRPC SensorsimService lists and "
                                                            "resolves it (docs/simulators.md)"),
                       keyframe_spacing: float | None = Query(None, description="a drive: a keyframe each time the "
                                                              f"ego moved this many metres (default "
                                                              f"{DEFAULT_SPACING_M:g})"),
                       keyframe_gap: float | None = Query(None, description="a drive: a keyframe at least every this "
                                                          f"many seconds (default {DEFAULT_MAX_GAP_S:g})"),
                       stationary_actors: bool = Query(False, description="a drive: its tracks marked stationary "
                                                       "(parked cars) become actors too, which a view can hide or "
                                                       "move (default: they stay in the static scene)")):
    stride = _detail_stride(request, detail, detail_stride)
    if name is not None and (why := name_error(name)):
        raise Invalid(f"name: {why}", "name")
    knobs = {"keyframe_spacing": keyframe_spacing, "keyframe_gap": keyframe_gap}
    for k, v in knobs.items():
        if len(request.query_params.getlist(k)) > 1:
            raise Invalid(f"{k}: given more than once", k)
        if (why := keyframe_error(v)) is not None:
            raise Invalid(f"{k}: {why}", k)
    require_content_type(request, "multipart/form-data", "POST /v1/scenes")
    rec = await service_of(request).create_scene(request.form, stride, wait, name=name, keyframes=knobs,
                                                 stationary_actors=stationary_actors)
    headers = {"Location": f"/v1/scenes/{rec.id}"}
    if rec.state == "failed" and wait:
        err = rec.error
        raise scene_failure(rec.id, err.code if err else "failed", err.message if err else "failed", headers)
    return JSONResponse(scene_info(rec), status_code=201 if rec.state == "ready" and wait else 202, headers=headers)


@router.get("/scenes", response_model=SceneList, summary="list scenes (newest first)", responses=ERRORS)
async def list_scenes(request: Request, offset: int = Query(0, ge=0, le=10**9),
                      limit: int = Query(50, ge=1, le=1000)):
    page, total = await service_of(request).list_scenes(offset, limit)
    return scene_list(page, total, offset, limit)


@router.get("/scenes/{scene_id}", response_model=SceneInfo, summary="a scene's state and metadata",
            responses=ERRORS)
async def get_scene(request: Request, scene_id: str):
    return scene_info(await service_of(request).record(scene_id))


@router.delete("/scenes/{scene_id}", status_code=204, summary="delete a scene", responses=ERRORS,
               response_class=Response)
async def delete_scene(request: Request, scene_id: str):
    await service_of(request).delete_scene(scene_id)
    return Response(status_code=204)


def _stream(f, chunk: int = _CHUNK):
    try:
        while data := f.read(chunk):
            yield data
    finally:
        f.close()


@router.get("/scenes/{scene_id}/gaussians", summary="the Gaussians: 3DGS PLY (default) or .splat",
            response_class=Response, responses={200: {"content": {"application/x-ply": {}, "application/x-splat": {}},
                                                      "description": "binary little-endian PLY or .splat"},
                                                **ERRORS})
async def gaussians(request: Request, scene_id: str,
                    format: Literal["ply", "splat"] | None = Query(None, description="default: from Accept, else ply")):
    s = service_of(request)
    await s.ready_record(scene_id)
    fmt = format or ("splat" if "splat" in request.headers.get("accept", "") else "ply")
    etag = f'"{scene_id}-{fmt}"'
    headers = {"ETag": etag, "Cache-Control": _IMMUTABLE,
               "Content-Disposition": f'attachment; filename="{scene_id}.{fmt}"'}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    if fmt == "splat":
        return Response(await s.splat(scene_id), media_type="application/x-splat", headers=headers)
    f = await s.scene_file(scene_id, "scene.ply")
    headers["Content-Length"] = str(f.seek(0, 2))
    f.seek(0)
    return StreamingResponse(_stream(f), media_type="application/x-ply", headers=headers)


@router.get("/scenes/{scene_id}/export", summary="the scene in another tool's format: an AlpaSim scene artifact "
            "(USDZ), glTF / GLB (KHR_gaussian_splatting), SPZ, PLY or .splat", response_class=Response,
            responses={200: {"content": {MEDIA_TYPES[f]: {} for f in EXPORT_FORMATS},
                             "description": "usdz: an AlpaSim scene artifact (the trajectory, cameras, tracks, a "
                                            "ground mesh and the Gaussians as a NuRec volume: docs/simulators.md); "
                                            "gltf/glb: glTF 2.0 with KHR_gaussian_splatting, +Y up, a drive's actors "
                                            "as nodes at ?time; spz/ply/splat: one cloud, a drive's actors at ?time "
                                            "baked in (docs/api.md)"},
                       **ERRORS})
async def export(request: Request, scene_id: str,
                 format: Literal[EXPORT_FORMATS] = Query(..., description="usdz, gltf, glb, spz, ply or splat"),
                 time: float | None = Query(None, allow_inf_nan=False, description=(
                     "a drive: seconds on the rigs' clock, when its actors are placed (default its first frame; "
                     "not for usdz)"))):
    from xyzcyl.runtime.exports import FORMAT_VERSION, ExportError, check_request
    from xyzcyl.runtime.usdz import FORMAT_VERSION as USDZ_VERSION

    for name in ("format", "time"):
        if len(request.query_params.getlist(name)) > 1:
            raise Invalid(f"{name}: given more than once", name)
    try:
        check_request(format, time, None)
    except ExportError as e:
        raise Invalid(f"{e.field}: {e.message}", e.field) from None
    version = USDZ_VERSION if format == "usdz" else FORMAT_VERSION
    etag = f'"{scene_id}-{format}-{version}"' if time is None else f'"{scene_id}-{format}-{version}-t{time!r}"'
    headers = {"ETag": etag, "Cache-Control": _IMMUTABLE,
               "Content-Disposition": f'attachment; filename="{scene_id}.{format}"'}
    s = service_of(request)
    if request.headers.get("if-none-match") == etag:
        await s.ready_record(scene_id)
        return Response(status_code=304, headers=headers)
    f, size = await s.export(scene_id, format, time)
    headers["Content-Length"] = str(size)
    return StreamingResponse(_stream(f), media_type=MEDIA_TYPES[format], headers=headers)


@router.get("/scenes/{scene_id}/actors", response_model=ActorList, summary="a drive scene's actors (the moving "
            "objects a view's actors= edits)", responses=ERRORS)
async def actors(request: Request, scene_id: str,
                 time: float | None = Query(None, allow_inf_nan=False, description=(
                     "seconds on the rigs' clock: each actor's pose then"))):
    return await service_of(request).actors(scene_id, time)


@router.get("/scenes/{scene_id}/background", summary="the background panorama on the scene's cylinder",
            response_class=Response, responses={200: {"content": {"image/png": {}, "image/x-exr": {}}}, **ERRORS})
async def background(request: Request, scene_id: str,
                     format: Literal["png", "exr"] = Query("png", description="png: 8-bit preview; exr: float32 "
                                                                              "linear RGB")):
    f = await service_of(request).background(scene_id, format)
    return StreamingResponse(_stream(f), media_type="image/png" if format == "png" else "image/x-exr",
                             headers={"ETag": f'"{scene_id}-bg-{format}"', "Cache-Control": _IMMUTABLE})


__all__ = ["router"]
