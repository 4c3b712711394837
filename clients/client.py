"""A Python client for the xyzcyl HTTP service (docs/api.md; docs/client.md has examples).

    from xyzcyl.clients import Client

    with Client("http://127.0.0.1:8000") as c:
        scene = c.reconstruct("examples/synth_nuscenes/rig.json")          # uploads, waits until ready
        drive = c.reconstruct("recording/drive.json")                      # a recorded drive: one scene
        rgb = c.render(scene.id, "CAM_FRONT")                              # [H, W, 3] float32 0..1, RGB
        depth = c.render(scene.id, {"x": 5, "y": 0, "z": 1.6, "pitch": 0, "yaw": 0, "roll": 0, "fov": 90,
                                    "width": 800, "height": 600}, output="depth")   # [H, W] metres
        c.gaussians(scene.id, "scene.ply")
        for name, frame in c.render_path(scene.id, "camera_path.json"):
            ...

The client speaks HTTP only. It builds the request the API documents and never converts camera conventions: a
CARLA transform goes to the server as CARLA fields, a nerfstudio camera path as the file's JSON.

Retries. A 429 or 503 answer means nothing was done; every call retries it after the answer's Retry-After
(capped at ``retry_after_cap`` seconds), at most ``retries`` times, then raises BusyError. Connection errors
(refused, reset, timed out) are retried the same way only for idempotent calls: GET, DELETE and the batch render
POST. A POST /v1/scenes whose connection failed is not repeated (it may have created a scene): ConnectionFailed.

Errors. Every failed call raises an XyzcylError subclass that carries the HTTP status and the server's error
``code``, ``message`` and ``field`` (docs/api.md, "Errors"). Input the client refuses itself (a missing image
file, a camera it cannot express) raises InvalidRequestError with ``status`` None.
"""

from __future__ import annotations

import email.utils
import json
import math
import os
import re
import secrets
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Self

import httpx
import numpy as np
from pydantic import BaseModel, ValidationError
from xyzcyl.common import wire
from xyzcyl.common.files import atomic_file
from xyzcyl.common.media import EXR, SNIFF_BYTES, exr_bytes, media_of_suffix, sniff
from xyzcyl.common.poses import CARLA_POSE, MOVE_NAMES, CameraMove, MoveError
from xyzcyl.common.wire import ViewError, is_drive_file, validated

DEFAULT_SERVER = "http://127.0.0.1:8000"
USER_AGENT = "xyzcyl-client/0.1"
Progress = Callable[[int, "int | None"], None]   # (done, total): bytes sent / received, or frames received

_CHUNK = 1 << 20
_MAX_WAIT_QUERY = 3600          # the server refuses ?wait= above this (it also caps it at its wait_max_s)
_BACKOFF_S, _BACKOFF_CAP_S = 0.25, 4.0
_IDEMPOTENT = ("GET", "HEAD", "OPTIONS", "DELETE", "PUT")

# Module-level so tests can patch them (retry delays, wait deadlines).
_sleep = time.sleep
_monotonic = time.monotonic


# ----------------------------------------------------------------------------------------------- errors

class XyzcylError(Exception):
    """A failed call. ``status``: the HTTP status (None when no answer came, or the client refused the input
    itself); ``code``, ``message``, ``field``: the server's error body (docs/api.md); ``scene_id``: the scene it
    concerns when known (a reconstruction that failed); ``retry_after``: seconds, from a 409/429/503 answer."""

    def __init__(self, status: int | None, code: str, message: str, field: str | None = None, *,
                 scene_id: str | None = None, retry_after: float | None = None):
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.scene_id = scene_id
        self.retry_after = retry_after

    def __str__(self) -> str:
        named = self.field and self.message.startswith((f"{self.field}:", f"part {self.field!r}:"))
        where = f"{self.field}: " if self.field and not named else ""
        tag = f"{self.status} {self.code}" if self.status is not None else self.code
        return f"{where}{self.message} [{tag}]"

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(status={self.status!r}, code={self.code!r}, message={self.message!r}, "
                f"field={self.field!r})")

    def __reduce__(self):
        return (_rebuild, (type(self), self.status, self.code, self.message, self.field, self.scene_id,
                           self.retry_after))


def _rebuild(cls, status, code, message, fld, scene_id, retry_after):
    return cls(status, code, message, fld, scene_id=scene_id, retry_after=retry_after)


class AuthError(XyzcylError):
    """401: the server wants an API key (``api_key=`` / $XYZCYL_API_KEY) and got none or a wrong one."""


class NotFoundError(XyzcylError):
    """404: unknown (or deleted) scene, or a scene without a background."""


class NotReadyError(XyzcylError):
    """409: the scene is queued or running (code ``not_ready``), or it failed (code ``scene_failed``)."""


class WaitTimeout(NotReadyError):
    """reconstruct(wait=True) / wait(): the scene was not ready by the deadline (``scene_id`` names it; it keeps
    running on the server)."""


class InvalidRequestError(XyzcylError):
    """400 / 413 / 415 / 422: the request was refused (``field`` names the part, parameter or JSON path), or the
    client refused the input before sending it (``status`` None)."""


class InvalidArgumentError(InvalidRequestError, ValueError):
    """An argument value the client refuses before sending anything (``status`` None, ``field`` the argument): an
    InvalidRequestError that is also a ValueError."""


class BusyError(XyzcylError):
    """429 / 503: still busy after the client's retries."""


class StorageFullError(XyzcylError):
    """507: the server's store is full (quota with when_full=reject, or its disk)."""


class ServerError(XyzcylError):
    """5xx: the server failed (``worker_crashed``, ``timeout``, ``internal``, ...)."""


class ConnectionFailed(XyzcylError):
    """No answer: the connection was refused, reset or timed out (after the retries of an idempotent call)."""


def error_for(status: int | None, code: str, message: str, field: str | None = None, **kw) -> XyzcylError:
    """The XyzcylError subclass for an HTTP status."""
    if status is None:
        cls = ConnectionFailed
    elif status == 401:
        cls = AuthError
    elif status == 404:
        cls = NotFoundError
    elif status == 409:
        cls = NotReadyError
    elif status in (400, 413, 415, 422):
        cls = InvalidRequestError
    elif status in (429, 503):
        cls = BusyError
    elif status == 507:
        cls = StorageFullError
    elif status >= 500:
        cls = ServerError
    else:
        cls = XyzcylError
    return cls(status, code, message, field, **kw)


def _invalid(message: str, field: str | None) -> InvalidRequestError:
    return InvalidRequestError(None, "invalid", message, field)


def _detail_params(detail_stride: int | None, detail: bool) -> dict[str, str]:
    """The query parameters of POST /v1/scenes for the detail layer (none for the server's default)."""
    if not isinstance(detail, bool):
        raise InvalidArgumentError(None, "invalid", f"detail: must be True or False (got {detail!r:.60})", "detail")
    if detail_stride is None:
        return {} if detail else {"detail": "false"}
    why = wire.detail_stride_error(detail_stride, detail, off="detail=False")
    if why is not None:
        raise InvalidArgumentError(None, "invalid", f"detail_stride: {why}", "detail_stride")
    return {"detail_stride": str(int(detail_stride))}


def _scene_params(detail_stride: int | None, detail: bool, name: str | None) -> dict[str, str]:
    """POST /v1/scenes' query parameters of the detail layer and the scene's name."""
    query = _detail_params(detail_stride, detail)
    if name is not None:
        if not isinstance(name, str):
            raise InvalidArgumentError(None, "invalid", f"name: must be a string (got {name!r:.60})", "name")
        query["name"] = name
    return query


def _retry_after(resp: httpx.Response) -> float | None:
    value = resp.headers.get("retry-after")
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:   # an HTTP date
        when = email.utils.parsedate_to_datetime(value)
        return max(0.0, when.timestamp() - time.time())
    except (TypeError, ValueError, IndexError, OverflowError):
        return None


def _scene_id_from(resp: httpx.Response) -> str | None:
    loc = resp.headers.get("location", "")
    return loc.rstrip("/").rsplit("/", 1)[-1] or None if loc.startswith("/v1/scenes/") else None


def _error_from(resp: httpx.Response) -> XyzcylError:
    """The error a non-2xx answer stands for (the body must have been read)."""
    status = resp.status_code
    code, message, fld = f"http_{status}", resp.reason_phrase or f"HTTP {status}", None
    try:
        err = wire.ErrorBody.model_validate_json(resp.content).error
    except ValidationError:     # not the API's error body (a proxy's page, no body): its text, if any
        text = resp.text.strip() if resp.content else ""
        if text:
            message = text[:300]
    else:
        code, message, fld = err.code or code, err.message or message, err.field
    return error_for(status, code, message, fld, scene_id=_scene_id_from(resp), retry_after=_retry_after(resp))


# ----------------------------------------------------------------------------------------------- scenes

# a scene as the server describes it (GET /v1/scenes/{id}; docs/api.md): the wire type itself
SceneInfo = wire.SceneInfo


def _failure(info: SceneInfo) -> XyzcylError:
    """A failed scene as the error POST /v1/scenes?wait= would have answered (same status for the same code)."""
    code = info.error.code if info.error is not None else "failed"
    message = info.error.message if info.error is not None else "failed"
    status, fld = wire.failure_answer(code)
    return error_for(status, code, f"scene {info.id}: {message}", fld, scene_id=info.id)


# ----------------------------------------------------------------------------------------------- uploads

def _quote(value: str) -> str:
    """A multipart parameter value, HTML5 style (what browsers and httpx send)."""
    out = value.replace("\\", "\\\\").replace('"', "%22")
    return re.sub(r"[\x00-\x1f]", lambda m: f"%{ord(m.group(0)):02X}", out)


@dataclass
class _Part:
    name: str
    filename: str
    content_type: str
    data: bytes | None = None
    path: Path | None = None

    def size(self) -> int:
        return len(self.data) if self.data is not None else self.path.stat().st_size

    def chunks(self) -> Iterator[bytes]:
        if self.data is not None:
            for i in range(0, len(self.data), _CHUNK):
                yield self.data[i:i + _CHUNK]
            return
        left = self.size()
        with open(self.path, "rb") as f:
            while left > 0 and (b := f.read(min(_CHUNK, left))):
                left -= len(b)
                yield b


class _Multipart:
    """multipart/form-data streamed from files (never all in memory), with a known Content-Length (the server
    refuses an oversized body from it before reading) and an upload progress callback. stream() can be called
    again for a retry."""

    def __init__(self, parts: list[_Part]):
        self.boundary = secrets.token_hex(16)
        self.parts = parts
        self.heads = [(f"--{self.boundary}\r\nContent-Disposition: form-data; name=\"{_quote(p.name)}\"; "
                       f"filename=\"{_quote(p.filename)}\"\r\nContent-Type: {p.content_type}\r\n\r\n").encode()
                      for p in parts]
        self.tail = f"--{self.boundary}--\r\n".encode()
        self.length = sum(len(h) + p.size() + 2 for h, p in zip(self.heads, parts)) + len(self.tail)

    @property
    def headers(self) -> dict[str, str]:
        return {"Content-Type": f"multipart/form-data; boundary={self.boundary}", "Content-Length": str(self.length)}

    def stream(self, progress: Progress | None = None) -> Iterator[bytes]:
        sent = 0
        for head, part in zip(self.heads, self.parts):
            for b in (head, *part.chunks(), b"\r\n"):
                yield b
                sent += len(b)
                if progress is not None:
                    progress(sent, self.length)
        yield self.tail
        if progress is not None:
            progress(self.length, self.length)


def _media_type(head: bytes) -> str:
    """The media type of a part whose file name says nothing, from its first bytes."""
    media = sniff(head)
    return "application/octet-stream" if media is None else media.type


def encode_png(image: np.ndarray) -> bytes:
    """An RGB(A) or grey array -> PNG bytes: uint8 / uint16 kept; float taken as 0..1 and written as 16-bit
    (no precision lost to 8 bits); RGB order in, as the PNG stores it."""
    import cv2

    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)) or a.size == 0:
        raise _invalid(f"an image array must be [H, W], [H, W, 3] or [H, W, 4] (got shape {list(a.shape)})", None)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif a.dtype.kind == "f":
        a = np.clip(np.rint(np.nan_to_num(a.astype(np.float64), nan=0.0) * 65535.0), 0, 65535).astype(np.uint16)
    elif a.dtype not in (np.uint8, np.uint16):
        raise _invalid(f"an image array must be uint8, uint16 or float (0..1), not {a.dtype}", None)
    if a.ndim == 3:
        a = a[..., [2, 1, 0, 3][: a.shape[2]]]      # RGB(A) -> OpenCV's BGR(A)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV always encodes these types
        raise _invalid("OpenCV could not encode the array as PNG", None)
    return buf.tobytes()


def _encode_depth(depth: np.ndarray) -> tuple[bytes, str, str]:
    """A depth array -> (bytes, extension, media type): uint16 = millimetres as a 16-bit PNG; float = metres
    along the optical axis as a float32 EXR (one channel Z)."""
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise _invalid(f"a depth array must be [H, W] (got shape {list(d.shape)})", None)
    if d.dtype == np.uint16:
        return encode_png(d), ".png", "image/png"
    if d.dtype.kind != "f":
        raise _invalid(f"a depth array must be uint16 (millimetres) or float (metres), not {d.dtype}", None)
    return exr_bytes(d.astype(np.float32)[..., None], ("Z",), compression="zip"), EXR.suffix, EXR.type


def _part(name: str, src: Any, root: Path | None, depth: bool) -> _Part:
    stem = name.replace("/", "_")
    if isinstance(src, (str, os.PathLike)):
        path = Path(src)
        if root is not None and not path.is_absolute():
            path = root / path
        if not path.is_file():
            raise InvalidRequestError(None, "file_missing", f"cannot read {str(path)!r}: no such file", name)
        media = media_of_suffix(path.suffix)
        if media is not None:
            return _Part(name, path.name, media.type, path=path)
        with open(path, "rb") as f:
            return _Part(name, path.name, _media_type(f.read(SNIFF_BYTES)), path=path)
    if isinstance(src, (bytes, bytearray, memoryview)):
        data = bytes(src)
        return _Part(name, stem, _media_type(data[:SNIFF_BYTES]), data=data)
    if isinstance(src, np.ndarray):
        try:
            if depth:
                data, ext, media = _encode_depth(src)
            else:
                data, ext, media = encode_png(src), ".png", "image/png"
        except InvalidRequestError as e:
            raise InvalidRequestError(None, e.code, e.message, name) from None
        return _Part(name, stem + ext, media, data=data)
    raise TypeError(f"{name}: an image is a file path, bytes or a numpy array, not {type(src).__name__}")


def _lidar_part(doc: dict[str, Any], root: Path | None, lidar: Any, part: str = "lidar") -> _Part | None:
    """The 'lidar' part (named ``part``): ``lidar`` (a path relative to the working folder, or bytes), or with None
    the file the rig's lidar block names (relative to rig.json's folder); False or nothing named: None."""
    if lidar is False:
        return None
    if lidar is None:
        block = doc.get("lidar")
        src = block.get("file") if isinstance(block, dict) else None
        if not src:
            return None
        path = Path(src)
        if root is not None and not path.is_absolute():
            path = root / path
    elif isinstance(lidar, (bytes, bytearray, memoryview)):
        return _Part(part, "lidar.bin", "application/octet-stream", data=bytes(lidar))
    elif isinstance(lidar, (str, os.PathLike)):
        path = Path(lidar)
    else:
        raise TypeError(f"lidar: a file path, bytes, None or False, not {type(lidar).__name__}")
    if not path.is_file():
        raise InvalidRequestError(None, "file_missing", f"cannot read {str(path)!r}: no such file", part)
    return _Part(part, path.name, "application/octet-stream", path=path)


def _rig_document(rig: Any) -> tuple[dict[str, Any], Path | None]:
    """(rig JSON as a dict, folder its file names are relative to) from a rig.json path, a runtime Rig, or the
    rig's JSON as a dict. The server validates the calibration; the client only reads the camera names."""
    if isinstance(rig, (str, os.PathLike)):
        path = Path(rig)
        try:
            doc = json.loads(path.read_text())
        except OSError as e:
            raise InvalidRequestError(None, "file_missing", f"cannot read {str(path)!r}: {e.strerror or e}",
                                      "rig") from None
        except ValueError as e:
            raise _invalid(f"{str(path)!r} is not valid JSON ({e})", "rig") from None
        root = path.parent
    elif hasattr(rig, "to_dict") and hasattr(rig, "cameras"):   # xyzcyl.runtime.rig.Rig
        doc, root = rig.to_dict(), getattr(rig, "root", None)
    elif isinstance(rig, Mapping):
        doc, root = dict(rig), None
    else:
        raise TypeError(f"rig: a rig.json path, a Rig or the rig's JSON dict, not {type(rig).__name__}")
    cams = doc.get("cameras") if isinstance(doc, Mapping) else None
    if not isinstance(cams, list) or not cams or not all(isinstance(c, Mapping) and isinstance(c.get("name"), str)
                                                         for c in cams):
        raise _invalid("cameras must be a non-empty list of objects with a name", "rig.cameras")
    return doc, (Path(root) if root is not None else None)


def _by_camera(values: Any, names: list[str], what: str) -> dict[str, Any] | None:
    if values is None:
        return None
    if isinstance(values, Mapping):
        unknown = [k for k in values if k not in names]
        if unknown:
            raise _invalid(f"{what}: {unknown[0]!r} is not a camera of the rig (cameras: {', '.join(names)})",
                           unknown[0])
        return dict(values)
    values = list(values)
    if len(values) != len(names):
        raise _invalid(f"{what}: {len(values)} given for {len(names)} cameras (give them in rig order, or a dict "
                       "by camera name)", what)
    return dict(zip(names, values))


def _rig_parts(doc: dict[str, Any], root: Path | None, imgs: dict | None, dps: dict | None, masks: dict | None,
               lidar: Any, prefix: str = "", where: str = "") -> list[_Part]:
    """One rig's file parts (Client.reconstruct's arguments: None = the files the rig names, relative to ``root``;
    a dict by camera = those given, relative to the working folder): an image per camera, its depth and ego mask
    when there is one, then the LiDAR sweep. ``prefix``: the parts' names start with it (a drive's
    ``frames/<frame>/``); ``where``: the words before a message about a camera ("frame 3: ")."""
    names = [c["name"] for c in doc["cameras"]]
    parts = []
    for cam in doc["cameras"]:
        name = cam["name"]
        if imgs is None:
            src = cam.get("image")
            if not src:
                hint = "" if prefix else "; pass images={...}"
                raise _invalid(f"{where}camera {name!r} names no image file{hint}", prefix + name)
            parts.append(_part(prefix + name, src, root, depth=False))
        elif name in imgs:
            parts.append(_part(prefix + name, imgs[name], None, depth=False))      # given paths: relative to the cwd
        else:
            raise _invalid(f"no image for camera {name!r} (cameras: {', '.join(names)})", prefix + name)
        dsrc = cam.get("depth") if dps is None else dps.get(name)
        if dsrc is not None:
            parts.append(_part(f"{prefix}depth:{name}", dsrc, root if dps is None else None, depth=True))
        msrc = cam.get("ego_mask") if masks is None else masks.get(name)
        if msrc is not None:
            try:
                parts.append(_part(f"{prefix}ego_mask:{name}", msrc, root if masks is None else None, depth=False))
            except InvalidRequestError as e:
                raise type(e)(None, e.code, f"{where}camera {name!r}: ego_mask: {e.message}", e.field) from None
    lidar_part = _lidar_part(doc, root, lidar, prefix + "lidar")
    if lidar_part is not None:
        parts.append(lidar_part)
    return parts


def _json_file(path: Path, field: str) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise InvalidRequestError(None, "file_missing", f"cannot read {str(path)!r}: {e.strerror or e}",
                                  field) from None
    except ValueError as e:
        raise _invalid(f"{str(path)!r} is not valid JSON ({e})", field) from None


@dataclass
class DriveUpload:
    """A drive file as POST /v1/scenes takes it (read_drive; docs/api.md "Drives"): ``parts``, the 'drive' part (the
    drive document with each frame's rig and the tracks inline) then every frame's file parts; ``frames``, the
    number of frames; ``cameras``, the first frame's camera names; ``lidar_frames``, the frames with a sweep."""

    path: Path
    parts: list[_Part]
    frames: int
    cameras: list[str]
    lidar_frames: int

    @property
    def size(self) -> int:
        """The bytes of the parts (the body is a little more)."""
        return sum(p.size() for p in self.parts)


def read_drive(path: str | os.PathLike, depths: bool = True, lidar: bool = True,
               ego_masks: bool = True) -> DriveUpload:
    """A drive file read for POST /v1/scenes (docs/api.md "Drives"): each frame's rig.json (relative to the drive
    file; or inline, its files then relative to the drive file) put inline in the 'drive' part with the frame
    entry's other keys (timestamp_s), the tracks file (relative to the drive file) put inline, and each frame's
    files (images, depth maps, ego masks, the LiDAR sweep its lidar block names; relative to its rig.json) as parts
    named ``frames/<frame>/<name>``. ``depths``, ``lidar``, ``ego_masks`` False leave those files out. The client's
    own small reader (the client speaks HTTP and imports no runtime): the server checks the drive
    (runtime.drive.load_drive), the client only what it needs to find the files. Refusals raise InvalidRequestError
    (``status`` None) naming the drive file's field ("frames[2].rig", "tracks") or the part
    ("frames/2/CAM_FRONT")."""
    p = Path(path)
    doc = _json_file(p, "drive")
    items = doc.get("frames") if wire.is_drive_document(doc) else None
    if not isinstance(items, list) or not items:
        raise _invalid(f"{str(p)!r} is not a drive file: it must be a JSON object with a non-empty \"frames\" list "
                       "({\"rig\": \"frame_00/rig.json\", \"timestamp_s\": ...})", "frames")
    parts: list[_Part] = []
    frames, cameras, with_lidar = [], None, 0
    for i, item in enumerate(items):
        fld = f"frames[{i}].rig"
        src = item.get("rig") if isinstance(item, Mapping) else None
        if not isinstance(src, (str, Mapping)):
            raise _invalid(f"{fld}: must name the frame's rig.json (relative to the drive file)", fld)
        try:
            rig, root = _rig_document(p.parent / src if isinstance(src, str) else src)
        except InvalidRequestError as e:
            raise type(e)(None, e.code, f"{fld}: {e.message}", fld) from None
        rig_parts = _rig_parts(rig, p.parent if root is None else root, None, None if depths else {},
                               None if ego_masks else {}, None if lidar else False, wire.frame_part(i, ""),
                               f"frame {i}: ")
        with_lidar += any(x.name.endswith("/lidar") for x in rig_parts)
        parts += rig_parts
        frames.append({**item, "rig": rig})
        cameras = cameras or [c["name"] for c in rig["cameras"]]
    out: dict[str, Any] = {"frames": frames}
    tracks = doc.get("tracks")
    if isinstance(tracks, str):
        tracks = _json_file(p.parent / tracks, "tracks")
    if tracks is not None:
        out["tracks"] = tracks
    try:
        data = json.dumps(out, allow_nan=False).encode()
    except ValueError as e:
        raise _invalid(f"{str(p)!r}: {e} (NaN or infinity in a rig or the tracks)", "drive") from None
    parts.insert(0, _Part(wire.DRIVE_PART, "drive.json", "application/json", data=data))
    return DriveUpload(p, parts, len(items), cameras or [], with_lidar)


def _keyframe_params(keyframe_spacing: Any, keyframe_gap: Any) -> dict[str, str]:
    """POST /v1/scenes' keyframe query parameters of a drive (none for the server's defaults);
    InvalidArgumentError naming the argument for a value that is not a finite number > 0."""
    out = {}
    for k, v in zip(wire.KEYFRAME_PARAMS, (keyframe_spacing, keyframe_gap), strict=True):
        if (why := wire.keyframe_error(v)) is not None:
            raise InvalidArgumentError(None, "invalid", f"{k}: {why}", k)
        if v is not None:
            out[k] = repr(float(v))
    return out


# ----------------------------------------------------------------------------------------------- views

def _fields(camera: Any) -> dict[str, Any]:
    if isinstance(camera, Mapping):
        return dict(camera)
    keys = ("K", "cam_to_ego", "cam_to_world", "width", "height", "fov", "distortion", "camera", *CARLA_POSE,
            "transform", "image_size_x", "image_size_y")
    return {k: getattr(camera, k) for k in keys if getattr(camera, k, None) is not None}


def _num(v: Any, fld: str) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise _invalid(f"must be a number (got {v!r:.60})", fld) from None
    return repr(x)


def _flat(v: Any, n: int, fld: str) -> list[float]:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _invalid(f"must be {n} numbers", fld) from None
    if a.size != n:
        raise _invalid(f"must be {n} numbers (got {a.size})", fld)
    return a.tolist()


def _move(move: Any, where: str = "move") -> CameraMove:
    """``move`` (None, a CameraMove or a mapping {forward, left, up, yaw}) as a CameraMove; InvalidRequestError
    naming "<where>.<field>" otherwise."""
    if move is None or isinstance(move, CameraMove):
        return move or CameraMove()
    if not isinstance(move, Mapping):
        raise _invalid(f"must be a CameraMove or a mapping {{{', '.join(MOVE_NAMES)}}} (got {move!r:.60})", where)
    unknown = [k for k in move if k not in MOVE_NAMES]
    if unknown:
        raise _invalid(f"unknown field (a move takes {', '.join(MOVE_NAMES)})", f"{where}.{unknown[0]}")
    try:
        return CameraMove.from_values(move)
    except MoveError as e:
        raise _invalid(e.message, f"{where}.{e.field}") from None


def view_params(camera: Any, width: int | None = None, height: int | None = None, move: Any = None
                ) -> dict[str, str]:
    """The query parameters of GET /v1/scenes/{id}/render for a camera (docs/api.md):

    - a str: an input camera of the scene (``width``/``height`` resize it; the server scales K);
    - OpenCV: a dict or object with ``cam_to_ego`` (or ``cam_to_world``; 4x4 or 16 numbers, row-major) and ``K``
      (3x3 or 9 numbers, pixels, no skew) or ``fov`` (horizontal degrees), plus ``width``/``height`` (the
      arguments win) and optionally ``distortion``, the lens as rig.json writes it (an OpenCV coefficient list or
      {"model": "opencv" | "opencv_fisheye" | "ftheta", ...}; an object with ``to_json()`` works too);
    - CARLA: {x, y, z, pitch, yaw, roll, fov, width, height} (a sensor's transform relative to the vehicle), or
      a CARLA sensor dict {"transform": {"location": {x, y, z}, "rotation": {pitch, yaw, roll}}, "fov",
      "image_size_x", "image_size_y"};
    - {"camera": NAME[, "width", "height", "distortion"]}, as the batch endpoint takes it (with ``distortion``: the
      input camera's pose and K through that lens).

    ``move``: a camera move (common.poses.CameraMove, or a mapping {forward, left, up (metres along ego x, y, z),
    yaw (degrees to the left)}), sent as the query's forward, left, up, yaw for an input camera or an explicit pose
    (the server moves it: runtime.views.move_camera); on a CARLA pose it is folded into the transform
    (CameraMove.apply_carla), as the query's yaw is the transform's there. An input-camera or OpenCV dict may hold
    the move's keys itself, as a batch item does (then no ``move`` argument)."""
    mv = _move(move)
    if isinstance(camera, str):
        p = {"camera": camera}
    else:
        c = _fields(camera)
        if "transform" in c:
            tf = c["transform"]
            if not isinstance(tf, Mapping) or not isinstance(tf.get("location"), Mapping) \
                    or not isinstance(tf.get("rotation"), Mapping):
                raise _invalid('must be {"location": {x, y, z}, "rotation": {pitch, yaw, roll}}', "camera.transform")
            c = {**tf["location"], **tf["rotation"], "fov": c.get("fov"),
                 "width": c.get("image_size_x", c.get("width")), "height": c.get("image_size_y", c.get("height"))}
        explicit = any(k in c for k in ("camera", "cam_to_ego", "cam_to_world"))   # then "yaw" is the move's
        carla = [k for k in CARLA_POSE if k in c and not (explicit and k == "yaw")]
        if explicit and carla:
            raise _invalid("give one pose: an input camera, cam_to_ego or a CARLA transform", f"camera.{carla[0]}")
        if carla:
            missing = [k for k in (*CARLA_POSE, "fov") if c.get(k) is None]
            if missing:
                raise _invalid(f"a CARLA pose needs x, y, z, pitch, yaw, roll and fov; missing {', '.join(missing)}",
                               f"camera.{missing[0]}")
            inline = [k for k in MOVE_NAMES if k != "yaw" and k in c]
            if inline:
                raise _invalid("a CARLA pose takes its move as the move argument (its yaw is the transform's)",
                               f"camera.{inline[0]}")
            p = {k: _num(c[k], f"camera.{k}") for k in (*CARLA_POSE, "fov")}
            if mv:           # folded into the transform; the query's yaw is the transform's
                pose = mv.apply_carla(*(float(p[k]) for k in CARLA_POSE))
                p.update({k: repr(v) for k, v in zip(CARLA_POSE, pose, strict=True)})
                mv = CameraMove()
        elif "cam_to_ego" in c or "cam_to_world" in c:
            pose = c.get("cam_to_ego", c.get("cam_to_world"))
            p = {"cam_to_ego": ",".join(repr(x) for x in _flat(pose, 16, "camera.cam_to_ego"))}
            if c.get("K") is not None:
                K = _flat(c["K"], 9, "camera.K")
                if K[1] != 0 or K[3] != 0 or K[6:] != [0.0, 0.0, 1.0]:
                    raise _invalid("must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)", "camera.K")
                p.update(fx=repr(K[0]), fy=repr(K[4]), cx=repr(K[2]), cy=repr(K[5]))
            elif c.get("fov") is not None:
                p["fov"] = _num(c["fov"], "camera.fov")
            else:
                raise _invalid("an OpenCV camera needs K (pixels) or fov (horizontal degrees)", "camera.K")
        elif "camera" in c:
            p = {"camera": str(c["camera"])}
        else:
            raise _invalid("a camera is an input camera name, {K or fov, cam_to_ego, width, height} (OpenCV) or "
                           "{x, y, z, pitch, yaw, roll, fov, width, height} (CARLA)", "camera")
        inline = {k: c[k] for k in MOVE_NAMES if k in c} if "cam_to_ego" in p or "camera" in p else {}
        if inline:
            if mv:
                raise _invalid("give the move in the camera or as the move argument, not both", "move")
            mv = _move(inline, "camera")
        lens = c.get("distortion")
        if lens is not None:
            if "cam_to_ego" not in p and "camera" not in p:
                raise _invalid("a lens goes with cam_to_ego or an input camera; a CARLA camera has none",
                               "camera.distortion")
            lens = lens.to_json() if hasattr(lens, "to_json") else lens
            if not isinstance(lens, (list, tuple, Mapping)):
                raise _invalid("must be a list of OpenCV coefficients or an object {\"model\": ..., ...}",
                               "camera.distortion")
            p["distortion"] = json.dumps(lens if isinstance(lens, Mapping) else list(lens), separators=(",", ":"))
        width = c.get("width") if width is None else width
        height = c.get("height") if height is None else height
        if "camera" not in p and (width is None or height is None):
            raise _invalid("width and height are required for a camera given by its pose",
                           "width" if width is None else "height")
    if width is not None:
        p["width"] = str(int(width))
    if height is not None:
        p["height"] = str(int(height))
    p.update({k: repr(v) for k, v in mv.values().items()})
    try:     # the query the server takes (common.wire.ViewQuery), checked here as the server checks it
        query = validated(p, {k: f"camera.{k}" for k in p if k not in ("width", "height", *MOVE_NAMES)})
    except ViewError as e:
        raise _invalid(e.message, e.field) from None
    return query.params()


def _read_float_image(data: bytes) -> np.ndarray:
    import OpenImageIO as oiio

    with tempfile.TemporaryDirectory(prefix="xyzcyl-view-") as tmp:
        path = Path(tmp) / "view.exr"
        path.write_bytes(data)
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ServerError(None, "bad_image", f"the server's EXR cannot be read ({oiio.geterror()})")
        try:
            a = inp.read_image(oiio.FLOAT)
        finally:
            inp.close()
    if a is None:
        raise ServerError(None, "bad_image", f"the server's EXR cannot be decoded ({oiio.geterror()})")
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


def decode_image(data: bytes, output: str = "rgb") -> np.ndarray:
    """A view's bytes (PNG, JPEG or EXR, as the render endpoints answer) -> float32 array: rgb [H, W, 3] in
    0..1, RGB order (EXR: linear floats as stored); depth [H, W] in metres (16-bit PNG millimetres x 0.001; 0 = no
    surface); alpha [H, W] in 0..1."""
    if sniff(data[:SNIFF_BYTES]) == EXR:
        a = _read_float_image(data)
    else:
        import cv2

        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise ServerError(None, "bad_image", "the server's image cannot be decoded")
        if a.ndim == 3:
            a = a[..., [2, 1, 0, 3][: a.shape[2]]]   # BGR(A) -> RGB(A)
        if output == "depth" and a.dtype == np.uint16:
            a = a.astype(np.float32) * np.float32(0.001)
        elif np.issubdtype(a.dtype, np.integer):
            a = a.astype(np.float32) / np.float32(np.iinfo(a.dtype).max)
        else:
            a = a.astype(np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if output in ("depth", "alpha") and a.ndim == 3:
        a = a[..., 0]
    return np.ascontiguousarray(a)


def write_video(frames_dir: Path, names: list[str], output: str, video: Path, fps: float) -> str | None:
    """The frame files ``names`` in ``frames_dir`` (as a batch render wrote them) -> an mp4 (OpenCV VideoWriter,
    mp4v) at ``fps``; grey frames (alpha) are repeated to RGB. Returns an error message, or None."""
    import cv2

    writer = None
    try:
        for name in names:
            img = decode_image((frames_dir / name).read_bytes(), output)
            if img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=-1)
            bgr = np.ascontiguousarray(np.clip(np.rint(img[..., ::-1] * 255.0), 0, 255).astype(np.uint8))
            h, w = bgr.shape[:2]
            if writer is None:
                size = (w, h)
                writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
                if not writer.isOpened():
                    return (f"OpenCV cannot write {str(video)!r}: the mp4v (MPEG-4) codec is unavailable in this "
                            f"OpenCV build; the frames are in {str(frames_dir)!r}")
            if (w, h) != size:
                return f"frame {name} is {w}x{h}, the video is {size[0]}x{size[1]}: a video needs one frame size"
            writer.write(bgr)
    finally:
        if writer is not None:
            writer.release()
    return None


class FrameBatch:
    """The frames of a batch render (POST /v1/scenes/{id}/render), spooled to a temporary file: iterate for
    (file name, frame) in order; ``index`` is the zip's index.json (each frame's size, K, cam_to_ego).
    Frames are float32 arrays (decode_image) or the server's bytes (decode=False)."""

    def __init__(self, spool: IO[bytes], decode: bool = True):
        self._spool = spool
        self._zip = zipfile.ZipFile(spool)
        try:
            self.index: dict[str, Any] = json.loads(self._zip.read("index.json"))
            index = wire.BatchIndex.model_validate(self.index)
        except (KeyError, ValueError) as e:       # not JSON, or not a wire.BatchIndex (a ValidationError)
            self.close()
            raise ServerError(None, "bad_batch", f"the batch answer has no readable index.json ({e})") from None
        self.output = index.output
        self.format = index.format
        self.names = [f.file for f in index.frames]
        self.decode = decode
        self._next = 0

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> FrameBatch:
        return self

    def __next__(self) -> tuple[str, np.ndarray | bytes]:
        if self._zip is None or self._next >= len(self.names):
            self.close()
            raise StopIteration
        name = self.names[self._next]
        self._next += 1
        data = self._zip.read(name)
        return name, (decode_image(data, self.output) if self.decode else data)

    def save(self, folder: str | os.PathLike) -> list[str]:
        """Write the remaining frames as the server encoded them, and index.json, into ``folder`` (each file
        atomically: temporary + rename). Returns the frame file names in order."""
        out = Path(folder)
        names = []
        decode, self.decode = self.decode, False
        try:
            for name, data in self:
                with atomic_file(out / name) as f:
                    f.write(data)
                names.append(name)
        finally:
            self.decode = decode
        with atomic_file(out / "index.json") as f:
            f.write((json.dumps(self.index, indent=1) + "\n").encode())
        return names

    def close(self) -> None:
        if self._zip is not None:
            self._zip.close()
            self._zip = None
        self._spool.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _FrameCounter:
    """Counts the frames of a batch zip as its bytes stream in. The server writes each frame (local file header
    PK\\x03\\x04 + name frame_NNNNN.ext + data) as soon as it is rendered; the header of the next expected name
    counts one frame. Reported to progress(frames, total)."""

    def __init__(self, total: int | None, progress: Progress | None):
        self.total, self.progress = total, progress
        self.reset()

    def reset(self, *_: Any) -> None:
        self.seen = 0
        self.tail = b""

    def feed(self, chunk: bytes) -> None:
        if self.progress is None:
            return
        buf = self.tail + chunk
        pos = 0
        while (i := buf.find(b"frame_%05d." % self.seen, pos)) >= 0:
            if i >= 30 and buf[i - 30:i - 26] == b"PK\x03\x04":
                self.seen += 1
                self.progress(self.seen, self.total)
            pos = i + 1
        self.tail = buf[max(pos, len(buf) - 64):]


# ----------------------------------------------------------------------------------------------- client

class Client:
    """The xyzcyl HTTP service from Python (module docstring; docs/client.md).

    base_url: the server (default $XYZCYL_SERVER, else http://127.0.0.1:8000); api_key: sent as
    ``Authorization: Bearer`` (default $XYZCYL_API_KEY); timeout: seconds per request (connect, read, write; a
    waiting POST adds its wait); retries: how many times a 429/503 (and a connection error of an idempotent call)
    is retried; retry_after_cap: the longest Retry-After honoured, seconds; http_client: an httpx.Client to use
    instead of one of our own (e.g. fastapi.testclient.TestClient(app)); base_url is then the client's."""

    def __init__(self, base_url: str | None = None, api_key: str | None = None, timeout: float = 60.0,
                 retries: int = 5, http_client: httpx.Client | None = None, retry_after_cap: float = 30.0):
        self.base_url = (base_url or os.environ.get("XYZCYL_SERVER") or DEFAULT_SERVER).rstrip("/")
        self.api_key = api_key if api_key is not None else (os.environ.get("XYZCYL_API_KEY") or None)
        self.timeout = float(timeout)
        self.retries = max(0, int(retries))
        self.retry_after_cap = float(retry_after_cap)
        self._owned = http_client is None
        self.http = http_client if http_client is not None else httpx.Client(
            base_url=self.base_url, timeout=self.timeout, follow_redirects=False)
        self.headers = {"User-Agent": USER_AGENT}
        if self.api_key:
            self.headers["Authorization"] = f"Bearer {self.api_key}"

    # -- plumbing ---------------------------------------------------------------------------------------------

    def close(self) -> None:
        if self._owned:
            self.http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self.base_url!r})"

    def _delay(self, resp: httpx.Response | None, attempt: int) -> float:
        after = _retry_after(resp) if resp is not None else None
        if after is None:
            after = min(_BACKOFF_CAP_S, _BACKOFF_S * 2 ** attempt)
        return min(after, self.retry_after_cap)

    def _send(self, method: str, path: str, *, params: Mapping[str, Any] | None = None, json_body: Any = None,
              content: Callable[[], Iterable[bytes]] | None = None, headers: Mapping[str, str] | None = None,
              stream: bool = False, idempotent: bool | None = None,
              timeout: httpx.Timeout | float | None = None) -> httpx.Response:
        """One call with the retries (module docstring). Returns a 2xx/3xx response (stream=True: open, the caller
        closes it); raises the XyzcylError of anything else."""
        idempotent = method.upper() in _IDEMPOTENT if idempotent is None else idempotent
        hdrs = {**self.headers, **(headers or {})}
        attempt = 0
        while True:
            try:
                req = self.http.build_request(method, path, params=params, json=json_body,
                                              content=content() if content is not None else None, headers=hdrs,
                                              timeout=timeout if timeout is not None else self.timeout)
                resp = self.http.send(req, stream=stream)
            except httpx.TransportError as e:
                if idempotent and attempt < self.retries:
                    _sleep(self._delay(None, attempt))
                    attempt += 1
                    continue
                raise self._connection_error(e, method, path) from e
            if resp.status_code in (429, 503) and attempt < self.retries:
                delay = self._delay(resp, attempt)
                resp.close()
                _sleep(delay)
                attempt += 1
                continue
            if resp.status_code >= 400:
                try:
                    resp.read()
                except httpx.TransportError:
                    pass
                finally:
                    resp.close()
                raise _error_from(resp)
            return resp

    def _connection_error(self, e: Exception, method: str, path: str) -> ConnectionFailed:
        code = "timeout" if isinstance(e, httpx.TimeoutException) else "connection_failed"
        what = "timed out" if code == "timeout" else "failed"
        detail = str(e) or type(e).__name__
        return ConnectionFailed(None, code, f"{method} {self.base_url}{path.split('?')[0]} {what}: {detail}",
                                "server")

    def _json(self, method: str, path: str, body: type[BaseModel], **kw) -> Any:
        """The answer's JSON, checked against its wire type ``body``."""
        return _answer(self._send(method, path, **kw), body, f"{method} {path}")

    def _download(self, method: str, path: str, sink: IO[bytes], *, on_chunk: Callable[[bytes], None] | None = None,
                  on_start: Callable[[httpx.Response], None] | None = None, idempotent: bool | None = None,
                  **kw) -> httpx.Response:
        """Stream an answer into ``sink`` (rewound and truncated before each try). A connection lost mid-stream
        starts the download again (idempotent calls, at most ``retries`` times)."""
        attempt = 0
        while True:
            sink.seek(0)
            sink.truncate()
            resp = self._send(method, path, stream=True, idempotent=idempotent, **kw)
            try:
                if on_start is not None:
                    on_start(resp)
                for chunk in resp.iter_bytes(_CHUNK):
                    sink.write(chunk)
                    if on_chunk is not None:
                        on_chunk(chunk)
                return resp
            except httpx.TransportError as e:
                if attempt >= self.retries or idempotent is False:
                    raise self._connection_error(e, method, path) from e
                _sleep(self._delay(None, attempt))
                attempt += 1
            finally:
                resp.close()

    # -- health -----------------------------------------------------------------------------------------------

    def ready(self) -> bool:
        """GET /v2/health/ready (no retries): True when the server takes reconstructions."""
        try:
            req = self.http.build_request("GET", "/v2/health/ready", headers=self.headers,
                                          timeout=min(self.timeout, 5.0))
            resp = self.http.send(req)
        except httpx.TransportError:
            return False
        return resp.status_code == 200

    # -- scenes -----------------------------------------------------------------------------------------------

    def reconstruct(self, rig: Any, images: Any = None, depths: Any = None, wait: bool = True,
                    timeout: float = 600.0, progress: Progress | None = None, lidar: Any = None,
                    detail_stride: int | None = None, detail: bool = True, ego_masks: Any = None,
                    name: str | None = None, keyframe_spacing: float | None = None,
                    keyframe_gap: float | None = None) -> SceneInfo:
        """POST /v1/scenes: upload a rig and its images; returns the scene.

        rig: a rig.json path, an xyzcyl.runtime.rig.Rig, or the rig's JSON as a dict; or a drive file's path
        (is_drive_file: a recorded drive, posted by reconstruct_drive with the files its frames name; images and
        ego_masks are then refused, depths={} and lidar=False leave those files out).
        images: None = the files the rig names (``image``), relative to rig.json's folder (a Rig: its root);
        else {camera name: file path (relative to the working folder) | encoded bytes | numpy array} (or a list in
        rig order). Arrays are sent as
        PNG (uint8 / uint16 as they are, floats 0..1 as 16-bit), RGB order.
        depths: None = the depth files the rig names (``depth``), if any; else as images, per camera, optional:
        a 16-bit PNG of millimetres or a float EXR of metres (uint16 arrays -> PNG mm, float arrays -> EXR m).
        ego_masks: None = the ego mask files the rig names (a camera's ``ego_mask``), if any; else as images, per
        camera, optional: a PNG or JPEG of the camera's size whose non-zero pixels are the ego's own body (hood,
        mirrors; no detail Gaussians there); arrays (bool or uint8/uint16) are sent as PNG. Sent as
        ``ego_mask:<camera>`` parts.
        lidar: None = the LiDAR file the rig's ``lidar`` block names, if any; False = none; else a file path or
        its bytes (.npy [N, >=3], or raw float32 .bin with the block's ``columns``; points in the frame the block's
        ``lidar_to_ego`` maps to ego, else ego). The server then makes each camera's depth from it.
        wait: hold the request with ?wait= then poll GET /v1/scenes/{id} until the scene is ready (returned) or
        failed (raised: InvalidRequestError for invalid_input, StorageFullError, ServerError for worker_crashed /
        timeout / interrupted), or ``timeout`` seconds pass (WaitTimeout). wait=False returns the queued scene.
        progress(sent bytes, total bytes) follows the upload.
        detail_stride: the detail layer's stride, 1..16 input pixels per detail Gaussian along each axis (None = the
        server's default, 2); detail=False: no detail layer (the model's Gaussians only; no detail_stride then).
        name: the scene's name (?name=, e.g. a simulator's scene id: the gRPC SensorsimService lists and resolves
        it; docs/simulators.md); the server checks it.
        keyframe_spacing, keyframe_gap: a drive's keyframes (reconstruct_drive); refused for a rig.
        Bad values raise InvalidArgumentError (a ValueError) naming the argument, before anything is sent."""
        if isinstance(rig, (str, os.PathLike)) and is_drive_file(rig):
            for arg, v in (("images", images), ("ego_masks", ego_masks)):
                if v is not None:
                    raise InvalidArgumentError(None, "invalid", f"{arg}: goes with a rig (a drive's frames name "
                                               "their files)", arg)
            if depths is not None and not (isinstance(depths, Mapping) and not depths):
                raise InvalidArgumentError(None, "invalid", "depths: a drive takes None (the files its frames "
                                           "name) or {} (none)", "depths")
            if lidar is not None and lidar is not False:
                raise InvalidArgumentError(None, "invalid", "lidar: a drive takes None (the sweeps its frames "
                                           "name) or False (none)", "lidar")
            return self.reconstruct_drive(rig, wait=wait, timeout=timeout, progress=progress, depths=depths is None,
                                          lidar=lidar is None, detail_stride=detail_stride, detail=detail,
                                          name=name, keyframe_spacing=keyframe_spacing, keyframe_gap=keyframe_gap)
        for arg, v in zip(wire.KEYFRAME_PARAMS, (keyframe_spacing, keyframe_gap), strict=True):
            if v is not None:
                raise InvalidArgumentError(None, "invalid", f"{arg}: goes with a drive file (a rig is one "
                                           "timestamp)", arg)
        query = _scene_params(detail_stride, detail, name)
        doc, root = _rig_document(rig)
        names = [c["name"] for c in doc["cameras"]]
        imgs = _by_camera(images, names, "images")
        dps = _by_camera(depths, names, "depths")
        masks = _by_camera(ego_masks, names, "ego_masks")
        parts = [_Part("rig", "rig.json", "application/json", data=json.dumps(doc, allow_nan=False).encode())]
        parts += _rig_parts(doc, root, imgs, dps, masks, lidar)
        return self._post_scene(parts, query, wait, timeout, progress)

    def reconstruct_drive(self, drive: str | os.PathLike | DriveUpload, wait: bool = True, timeout: float = 600.0,
                          progress: Progress | None = None, depths: bool = True, lidar: bool = True,
                          ego_masks: bool = True, detail_stride: int | None = None, detail: bool = True,
                          name: str | None = None, keyframe_spacing: float | None = None,
                          keyframe_gap: float | None = None, stationary_actors: bool = False) -> SceneInfo:
        """POST /v1/scenes with a recorded drive (docs/api.md "Drives"); returns the scene, whose ``drive`` says its
        frames and keyframes.

        drive: a drive file's path (docs/inference.md "Drives": {"frames": [{"rig": "frame_00/rig.json",
        "timestamp_s": ...}, ...], "tracks": "tracks.json"}), read by read_drive (its rigs and tracks sent inline,
        each frame's files as ``frames/<frame>/<name>`` parts), or what read_drive returned.
        depths, lidar, ego_masks: False leaves the frames' depth maps, LiDAR sweeps, ego masks out.
        keyframe_spacing (metres), keyframe_gap (seconds): the keyframes' spacing and longest gap (None: the
        server's defaults, 1.5 m and 2 s; `xyzcyl reconstruct --keyframe-spacing/--keyframe-gap`).
        stationary_actors: the tracks marked stationary (parked cars) become actors too (docs/api.md "Actors").
        wait, timeout, progress, detail_stride, detail, name: as reconstruct. The upload is one request: a failed or
        cut one is posted again whole."""
        if not isinstance(stationary_actors, bool):
            raise InvalidArgumentError(None, "invalid", f"stationary_actors: must be True or False (got "
                                                        f"{stationary_actors!r:.60})", "stationary_actors")
        query = _scene_params(detail_stride, detail, name) | _keyframe_params(keyframe_spacing, keyframe_gap)
        if stationary_actors:
            query["stationary_actors"] = "true"
        upload = drive if isinstance(drive, DriveUpload) else read_drive(drive, depths, lidar, ego_masks)
        return self._post_scene(upload.parts, query, wait, timeout, progress)

    def _post_scene(self, parts: list[_Part], query: dict[str, str], wait: bool, timeout: float,
                    progress: Progress | None) -> SceneInfo:
        """POST /v1/scenes with ``parts`` (streamed) and ``query``; then, with ``wait``, the scene once ready
        (reconstruct's docstring)."""
        body = _Multipart(parts)
        params = {"wait": f"{min(max(timeout, 0.0), _MAX_WAIT_QUERY):g}"} if wait else {}
        t0 = _monotonic()
        held = float(params["wait"]) if wait else 0.0
        params |= query
        resp = self._send("POST", "/v1/scenes", params=params or None, content=lambda: body.stream(progress),
                          headers=body.headers, idempotent=False,
                          timeout=httpx.Timeout(self.timeout, read=self.timeout + held))
        info = SceneInfo.from_json(_answer(resp, wire.SceneInfo, "POST /v1/scenes"))
        if not wait or info.ready:
            return info
        if info.failed:
            raise _failure(info)
        return self.wait(info.id, timeout=max(0.0, timeout - (_monotonic() - t0)))

    def wait(self, scene_id: str, timeout: float = 600.0, poll: float = 0.5) -> SceneInfo:
        """Poll GET /v1/scenes/{id} until the scene is ready (returned) or failed (raised, as reconstruct says);
        WaitTimeout after ``timeout`` seconds."""
        deadline = _monotonic() + timeout
        interval = poll
        while True:
            info = self.scene(scene_id)
            if info.ready:
                return info
            if info.failed:
                raise _failure(info)
            left = deadline - _monotonic()
            if left <= 0:
                raise WaitTimeout(None, "wait_timeout", f"scene {scene_id} is still {info.state} after {timeout:g} s",
                                  "id", scene_id=scene_id)
            _sleep(min(interval, left))
            interval = min(interval * 1.5, 2.0)

    def scene(self, scene_id: str) -> SceneInfo:
        """GET /v1/scenes/{id}."""
        return SceneInfo.from_json(self._json("GET", f"/v1/scenes/{_seg(scene_id)}", wire.SceneInfo))

    def scenes(self, page_size: int = 100) -> Iterator[SceneInfo]:
        """Every scene, newest first (GET /v1/scenes, page by page)."""
        offset, seen = 0, set()
        while True:
            page = self._json("GET", "/v1/scenes", wire.SceneList, params={"offset": offset, "limit": page_size})
            for d in page.get("scenes", []):
                if d["id"] not in seen:      # a scene posted meanwhile shifts the pages by one
                    seen.add(d["id"])
                    yield SceneInfo.from_json(d)
            offset += page_size
            if not page.get("next") or offset >= int(page.get("total", 0)):
                return

    def delete(self, scene_id: str) -> None:
        """DELETE /v1/scenes/{id} (NotFoundError when there is no such scene)."""
        self._send("DELETE", f"/v1/scenes/{_seg(scene_id)}").close()

    def gaussians(self, scene_id: str, path: str | os.PathLike, format: str | None = None,
                  progress: Progress | None = None) -> Path:
        """GET /v1/scenes/{id}/gaussians streamed into ``path`` (a temporary file beside it, renamed into place
        when complete). format: "ply" (3DGS binary PLY) or "splat" (antimatter15); default from the suffix
        (.splat, else ply). progress(received bytes, total or None). Returns the path."""
        path = Path(path)
        fmt = format or ("splat" if path.suffix.lower() == ".splat" else "ply")
        if fmt not in ("ply", "splat"):
            raise _invalid(f"must be ply or splat (got {fmt!r})", "format")
        with atomic_file(path) as f:
            self._stream_to(f, "GET", f"/v1/scenes/{_seg(scene_id)}/gaussians", {"format": fmt}, progress)
        return path

    def _stream_to(self, f: IO[bytes], method: str, path: str, params: Mapping[str, Any],
                   progress: Progress | None) -> None:
        state = {"n": 0, "total": None}

        def start(resp: httpx.Response) -> None:
            state["n"] = 0
            cl = resp.headers.get("content-length")
            state["total"] = int(cl) if cl and cl.isdigit() else None

        def chunk(b: bytes) -> None:
            state["n"] += len(b)
            if progress is not None:
                progress(state["n"], state["total"])

        self._download(method, path, f, params=params, on_start=start, on_chunk=chunk)

    # -- views ------------------------------------------------------------------------------------------------

    def render_bytes(self, scene_id: str, camera: Any, output: str = "rgb", format: str = "png",
                     width: int | None = None, height: int | None = None, quality: int | None = None,
                     move: Any = None, time: float | None = None, actors: Any = None) -> bytes:
        """GET /v1/scenes/{id}/render: the encoded view as the server sends it (PNG, JPEG or EXR bytes). camera:
        as view_params() describes (an input camera name, OpenCV K + cam_to_ego, or a CARLA pose + fov); move: a
        camera move (a CameraMove or {forward, left, up, yaw}; view_params); time: seconds on the rigs' clock (a
        drive's scene draws its moving objects then; None: the drive's first frame); actors: edits of a drive's
        actors for this view (a list of {"id", and one of "pose" (16 numbers, box -> scene frame), "offset"
        ([forward, left, up] metres from where it is then), "hide": True; "insert": a new id draws a copy}, or
        common.wire.ActorEdit; JSON text; docs/api.md "Actors"; the ids: actors())."""
        params = view_params(camera, width, height, move)
        if actors is not None:
            try:
                edits = wire.actor_edits(actors, "actors")
            except ViewError as e:
                raise InvalidArgumentError(None, "invalid", str(e), e.field) from None
            params["actors"] = json.dumps([e.wire() for e in edits], separators=(",", ":"))
        params.update(output=output, format=format)
        if quality is not None:
            params["quality"] = str(int(quality))
        if time is not None:
            if isinstance(time, bool) or not isinstance(time, (int, float)) or not math.isfinite(time):
                raise InvalidArgumentError(None, "invalid", f"time: must be a finite number of seconds (got "
                                                            f"{time!r:.60})", "time")
            params["time"] = repr(float(time))
        return self._send("GET", f"/v1/scenes/{_seg(scene_id)}/render", params=params).content

    def render(self, scene_id: str, camera: Any, output: str = "rgb", format: str = "png",
               width: int | None = None, height: int | None = None, quality: int | None = None,
               move: Any = None, time: float | None = None, actors: Any = None) -> np.ndarray:
        """One view as a float32 array (decode_image): rgb [H, W, 3] 0..1 RGB; depth [H, W] metres (0 = no
        surface; png saturates at 65.535 m, use format="exr" for float depth); alpha [H, W] 0..1. Arguments as
        render_bytes."""
        return decode_image(self.render_bytes(scene_id, camera, output, format, width, height, quality, move, time,
                                              actors), output)

    def actors(self, scene_id: str, time: float | None = None) -> wire.ActorList:
        """GET /v1/scenes/{id}/actors: a drive scene's actors (wire.ActorList: id, label, tracked, size, span_s,
        copies, gaussians; with ``time`` (seconds on the rigs' clock) each one's pose then, box -> scene frame)."""
        params = {}
        if time is not None:
            if isinstance(time, bool) or not isinstance(time, (int, float)) or not math.isfinite(time):
                raise InvalidArgumentError(None, "invalid", f"time: must be a finite number of seconds (got "
                                                            f"{time!r:.60})", "time")
            params["time"] = repr(float(time))
        doc = self._json("GET", f"/v1/scenes/{_seg(scene_id)}/actors", wire.ActorList, params=params)
        return wire.ActorList.model_validate(doc)

    def render_path(self, scene_id: str, camera_path: Any, output: str | None = None, format: str | None = None,
                    quality: int | None = None, decode: bool = True, progress: Progress | None = None) -> FrameBatch:
        """POST /v1/scenes/{id}/render: a batch of views. camera_path: a JSON file (a nerfstudio camera_path.json
        or {"cameras": [...]}), its dict, or a list of camera items (docs/api.md: {"K", "cam_to_ego", "width",
        "height"}, {"fov", ...}, CARLA sensors, {"camera": NAME}). The zip is spooled to a temporary file;
        returns a FrameBatch: iterate it for (file name, frame). progress(frames received, frames requested)."""
        if isinstance(camera_path, (str, os.PathLike)):
            try:
                doc = json.loads(Path(camera_path).read_text())
            except OSError as e:
                raise InvalidRequestError(None, "file_missing", f"cannot read {str(camera_path)!r}: "
                                          f"{e.strerror or e}", "camera_path") from None
            except ValueError as e:
                raise _invalid(f"{str(camera_path)!r} is not valid JSON ({e})", "camera_path") from None
        elif isinstance(camera_path, Mapping):
            doc = dict(camera_path)
        else:
            doc = {"cameras": list(camera_path)}
        frames = doc.get("cameras", doc.get("camera_path"))
        total = len(frames) if isinstance(frames, list) else None
        params = {k: v for k, v in (("output", output), ("format", format), ("quality", quality)) if v is not None}
        counter = _FrameCounter(total, progress)
        spool = tempfile.TemporaryFile(prefix="xyzcyl-frames-")  # noqa: SIM115 (the FrameBatch closes it)
        try:
            self._download("POST", f"/v1/scenes/{_seg(scene_id)}/render", spool, params=params, json_body=doc,
                           idempotent=True, on_start=counter.reset, on_chunk=counter.feed)
            spool.seek(0)
            return FrameBatch(spool, decode=decode)
        except BaseException:
            spool.close()
            raise


def _answer(resp: httpx.Response, body: type[BaseModel], what: str) -> Any:
    """The JSON of a 2xx answer, checked against its wire type ``body`` (ServerError ``bad_answer`` otherwise)."""
    try:
        doc = resp.json()
    except ValueError:
        raise ServerError(resp.status_code, "bad_answer", f"{what}: the answer is not JSON") from None
    try:
        body.model_validate(doc)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(x) for x in first["loc"]) or "body"
        raise ServerError(resp.status_code, "bad_answer", f"{what}: the answer is not a {body.__name__} ({where}: "
                          f"{first['msg']})") from None
    return doc


def _seg(scene_id: str) -> str:
    """A scene id as one path segment (ids are URL-safe; anything else is quoted and simply unknown)."""
    from urllib.parse import quote

    return quote(str(scene_id), safe="")


__all__ = ["AuthError", "BusyError", "Client", "ConnectionFailed", "DriveUpload", "FrameBatch",
           "InvalidArgumentError", "InvalidRequestError", "NotFoundError", "NotReadyError", "SceneInfo", "ServerError",
           "StorageFullError", "WaitTimeout", "XyzcylError", "decode_image", "encode_png", "error_for",
           "is_drive_file", "read_drive", "view_params"]
