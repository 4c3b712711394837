"""What the routes declare and answer besides the wire types (xyzcyl.common.wire, the JSON bodies shared with the
client): the OpenAPI error responses and request bodies, and the API's scene JSON made
from a store record."""

from __future__ import annotations

import datetime as dt
from typing import Any

from xyzcyl.common.wire import ErrorBody

from .store import SceneRecord

# the error answers of the /v1 routes, for the OpenAPI document
ERRORS = {s: {"model": ErrorBody} for s in (401, 404, 409, 413, 415, 422, 503, 507)}
NO_MODEL = {404: {"model": ErrorBody, "description": "no such model"}}

# POST /v1/scenes reads its multipart body itself (uploads.py); the schema for the OpenAPI document
SCENE_UPLOAD = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object",
    "properties": {"rig": {"type": "string", "format": "binary", "description": "rig.json (cameras, calibrations)"},
                   "drive": {"type": "string", "format": "binary",
                             "description": "instead of 'rig', a recorded drive: {\"frames\": [{\"rig\": {... "
                                            "rig.json ...}, \"timestamp_s\": ...}, ...], \"tracks\": [...]} "
                                            "(docs/api.md \"Drives\")"}},
    "additionalProperties": {"type": "string", "format": "binary",
                             "description": "one image part per camera, named by the camera; optional "
                                            "'depth:<camera>' and 'ego_mask:<camera>' parts and an optional 'lidar' "
                                            "part (a LiDAR sweep: .npy or float32 .bin); a drive's parts are "
                                            "named the same way under 'frames/<frame>/'"}}}}}}

# POST /v1/scenes/{id}/render reads its JSON body itself (runtime.views.cameras_from_batch)
RENDER_BATCH = {"requestBody": {"required": True, "content": {"application/json": {"schema": {
    "type": "object", "description": "{\"cameras\": [...]} (OpenCV K + cam_to_ego, CARLA sensors, input camera "
    "names) or a nerfstudio camera_path.json; optional output, format, quality"}}}}}


def _iso(ts: float | None) -> str:
    return dt.datetime.fromtimestamp(ts or 0.0, dt.UTC).replace(microsecond=0).isoformat()


def scene_info(rec: SceneRecord) -> dict[str, Any]:
    """The API's scene JSON (wire.SceneInfo) of a record: times in ISO 8601, the links a client may follow."""
    sid = rec.id
    base = f"/v1/scenes/{sid}"
    links = {"self": base}
    if rec.state == "ready":
        links |= {"gaussians": f"{base}/gaussians", "render": f"{base}/render"}
        if rec.background:
            links["background"] = f"{base}/background"
    return {"id": sid, "name": rec.name, "state": rec.state, "created": _iso(rec.created_ts),
            "updated": _iso(rec.updated_ts), "error": None if rec.error is None else rec.error.model_dump(),
            "cameras": [c.model_dump() for c in rec.cameras],
            "detail": None if rec.detail is None else rec.detail.model_dump(), "model": rec.model,
            "counts": rec.counts, "gaussians": rec.gaussians, "background": rec.background, "bbox": rec.bbox,
            "timings": rec.timings, "bytes": rec.bytes, "drive": None if rec.drive is None else rec.drive.model_dump(),
            "links": links}


def scene_list(page: list[SceneRecord], total: int, offset: int, limit: int) -> dict[str, Any]:
    """A page of GET /v1/scenes (wire.SceneList): ``next`` is the next page's path, None on the last."""
    nxt = f"/v1/scenes?offset={offset + limit}&limit={limit}" if offset + limit < total else None
    return {"scenes": [scene_info(r) for r in page], "total": total, "offset": offset, "limit": limit, "next": nxt}


__all__ = ["ERRORS", "NO_MODEL", "RENDER_BATCH", "SCENE_UPLOAD", "scene_info", "scene_list"]
