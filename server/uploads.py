"""The upload of POST /v1/scenes: the multipart form's parts checked and written into a work folder as rig.json and
files whose names are ours (never the request's), for a reconstruction worker to read. Each image, depth map and
ego mask is checked against the rig (size, the pixel limit) and decoded once in full (a file cut short or corrupt
is refused, naming its part); a LiDAR sweep is read once. Errors are 415 / 422 naming the part."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from starlette.datastructures import UploadFile
from xyzcyl.common.media import SNIFF_BYTES, sniff
from xyzcyl.runtime.rig import Rig, RigError, image_size, save_rig, verify_image

from .errors import Invalid, UnsupportedMedia
from .settings import Settings

RIG_PART_BYTES = 1 << 20          # a rig.json of 16 cameras is ~10 kB; 1 MiB is plenty
_PART_TYPES = ("image/png", "image/jpeg", "image/x-exr", "image/exr", "image/tiff", "application/octet-stream")
_CHUNK = 1 << 20


def _save_part(part: UploadFile, field: str, dest_stem: Path) -> Path:
    ctype = (part.content_type or "application/octet-stream").split(";")[0].strip().lower()
    if ctype not in _PART_TYPES:
        raise UnsupportedMedia(f"part {field!r}: media type {ctype!r} is not one of {', '.join(_PART_TYPES)}",
                               field)
    part.file.seek(0)
    media = sniff(part.file.read(SNIFF_BYTES))
    if media is None:
        raise UnsupportedMedia(f"part {field!r}: not a PNG, JPEG, EXR or TIFF file", field)
    path = dest_stem.with_suffix(media.suffix)
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


def _lidar_label(part: UploadFile) -> str:
    """How messages name the 'lidar' part: by the client's file name (its last component, at most 100 characters),
    never by the store's path."""
    name = Path(part.filename or "").name[:100]
    return f"part 'lidar' (file {name!r})" if name else "part 'lidar'"


def _ingest_lidar(form, rig: Rig, work: Path) -> dict | None:
    """The optional 'lidar' part (a sweep of the same timestamp: .npy [N, >=3] or raw float32 .bin, in the frame
    of the rig's lidar block's lidar_to_ego, else ego) written to ``work`` and read once to validate it
    (runtime.lidar.read_points, the command line's check). Its format is the client's file name's
    (runtime.lidar.lidar_format: .npy must be one; .bin / .pcd.bin raw float32 unless the bytes start with the .npy
    magic; any other name or none: by the bytes); the saved file's name is ours. Returns the rig's lidar block for
    the saved file, or without a file when there is no part, or None when the rig has neither."""
    from xyzcyl.runtime.lidar import NPY_MAGIC, LidarError, lidar_format, load_lidar

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
    name = "lidar." + lidar_format(part.filename or "", part.file.read(len(NPY_MAGIC)), sniff=True)
    part.file.seek(0)
    with open(work / name, "wb") as f:
        shutil.copyfileobj(part.file, f, _CHUNK)
    block["file"] = name
    label = _lidar_label(part)
    try:
        load_lidar(Rig(cameras=rig.cameras, root=work, extra={"lidar": block}), label=label)
    except LidarError as e:
        # the file as a whole (field "lidar", no ``where``): the message names it by ``label`` already
        whole_file = e.field == "lidar" and e.where is None
        raise Invalid(e.message if whole_file else f"part 'lidar': {e}", "lidar") from None
    return block


def ingest(form, work: Path, st: Settings, model_input: dict[str, Any]) -> Rig:
    """Validate the multipart form and write rig.json + the parts into ``work`` (file names are ours, never
    the request's). ``st``: the limits; ``model_input``: the model's input block (its max_cameras). Returns the rig
    as written."""
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
    # the ego's pose in the world (a simulator's local frame: docs/simulators.md), Rig.ego_to_world: checked by
    # Rig.from_dict above, so a bad one is refused at the upload, not at the first simulator render
    limit = min(st.max_cameras, int(model_input.get("max_cameras", st.max_cameras)))
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


__all__ = ["RIG_PART_BYTES", "ingest"]
