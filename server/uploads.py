"""The upload of POST /v1/scenes: the multipart form's parts checked and written into a work folder as rig.json and
files whose names are ours (never the request's), for a reconstruction worker to read. Each image, depth map and
ego mask is checked against the rig (size, the pixel limit) and decoded once in full (a file cut short or corrupt
is refused, naming its part); a LiDAR sweep is read once. Errors are 415 / 422 naming the part.

A recorded drive (docs/api.md "Drives") comes as a 'drive' part, the drive document with each frame's rig inline
and the tracks inline, and each frame's parts named as a rig's with the prefix ``frames/<frame>/``
(common.wire.frame_part). Every frame's rig and parts go through the same checks as one rig's (``_Frame`` says how
a rig's parts and fields are named); the drive is written as runtime.drive reads it (drive.json, frame_NNN/rig.json
and its files, tracks.json) and checked by runtime.drive.load_drive before any file part is read, its refusals
(DriveError) answered as 422 naming the drive part's field ("drive.frames[3].timestamp_s")."""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.datastructures import UploadFile
from xyzcyl.common.media import SNIFF_BYTES, sniff
from xyzcyl.common.wire import DRIVE_PART, FRAME_PARTS, frame_part
from xyzcyl.runtime.rig import Rig, RigError, image_size, save_rig, verify_image

from .errors import Invalid, UnsupportedMedia
from .settings import Settings

RIG_PART_BYTES = 1 << 20          # a rig.json of 16 cameras is ~10 kB; 1 MiB is plenty
DRIVE_PART_BYTES = 32 << 20       # a drive document: 200 frames' rigs inline (~7 kB each) and the tracks (the
#                                   PandaSet drive's 40 frames and 94 tracks: 0.6 MB)
_PART_TYPES = ("image/png", "image/jpeg", "image/x-exr", "image/exr", "image/tiff", "application/octet-stream")
_CHUNK = 1 << 20


@dataclass(frozen=True)
class _Frame:
    """How one rig of an upload is named: the prefix of its parts ("" for one rig, "frames/3/" for a drive's frame
    3), its JSON field ("rig", "drive.frames[3].rig") and the words its messages start with."""

    prefix: str = ""
    field: str = "rig"
    label: str = "rig"
    index: int | None = None

    @classmethod
    def of_drive(cls, i: int) -> _Frame:
        return cls(frame_part(i, ""), f"drive.frames[{i}].rig", f"drive: frames[{i}].rig", i)

    def part(self, name: str) -> str:
        return self.prefix + name

    def names(self, rig: Rig) -> set[str]:
        """The names of the parts this rig may have besides its rig: an image per camera, depth and ego mask
        parts, the LiDAR sweep."""
        out = {self.part("lidar")}
        for c in rig.names:
            out |= {self.part(c), self.part(f"depth:{c}"), self.part(f"ego_mask:{c}")}
        return out


_ONE_RIG = _Frame()


@dataclass(frozen=True)
class Upload:
    """What ``ingest`` wrote into the work folder: ``path`` the file the worker reads (rig.json, or drive.json for
    a drive), ``rig`` the rig (a drive's first frame's), ``drive`` the runtime.drive.Drive of a drive (its frames'
    times and poses, its tracks), None for one rig."""

    path: str
    rig: Rig
    drive: Any = None


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


def _ingest_ego_mask(part, cam, dest_stem: Path, max_pixels: int, frame: _Frame = _ONE_RIG) -> str:
    """An 'ego_mask:<camera>' part (PNG 8/16-bit, any channels, or JPEG; non-zero = the ego's own body) saved as
    ``dest_stem`` + its type's suffix and decoded once in full (_check_image: the decoder the worker's
    runtime.detail.read_ego_mask reads it with). Returns the saved file's name for the rig's camera ``ego_mask``."""
    field = frame.part(f"ego_mask:{cam.name}")
    if not isinstance(part, UploadFile):
        raise Invalid(f"part {field!r} must be a file part (a PNG or JPEG mask)", field)
    path = _save_part(part, field, dest_stem)
    if path.suffix not in (".png", ".jpg"):
        raise UnsupportedMedia(f"part {field!r}: an ego mask must be a PNG or JPEG, not {path.suffix[1:].upper()}",
                               field)
    _check_image(path, field, cam, max_pixels, "the ego mask")      # size, then a full decode (cut or corrupt)
    return path.name


def _lidar_label(part: UploadFile, field: str = "lidar") -> str:
    """How messages name the 'lidar' part (``field``: its name): by the client's file name (its last component, at
    most 100 characters), never by the store's path."""
    name = Path(part.filename or "").name[:100]
    return f"part {field!r} (file {name!r})" if name else f"part {field!r}"


def _ingest_lidar(form, rig: Rig, work: Path, frame: _Frame = _ONE_RIG) -> dict | None:
    """The optional 'lidar' part (a sweep of the same timestamp: .npy [N, >=3] or raw float32 .bin, in the frame
    of the rig's lidar block's lidar_to_ego, else ego) written to ``work`` and read once to validate it
    (runtime.lidar.read_points, the command line's check). Its format is the client's file name's
    (runtime.lidar.lidar_format: .npy must be one; .bin / .pcd.bin raw float32 unless the bytes start with the .npy
    magic; any other name or none: by the bytes); the saved file's name is ours. Returns the rig's lidar block for
    the saved file, or without a file when there is no part, or None when the rig has neither."""
    from xyzcyl.runtime.lidar import NPY_MAGIC, LidarError, lidar_format, load_lidar

    block = rig.extra.get("lidar")
    if block is not None and not isinstance(block, dict):
        raise Invalid(f"{frame.label}: lidar must be an object (got {type(block).__name__})", f"{frame.field}.lidar")
    block = {k: v for k, v in (block or {}).items() if k != "file"}
    field = frame.part("lidar")
    part = form.get(field)
    if part is None:
        return block or None
    if not isinstance(part, UploadFile):
        raise Invalid(f"part {field!r} must be a file part (.npy or float32 .bin)", field)
    ctype = (part.content_type or "application/octet-stream").split(";")[0].strip().lower()
    if ctype not in ("application/octet-stream", "application/x-npy"):
        raise UnsupportedMedia(f"part {field!r}: media type {ctype!r} is not application/octet-stream or "
                               "application/x-npy", field)
    part.file.seek(0)
    name = "lidar." + lidar_format(part.filename or "", part.file.read(len(NPY_MAGIC)), sniff=True)
    part.file.seek(0)
    with open(work / name, "wb") as f:
        shutil.copyfileobj(part.file, f, _CHUNK)
    block["file"] = name
    label = _lidar_label(part, field)
    try:
        load_lidar(Rig(cameras=rig.cameras, root=work, extra={"lidar": block}), label=label)
    except LidarError as e:
        # the file as a whole (field "lidar", no ``where``): the message names it by ``label`` already
        whole_file = e.field == "lidar" and e.where is None
        raise Invalid(e.message if whole_file else f"part {field!r}: {e}", field) from None
    return block


def _json_part(form, name: str, limit: int) -> Any:
    """The JSON document of the part ``name`` (a file part or a field), at most ``limit`` bytes; Invalid naming
    it otherwise."""
    part = form.get(name)
    if isinstance(part, UploadFile):
        part.file.seek(0)
        raw = part.file.read(limit + 1)
    else:
        raw = part.encode()
    if len(raw) > limit:
        raise Invalid(f"the {name!r} part is over {limit} bytes", name)
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        raise Invalid(f"{name}: not valid JSON ({e})", name) from None


def _rig_of(doc: Any, st: Settings, model_input: dict[str, Any], frame: _Frame = _ONE_RIG) -> Rig:
    """The rig of a rig.json document (the 'rig' part, or a drive frame's inline rig): the camera limits (the
    server's max_cameras, the model's) and runtime.rig's checks; Invalid naming ``frame``'s field."""
    what = "" if frame.index is None else f"{frame.label}: "
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list) and len(doc["cameras"]) > st.max_cameras:
        raise Invalid(f"{frame.label}: {len(doc['cameras'])} cameras, more than the limit of {st.max_cameras}",
                      f"{frame.field}.cameras")
    try:
        rig = Rig.from_dict(doc)
    except RigError as e:
        raise Invalid(f"{what}{e}", frame.field) from None      # its message names the rig or camera, and the field
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise Invalid(f"{frame.label}: {type(e).__name__}: {e}", frame.field) from None
    # the ego's pose in the world (a simulator's local frame: docs/simulators.md), Rig.ego_to_world: checked by
    # Rig.from_dict above, so a bad one is refused at the upload, not at the first simulator render
    limit = min(st.max_cameras, int(model_input.get("max_cameras", st.max_cameras)))
    if len(rig.cameras) > limit:
        raise Invalid(f"{frame.label}: {len(rig.cameras)} cameras, more than the limit of {limit}",
                      f"{frame.field}.cameras")
    return rig


def _check_part_names(form, allowed: set[str], unknown) -> None:
    """Invalid for a part given twice, or (``unknown(key)``: its Invalid) for one not in ``allowed``."""
    seen: set[str] = set()
    for key, _ in form.multi_items():
        if key in seen:
            raise Invalid(f"part {key!r} appears more than once", key)
        seen.add(key)
        if key not in allowed:
            raise unknown(key)


def _ingest_files(form, rig: Rig, work: Path, st: Settings, frame: _Frame = _ONE_RIG) -> Rig:
    """The file parts of one rig (``frame`` names them: an image per camera, optional depth and ego mask parts and a
    LiDAR sweep) checked and written into ``work`` under our names; returns the rig naming them (not yet
    saved)."""
    cams = []
    for i, cam in enumerate(rig.cameras):
        field = frame.part(cam.name)
        part = form.get(field)
        if part is None:
            if frame.index is None:
                raise Invalid(f"no image part for camera {cam.name!r} (one part per camera, named by the camera)",
                              field)
            raise Invalid(f"no image part {field!r} for camera {cam.name!r} of frame {frame.index} (one part per "
                          f"camera and frame, named '{FRAME_PARTS}<frame>/<camera>')", field)
        if not isinstance(part, UploadFile):
            raise Invalid(f"part {field!r} must be a file part (an image)", field)
        img = _save_part(part, field, work / f"image_{i:02d}")
        _check_image(img, field, cam, st.max_image_pixels, "the image")
        depth = None
        dfield = frame.part(f"depth:{cam.name}")
        dpart = form.get(dfield)
        if dpart is not None:
            if not isinstance(dpart, UploadFile):
                raise Invalid(f"part {dfield!r} must be a file part (16-bit PNG mm or float EXR m)", dfield)
            if cam.model != "pinhole":
                raise Invalid(f"part {dfield!r}: depth is supported for pinhole cameras only", dfield)
            dpath = _save_part(dpart, dfield, work / f"depth_{i:02d}")
            if dpath.suffix == ".jpg":
                raise UnsupportedMedia(f"part {dfield!r}: depth must be a 16-bit PNG (millimetres) or a float EXR "
                                       "(metres), not JPEG", dfield)
            _check_image(dpath, dfield, cam, st.max_image_pixels, "the depth map")
            depth = dpath.name
        # like depth, a rig's own ego_mask file name is not used (the file is not here): only an uploaded part
        extra = {k: v for k, v in cam.extra.items() if k != "ego_mask"}
        mpart = form.get(frame.part(f"ego_mask:{cam.name}"))
        if mpart is not None:
            extra["ego_mask"] = _ingest_ego_mask(mpart, cam, work / f"ego_mask_{i:02d}", st.max_image_pixels, frame)
        cams.append(cam.replace(image=img.name, depth=depth, extra=extra))
    extra = {k: v for k, v in rig.extra.items() if k != "lidar"}
    lidar = _ingest_lidar(form, rig, work, frame)
    if lidar is not None:
        extra["lidar"] = lidar
    return Rig(cameras=tuple(cams), extra=extra)


def _calibration(rig: Rig) -> Rig:
    """``rig`` without the request's file names (images, depth, ego masks, the LiDAR sweep): what runtime.drive's
    checks read before the files are in."""
    cams = tuple(c.replace(image=None, depth=None, extra={k: v for k, v in c.extra.items() if k != "ego_mask"})
                 for c in rig.cameras)
    extra = dict(rig.extra)
    if isinstance(extra.get("lidar"), dict):
        extra["lidar"] = {k: v for k, v in extra["lidar"].items() if k != "file"}
    return Rig(cameras=cams, extra=extra)


def _frame_dir(i: int) -> str:
    return f"frame_{i:03d}"


def _ingest_drive(form, work: Path, st: Settings, model_input: dict[str, Any]) -> Upload:
    """A drive upload (module docstring): the drive document and every frame's rig first, then runtime.drive's
    checks of the drive as written (before any file part is read), then every frame's files."""
    from xyzcyl.runtime.drive import DriveError, load_drive

    doc = _json_part(form, DRIVE_PART, DRIVE_PART_BYTES)
    if not isinstance(doc, dict):
        raise Invalid('drive: must be a JSON object {"frames": [...], "tracks": [...]}', DRIVE_PART)
    items = doc.get("frames")
    if not isinstance(items, list) or not items:
        raise Invalid('drive: frames: must be a non-empty list of {"rig": {... rig.json ...}, "timestamp_s": ...}',
                      "drive.frames")
    if len(items) > st.max_drive_frames:
        raise Invalid(f"drive: frames: {len(items)} frames, more than the limit of {st.max_drive_frames}",
                      "drive.frames")
    frames = [_Frame.of_drive(i) for i in range(len(items))]
    rigs = []
    for item, fr in zip(items, frames):
        if not isinstance(item, dict) or not isinstance(item.get("rig"), dict):
            raise Invalid(f"{fr.label}: must be the frame's rig.json inline (an object; file names are not read)",
                          fr.field)
        rigs.append(_rig_of(item["rig"], st, model_input, fr))
    # the drive as runtime.drive reads it, calibration only so far: its checks before any file part is read
    entries = []
    for i, (item, rig) in enumerate(zip(items, rigs)):
        (work / _frame_dir(i)).mkdir()
        save_rig(_calibration(rig), work / _frame_dir(i) / "rig.json")
        entry = {"rig": f"{_frame_dir(i)}/rig.json"}
        if "timestamp_s" in item:
            entry["timestamp_s"] = item["timestamp_s"]
        entries.append(entry)
    out: dict[str, Any] = {"frames": entries}
    tracks = doc.get("tracks")
    if tracks is not None:
        if not isinstance(tracks, (list, dict)):
            raise Invalid('drive: tracks: must be the tracks inline (a list of objects, or {"tracks": [...]}); '
                          "file names are not read", "drive.tracks")
        (work / "tracks.json").write_text(json.dumps(tracks))
        out["tracks"] = "tracks.json"
    (work / "drive.json").write_text(json.dumps(out, indent=1))
    try:
        drive = load_drive(work / "drive.json", check_images=False)
    except DriveError as e:        # its ``where`` is our work folder, and a rig is named by our file name
        message = re.sub(r"\bframe_\d+/rig\.json\b", "its rig", e.message)
        raise Invalid(f"drive: {e.field}: {message}", f"drive.{e.field}") from None
    n = len(items)
    if not math.isfinite(drive.frames[-1].timestamp_s - drive.frames[0].timestamp_s):     # e.g. -1e308 .. 1e308
        raise Invalid(f"drive: frames[{n - 1}].timestamp_s: the drive's span from frames[0] is not a finite number "
                      "of seconds", f"drive.frames[{n - 1}].timestamp_s")
    allowed = {DRIVE_PART}
    for rig, fr in zip(rigs, frames):
        allowed |= fr.names(rig)

    def unknown(key: str) -> Invalid:
        head, _, rest = key[len(FRAME_PARTS):].partition("/")
        if not key.startswith(FRAME_PARTS) or not rest:
            return Invalid(f"part {key!r} is not a part of a drive upload ('drive', and per frame "
                           f"'{FRAME_PARTS}<frame>/<camera>', '.../depth:<camera>', '.../ego_mask:<camera>', "
                           "'.../lidar')", key)
        if not (head.isdigit() and str(int(head)) == head and int(head) < n):
            return Invalid(f"part {key!r} names no frame of the drive (frames 0..{n - 1}, written without leading "
                           "zeros)", key)
        i = int(head)
        return Invalid(f"part {key!r} names no camera of frame {i}'s rig (cameras: {', '.join(rigs[i].names)}; "
                       f"depth parts are named '{frame_part(i, 'depth:<camera>')}', ego masks "
                       f"'{frame_part(i, 'ego_mask:<camera>')}', a LiDAR sweep '{frame_part(i, 'lidar')}')", key)

    _check_part_names(form, allowed, unknown)
    written = []
    for rig, fr, i in zip(rigs, frames, range(n)):
        written.append(_ingest_files(form, rig, work / _frame_dir(i), st, fr))
        save_rig(written[-1], work / _frame_dir(i) / "rig.json")
    return Upload("drive.json", written[0], drive)


def ingest(form, work: Path, st: Settings, model_input: dict[str, Any]) -> Upload:
    """Validate the multipart form and write rig.json + the parts into ``work`` (file names are ours, never
    the request's), or a drive (a 'drive' part: module docstring). ``st``: the limits; ``model_input``: the model's
    input block (its max_cameras). Returns what was written."""
    if form.get(DRIVE_PART) is not None:
        if form.get("rig") is not None:
            raise Invalid("give a 'rig' part (one timestamp) or a 'drive' part (a recorded drive), not both",
                          DRIVE_PART)
        return _ingest_drive(form, work, st, model_input)
    if form.get("rig") is None:
        raise Invalid("the 'rig' part (rig.json) is missing (or a 'drive' part, for a recorded drive)", "rig")
    rig = _rig_of(_json_part(form, "rig", RIG_PART_BYTES), st, model_input)

    def unknown(key: str) -> Invalid:
        return Invalid(f"part {key!r} names no camera of the rig (cameras: {', '.join(rig.names)}; depth parts are "
                       "named 'depth:<camera>', ego masks 'ego_mask:<camera>', a LiDAR sweep 'lidar')", key)

    _check_part_names(form, {"rig", *_ONE_RIG.names(rig)}, unknown)
    out = _ingest_files(form, rig, work, st)
    save_rig(out, work / "rig.json")
    return Upload("rig.json", out)


__all__ = ["DRIVE_PART_BYTES", "RIG_PART_BYTES", "Upload", "ingest"]
