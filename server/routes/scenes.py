"""/v1/scenes: post a rig (multipart), list, inspect, delete; download the Gaussians and the background."""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import shutil
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, Field
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from xyzcyl.runtime.inference import DEFAULT_DETAIL
from xyzcyl.runtime.rig import Rig, RigError, image_size, save_rig, verify_image

from ..app import Service, service_of
from ..errors import ApiError, Busy, Conflict, Invalid, NotFound, StorageFull, UnsupportedMedia
from ..jobs import Job
from ..params import known_query
from ..security import require_key
from ..store import StoreFull, new_scene_id

# require_key first (401 before anything else), then known_query (422 for a query parameter the route lacks)
router = APIRouter(prefix="/v1", tags=["scenes"], dependencies=[Depends(require_key), Depends(known_query)])

RIG_PART_BYTES = 1 << 20          # a rig.json of 16 cameras is ~10 kB; 1 MiB is plenty
_MAGIC = ((b"\x89PNG\r\n\x1a\n", ".png"), (b"\xff\xd8\xff", ".jpg"), (b"\x76\x2f\x31\x01", ".exr"),
          (b"II*\x00", ".tif"), (b"MM\x00*", ".tif"))
_PART_TYPES = ("image/png", "image/jpeg", "image/x-exr", "image/exr", "image/tiff", "application/octet-stream")
_CHUNK = 1 << 20


# ----------------------------------------------------------------------------------------------- schemas

class ErrorDetail(BaseModel):
    code: str
    message: str
    field: str | None = None


class ErrorBody(BaseModel):
    error: ErrorDetail


class CameraInfo(BaseModel):
    name: str
    width: int
    height: int
    model: str


class DetailInfo(BaseModel):
    enabled: bool = Field(description="whether the detail layer was asked for (POST ?detail=)")
    stride: int | None = Field(None, description="input pixels per detail Gaussian along each axis (null when off)")


class SceneInfo(BaseModel):
    id: str = Field(examples=["q3R1x9Z2bC7dE5fG8hJ0kA"])
    state: Literal["queued", "running", "ready", "failed"]
    created: str
    updated: str
    error: ErrorDetail | None = None
    cameras: list[CameraInfo]
    detail: DetailInfo | None = None
    model: dict[str, Any] | None = None
    counts: dict[str, int] | None = None
    gaussians: int | None = None
    background: bool | None = None
    bbox: dict[str, list[float]] | None = None
    timings: dict[str, float] | None = None
    bytes: int | None = None
    links: dict[str, str]


class SceneList(BaseModel):
    scenes: list[SceneInfo]
    total: int
    offset: int
    limit: int
    next: str | None = None


ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 413, 415, 422, 503, 507)}


def _iso(ts: float | None) -> str:
    return dt.datetime.fromtimestamp(ts or 0.0, dt.UTC).replace(microsecond=0).isoformat()


def scene_info(rec: dict[str, Any]) -> dict[str, Any]:
    sid = rec["id"]
    base = f"/v1/scenes/{sid}"
    links = {"self": base}
    if rec["state"] == "ready":
        links |= {"gaussians": f"{base}/gaussians", "render": f"{base}/render"}
        if rec.get("background"):
            links["background"] = f"{base}/background"
    err = rec.get("error")
    return {"id": sid, "state": rec["state"], "created": _iso(rec.get("created_ts")),
            "updated": _iso(rec.get("updated_ts")), "error": err, "cameras": rec.get("cameras", []),
            "detail": rec.get("detail"), "model": rec.get("model"), "counts": rec.get("counts"),
            "gaussians": rec.get("gaussians"), "background": rec.get("background"), "bbox": rec.get("bbox"),
            "timings": rec.get("timings"), "bytes": rec.get("bytes"), "links": links}


async def get_record(service: Service, sid: str) -> dict[str, Any]:
    # None for an unknown or malformed id (never a path); off the loop: an S3 store reads over the network
    rec = await asyncio.to_thread(service.store.get, sid)
    if rec is None:
        raise NotFound(f"no scene {sid!r}", "id")
    return rec


async def ready_record(service: Service, sid: str) -> dict[str, Any]:
    rec = await get_record(service, sid)
    if rec["state"] == "failed":
        e = rec.get("error") or {}
        raise Conflict(f"scene {sid} failed: {e.get('message', 'unknown error')}", "id", code="scene_failed")
    if rec["state"] != "ready":
        raise Conflict(f"scene {sid} is {rec['state']}; poll GET /v1/scenes/{sid} until it is ready", "id",
                       headers={"Retry-After": "1"})
    return rec


# ----------------------------------------------------------------------------------------------- upload

def _sniff(head: bytes) -> str | None:
    for magic, ext in _MAGIC:
        if head.startswith(magic):
            return ext
    return None


def _save_part(part: UploadFile, field: str, dest_stem: Path) -> Path:
    ctype = (part.content_type or "application/octet-stream").split(";")[0].strip().lower()
    if ctype not in _PART_TYPES:
        raise UnsupportedMedia(f"part {field!r}: media type {ctype!r} is not one of {', '.join(_PART_TYPES)}",
                               field)
    part.file.seek(0)
    head = part.file.read(16)
    ext = _sniff(head)
    if ext is None:
        raise UnsupportedMedia(f"part {field!r}: not a PNG, JPEG, EXR or TIFF file", field)
    path = dest_stem.with_suffix(ext)
    part.file.seek(0)
    with open(path, "wb") as f:
        shutil.copyfileobj(part.file, f, _CHUNK)
    return path


def _check_image(path: Path, field: str, cam, max_pixels: int, what: str) -> None:
    """The saved part's header (size, pixel limit: nothing decoded yet, so a decompression bomb is refused here),
    then one full decode that refuses a file cut short or corrupt (a cut JPEG otherwise "decodes" with the rest
    grey). Messages name the part once and say ``what`` for the file (never the store's path)."""
    try:
        w, h = image_size(path, f"part {field!r}", label=what)
    except RigError as e:
        raise Invalid(str(e), field) from None
    if w * h > max_pixels:
        raise Invalid(f"part {field!r}: {what} is {w}x{h} = {w * h} pixels, over the limit of {max_pixels}", field)
    if (w, h) != (cam.width, cam.height):
        raise Invalid(f"part {field!r}: {what} is {w}x{h}, but the rig declares camera {cam.name!r} as "
                      f"{cam.width}x{cam.height}", field)
    try:
        verify_image(path, f"part {field!r}", label=what)
    except RigError as e:
        raise Invalid(str(e), field) from None


def _ingest_ego_mask(part, cam, dest_stem: Path, max_pixels: int) -> str:
    """An 'ego_mask:<camera>' part (PNG 8/16-bit, any channels, or JPEG; non-zero = the ego's own body) saved as
    ``dest_stem`` + its type's suffix and decoded once in full (_check_image: the decoder the worker's
    runtime.detail.read_ego_mask reads it with). Returns the saved file's name for the rig's camera ``ego_mask``."""
    field = f"ego_mask:{cam.name}"
    if not isinstance(part, UploadFile):
        raise Invalid(f"part {field!r} must be a file part (a PNG or JPEG mask)", field)
    path = _save_part(part, field, dest_stem)
    if path.suffix not in (".png", ".jpg"):
        raise UnsupportedMedia(f"part {field!r}: an ego mask must be a PNG or JPEG, not {path.suffix[1:].upper()}",
                               field)
    _check_image(path, field, cam, max_pixels, "the ego mask")      # size, then a full decode (cut or corrupt)
    return path.name


def _ingest_lidar(form, rig: Rig, work: Path) -> dict | None:
    """The optional 'lidar' part (a sweep of the same timestamp: .npy [N, >=3] or raw float32 .bin, in the frame
    of the rig's lidar block's lidar_to_ego, else ego) written to ``work`` and read once to validate it. Returns
    the rig's lidar block for the saved file, or without a file when there is no part (the client's file name
    means nothing here), or None when the rig has neither."""
    from xyzcyl.runtime.lidar import LidarError, load_lidar

    block = rig.extra.get("lidar")
    if block is not None and not isinstance(block, dict):
        raise Invalid(f"rig: lidar must be an object (got {type(block).__name__})", "rig.lidar")
    block = {k: v for k, v in (block or {}).items() if k != "file"}
    part = form.get("lidar")
    if part is None:
        return block or None
    if not isinstance(part, UploadFile):
        raise Invalid("part 'lidar' must be a file part (.npy or float32 .bin)", "lidar")
    ctype = (part.content_type or "application/octet-stream").split(";")[0].strip().lower()
    if ctype not in ("application/octet-stream", "application/x-npy"):
        raise UnsupportedMedia(f"part 'lidar': media type {ctype!r} is not application/octet-stream or "
                               "application/x-npy", "lidar")
    part.file.seek(0)
    head = part.file.read(6)
    client_name = (part.filename or "").lower()
    name = ("lidar.npy" if head == b"\x93NUMPY" else "lidar.pcd.bin" if client_name.endswith(".pcd.bin")
            else "lidar.bin")
    part.file.seek(0)
    with open(work / name, "wb") as f:
        shutil.copyfileobj(part.file, f, _CHUNK)
    block["file"] = name
    try:
        load_lidar(Rig(cameras=rig.cameras, root=work, extra={"lidar": block}))
    except LidarError as e:
        raise Invalid(f"part 'lidar': {e}", "lidar") from None
    return block


def _ingest(form, service: Service, work: Path) -> Rig:
    """Validate the multipart form and write rig.json + the parts into ``work`` (file names are ours, never
    the request's). Returns the rig as written."""
    st = service.settings
    rig_part = form.get("rig")
    if rig_part is None:
        raise Invalid("the 'rig' part (rig.json) is missing", "rig")
    if isinstance(rig_part, UploadFile):
        rig_part.file.seek(0)
        raw = rig_part.file.read(RIG_PART_BYTES + 1)
    else:
        raw = rig_part.encode()
    if len(raw) > RIG_PART_BYTES:
        raise Invalid(f"the 'rig' part is over {RIG_PART_BYTES} bytes", "rig")
    try:
        doc = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        raise Invalid(f"rig: not valid JSON ({e})", "rig") from None
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list) and len(doc["cameras"]) > st.max_cameras:
        raise Invalid(f"rig: {len(doc['cameras'])} cameras, more than the limit of {st.max_cameras}", "rig.cameras")
    try:
        rig = Rig.from_dict(doc)
    except RigError as e:
        raise Invalid(str(e), "rig") from None          # its message names the rig or the camera, and the field
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise Invalid(f"rig: {type(e).__name__}: {e}", "rig") from None
    limit = min(st.max_cameras, int((service.info.meta.get("input") or {}).get("max_cameras", st.max_cameras)))
    if len(rig.cameras) > limit:
        raise Invalid(f"rig: {len(rig.cameras)} cameras, more than the limit of {limit}", "rig.cameras")
    names = set(rig.names)
    seen: set[str] = set()
    for key, _ in form.multi_items():
        if key in seen:
            raise Invalid(f"part {key!r} appears more than once", key)
        seen.add(key)
        prefix, _, cam_name = key.partition(":")
        if key not in ("rig", "lidar") and key not in names and not (prefix in ("depth", "ego_mask")
                                                                     and cam_name in names):
            raise Invalid(f"part {key!r} names no camera of the rig (cameras: {', '.join(rig.names)}; depth parts "
                          "are named 'depth:<camera>', ego masks 'ego_mask:<camera>', a LiDAR sweep 'lidar')", key)
    cams = []
    for i, cam in enumerate(rig.cameras):
        part = form.get(cam.name)
        if part is None:
            raise Invalid(f"no image part for camera {cam.name!r} (one part per camera, named by the camera)",
                          cam.name)
        if not isinstance(part, UploadFile):
            raise Invalid(f"part {cam.name!r} must be a file part (an image)", cam.name)
        img = _save_part(part, cam.name, work / f"image_{i:02d}")
        _check_image(img, cam.name, cam, st.max_image_pixels, "the image")
        depth = None
        dpart = form.get(f"depth:{cam.name}")
        if dpart is not None:
            field = f"depth:{cam.name}"
            if not isinstance(dpart, UploadFile):
                raise Invalid(f"part {field!r} must be a file part (16-bit PNG mm or float EXR m)", field)
            if cam.model != "pinhole":
                raise Invalid(f"part {field!r}: depth is supported for pinhole cameras only", field)
            dpath = _save_part(dpart, field, work / f"depth_{i:02d}")
            if dpath.suffix == ".jpg":
                raise UnsupportedMedia(f"part {field!r}: depth must be a 16-bit PNG (millimetres) or a float EXR "
                                       "(metres), not JPEG", field)
            _check_image(dpath, field, cam, st.max_image_pixels, "the depth map")
            depth = dpath.name
        # like depth, a rig's own ego_mask file name is not used (the file is not here): only an uploaded part
        extra = {k: v for k, v in cam.extra.items() if k != "ego_mask"}
        mpart = form.get(f"ego_mask:{cam.name}")
        if mpart is not None:
            extra["ego_mask"] = _ingest_ego_mask(mpart, cam, work / f"ego_mask_{i:02d}", st.max_image_pixels)
        cams.append(cam.replace(image=img.name, depth=depth, extra=extra))
    extra = {k: v for k, v in rig.extra.items() if k != "lidar"}
    lidar = _ingest_lidar(form, rig, work)
    if lidar is not None:
        extra["lidar"] = lidar
    out = Rig(cameras=tuple(cams), extra=extra)
    save_rig(out, work / "rig.json")
    return out


def _detail_stride(request: Request, detail: bool, detail_stride: int | None) -> int | None:
    """The detail layer's stride for the job (None: off), from POST /v1/scenes' query (types and range checked by
    FastAPI)."""
    for name in ("detail", "detail_stride"):
        if len(request.query_params.getlist(name)) > 1:
            raise Invalid(f"{name}: given more than once", name)
    if not detail:
        if detail_stride is not None:
            raise Invalid("detail_stride: cannot be combined with detail=false (the detail layer is off)",
                          "detail_stride")
        return None
    return DEFAULT_DETAIL.stride if detail_stride is None else detail_stride


@router.post("/scenes", status_code=202, response_model=SceneInfo, summary="reconstruct a rig",
             responses={201: {"model": SceneInfo, "description": "ready (with ?wait)"}, **ERRORS},
             openapi_extra={"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
                 "type": "object", "required": ["rig"],
                 "properties": {"rig": {"type": "string", "format": "binary",
                                        "description": "rig.json (cameras, calibrations)"}},
                 "additionalProperties": {"type": "string", "format": "binary",
                                          "description": "one image part per camera, named by the camera; "
                                                         "optional 'depth:<camera>' and 'ego_mask:<camera>' parts "
                                                         "and an optional 'lidar' part (a LiDAR sweep: .npy or "
                                                         "float32 .bin)"}}}}}})
async def create_scene(request: Request,
                       wait: float | None = Query(None, ge=0, le=3600,
                                                  description="hold up to this many seconds for the result"),
                       detail_stride: int | None = Query(None, ge=1, le=16,
                                                         description="detail layer: input pixels per detail "
                                                                     "Gaussian along each axis (default "
                                                                     f"{DEFAULT_DETAIL.stride})"),
                       detail: bool = Query(True, description="false: no detail layer (the model's Gaussians "
                                                              "only)")):
    s = service_of(request)
    stride = _detail_stride(request, detail, detail_stride)
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise UnsupportedMedia(f"POST /v1/scenes takes multipart/form-data, not {ctype or 'no content type'!r}",
                               "content-type")
    if not s.ready:
        raise Busy("the model is still loading; retry shortly", s.settings.retry_after_s)
    if s.reconstructions.full():
        s.metrics.rejected.labels("reconstruct").inc()
        raise Busy(f"{s.reconstructions.pending} reconstructions are running or queued; retry later",
                   s.settings.retry_after_s)
    n = s.settings.max_cameras
    work = await asyncio.to_thread(s.store.work_dir)
    form = None
    job = None
    try:
        try:
            form = await request.form(max_files=3 * n + 8, max_fields=3 * n + 8, max_part_size=RIG_PART_BYTES)
        except StarletteHTTPException as e:
            raise Invalid(f"the multipart body cannot be parsed: {e.detail}", "body") from None
        rig = await asyncio.to_thread(_ingest, form, s, work)
        sid = new_scene_id()
        cameras = [{"name": c.name, "width": c.width, "height": c.height, "model": c.model} for c in rig.cameras]
        try:
            await asyncio.to_thread(s.store.create, sid, {"cameras": cameras, "detail": {
                "enabled": stride is not None, "stride": stride}})
        except StoreFull as e:
            raise StorageFull(str(e)) from None
        job = Job(sid=sid, work=work, detail_stride=stride)
        try:
            s.reconstructions.submit(job)
        except Busy:
            s.store.delete(sid)
            raise
    except OSError as e:
        await asyncio.to_thread(shutil.rmtree, work, True)
        import errno

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
            await asyncio.wait_for(asyncio.shield(job.done.wait()), min(wait, s.settings.wait_max_s))
        except TimeoutError:
            pass
    rec = await asyncio.to_thread(s.store.get, sid) or {"id": sid, "state": "failed", "cameras": cameras,
                                "error": {"code": "deleted", "message": "the scene was deleted"}}
    info = scene_info(rec)
    headers = {"Location": f"/v1/scenes/{sid}"}
    if rec["state"] == "ready" and wait:
        return JSONResponse(info, status_code=201, headers=headers)
    if rec["state"] == "failed" and wait:
        err = rec.get("error") or {}
        code = err.get("code", "failed")
        status = {"invalid_input": 422, "storage_full": 507}.get(code, 500)
        raise ApiError(f"scene {sid}: {err.get('message', 'failed')}", "rig" if status == 422 else None,
                       headers, code=code, status=status)
    return JSONResponse(info, status_code=202, headers=headers)


# ----------------------------------------------------------------------------------------------- reading

@router.get("/scenes", response_model=SceneList, summary="list scenes (newest first)", responses=ERRORS)
async def list_scenes(request: Request, offset: int = Query(0, ge=0, le=10**9),
                      limit: int = Query(50, ge=1, le=1000)):
    s = service_of(request)
    page, total = await asyncio.to_thread(s.store.list, offset, limit)
    nxt = f"/v1/scenes?offset={offset + limit}&limit={limit}" if offset + limit < total else None
    return {"scenes": [scene_info(r) for r in page], "total": total, "offset": offset, "limit": limit, "next": nxt}


@router.get("/scenes/{scene_id}", response_model=SceneInfo, summary="a scene's state and metadata",
            responses=ERRORS)
async def get_scene(request: Request, scene_id: str):
    return scene_info(await get_record(service_of(request), scene_id))


@router.delete("/scenes/{scene_id}", status_code=204, summary="delete a scene", responses=ERRORS,
               response_class=Response)
async def delete_scene(request: Request, scene_id: str):
    s = service_of(request)
    await get_record(s, scene_id)
    await asyncio.to_thread(s.store.delete, scene_id)
    return Response(status_code=204)


def _open_scene_file(s: Service, sid: str, name: str):
    try:
        return open(s.store.scene_dir(sid) / name, "rb")
    except (KeyError, FileNotFoundError):
        raise NotFound(f"scene {sid} was deleted", "id") from None


def _stream(f, chunk: int = _CHUNK):
    try:
        while data := f.read(chunk):
            yield data
    finally:
        f.close()


_IMMUTABLE = "private, max-age=86400"


@router.get("/scenes/{scene_id}/gaussians", summary="the Gaussians: 3DGS PLY (default) or .splat",
            response_class=Response, responses={200: {"content": {"application/x-ply": {}, "application/x-splat": {}},
                                                      "description": "binary little-endian PLY or .splat"},
                                                **ERRORS})
async def gaussians(request: Request, scene_id: str,
                    format: Literal["ply", "splat"] | None = Query(None, description="default: from Accept, else ply")):
    s = service_of(request)
    await ready_record(s, scene_id)
    fmt = format or ("splat" if "splat" in request.headers.get("accept", "") else "ply")
    etag = f'"{scene_id}-{fmt}"'
    headers = {"ETag": etag, "Cache-Control": _IMMUTABLE,
               "Content-Disposition": f'attachment; filename="{scene_id}.{fmt}"'}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    await asyncio.to_thread(s.store.touch, scene_id)
    if fmt == "ply":
        f = await asyncio.to_thread(_open_scene_file, s, scene_id, "scene.ply")
        headers["Content-Length"] = str(f.seek(0, 2))
        f.seek(0)
        return StreamingResponse(_stream(f), media_type="application/x-ply", headers=headers)
    scene = await s.renders.run(load_scene, s, scene_id)
    data = await s.renders.run(scene.gaussians.splat_bytes)
    return Response(data, media_type="application/x-splat", headers=headers)


@router.get("/scenes/{scene_id}/background", summary="the background panorama on the scene's cylinder",
            response_class=Response, responses={200: {"content": {"image/png": {}, "image/x-exr": {}}}, **ERRORS})
async def background(request: Request, scene_id: str,
                     format: Literal["png", "exr"] = Query("png", description="png: 8-bit preview; exr: float32 "
                                                                              "linear RGB")):
    s = service_of(request)
    rec = await ready_record(s, scene_id)
    if not rec.get("background"):
        raise NotFound(f"scene {scene_id} has no background (the model has no background graph)", "id",
                       code="no_background")
    name, media = ("background.png", "image/png") if format == "png" else ("background.exr", "image/x-exr")
    await asyncio.to_thread(s.store.touch, scene_id)
    f = await asyncio.to_thread(_open_scene_file, s, scene_id, name)
    headers = {"ETag": f'"{scene_id}-bg-{format}"', "Cache-Control": _IMMUTABLE}
    return StreamingResponse(_stream(f), media_type=media, headers=headers)


def load_scene(s: Service, sid: str):
    """The loaded runtime Scene of a ready scene (from the scene cache), in a worker thread."""
    from xyzcyl.runtime.scene import Scene, SceneError

    def load():
        try:
            return Scene.load(s.store.scene_dir(sid))
        except (KeyError, SceneError, FileNotFoundError):
            raise NotFound(f"scene {sid} was deleted", "id") from None

    return s.scenes.get(sid, load)


__all__ = ["ERRORS", "get_record", "load_scene", "ready_record", "router", "scene_info"]
