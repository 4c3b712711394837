"""Camera rigs: the `rig.json` format, validation and image loading. A rig's cameras are runtime.camera.Camera
(the one camera type: conventions, projection and the validator live there; docs/conventions.md).

Every check raises `RigError` (runtime.errors) with ``where`` naming the camera (or 'rig') and ``field`` the field.
"""

from __future__ import annotations

import difflib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from .camera import CAMERA_KEYS, Camera, PicklableExtra, check_pose, look_rotation, where_camera
from .errors import CameraError, RigError

MAX_CAMERAS = 16

# Keys of rig.json (docs/conventions.md "rig.json"). A key a reader does not know is kept (Rig.extra /
# Camera.extra) and written back, unless it looks like a misspelling of one it reads (misspelt_key): "camras"
# would otherwise answer "cameras: must be a list", and "ego_to_wrld" would silently leave the scene unplaced.
RIG_KEYS = ("cameras", "lidar", "ego_to_world", "ego_to_global")        # read by runtime.lidar, Rig.ego_to_world
EGO_POSE_KEYS = ("ego_to_world", "ego_to_global")   # the ego pose: PandaSet conversions write the first, nuScenes the 2nd
RIG_CAMERA_KEYS = (*CAMERA_KEYS, "ego_mask")                           # ego_mask: runtime.detail
# keys that real and generated rigs carry on purpose (../shared/data/real, the synthetic generator, the
# converters' records): never taken for a misspelling, whatever they resemble
KEPT_RIG_KEYS = ("source", "license", "frame", "dataset", "timestamp_s", "sample_token", "seed", "scene_index",
                 "generator_version", "depth_sky_value")
KEPT_CAMERA_KEYS = ("timestamp_s", "cam_to_world", "virtual", "sky", "semantic")
CLOSE = 0.8             # difflib ratio from which an unknown key is a misspelling of a known one
CLOSE_MISSING = 0.6     # ... of a required key that is missing (the rig is refused anyway: name the likely cause)


def misspelt_key(d: Mapping[str, Any], known: Sequence[str], required: Sequence[str] = (),
                 kept: Sequence[str] = ()) -> tuple[str, str] | None:
    """The first key of ``d`` that is unknown (not in ``known`` nor ``kept``) and a likely misspelling of a known
    key, as (the key, the known key); None when there is none.

    Likely: a difflib similarity >= CLOSE to a known key, or >= CLOSE_MISSING to a ``required`` key that ``d``
    lacks. Compared case-insensitively ("k" is K). Keys that are neither are extras, kept as they are."""
    unknown = [k for k in d if isinstance(k, str) and k not in known and k not in kept]
    if not unknown:
        return None
    missing = [k for k in required if k not in d]
    for candidates, cutoff in ((known, CLOSE), (missing, CLOSE_MISSING)):
        lower = {k.lower(): k for k in candidates}
        for key in unknown:
            match = difflib.get_close_matches(key.lower(), list(lower), n=1, cutoff=cutoff)
            if match:
                return key, lower[match[0]]
    return None


def check_keys(d: Any, known: Sequence[str], required: Sequence[str], kept: Sequence[str], path: str,
               where: str | None) -> None:
    """RigError naming the field ``path`` + key when ``d`` (a rig.json object; anything else is left to its
    parser) has a misspelt key (misspelt_key): "camras: unknown key (did you mean 'cameras'?)"."""
    if not isinstance(d, Mapping):
        return
    hit = misspelt_key(d, known, required, kept)
    if hit is not None:
        key, meant = hit
        raise RigError(f"{path}{key}", f"unknown key (did you mean {meant!r}?)", where)


@dataclass(frozen=True, eq=False)
class Rig(PicklableExtra):
    """A set of 1..16 uniquely named cameras in one ego frame, plus the folder their files are relative to."""

    cameras: tuple[Camera, ...]
    root: Path | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)  # top-level keys, kept for the round trip
    # [4, 4] ego -> world, metres (rig.json "ego_to_world", or nuScenes' "ego_to_global"): where the ego stood (a
    # drive's world frame, a simulator's local frame: docs/simulators.md); None when the rig.json has none
    ego_to_world: np.ndarray | None = None

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if not 1 <= len(cams) <= MAX_CAMERAS:
            raise RigError("cameras", f"must have 1..{MAX_CAMERAS} entries (got {len(cams)})", "rig")
        seen: set[str] = set()
        for c in cams:
            if not isinstance(c, Camera):
                raise RigError("cameras", f"must be Camera objects (got {type(c).__name__})", "rig")
            if not c.name:
                raise RigError("name", "a rig's cameras need a name", "rig")
            if c.name in seen:
                raise RigError("name", "is a duplicate", c.where)
            seen.add(c.name)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "root", None if self.root is None else Path(self.root))
        object.__setattr__(self, "extra", MappingProxyType(dict(self.extra)))
        if self.ego_to_world is not None:
            pose = check_pose(self.ego_to_world, "rig", "ego_to_world")
            pose.setflags(write=False)
            object.__setattr__(self, "ego_to_world", pose)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def clockwise_order(self) -> list[int]:
        """Camera indices sorted clockwise seen from above by the optical axis' azimuth
        a = (-atan2(axis_y, axis_x)) mod 2 pi, starting at the camera whose axis is nearest ego forward; ties
        kept in rig order. This is the order the paper's F+ overlay assumes (nuScenes: FRONT, FRONT_RIGHT,
        BACK_RIGHT, BACK, BACK_LEFT, FRONT_LEFT)."""
        two_pi = 2.0 * math.pi
        cw = [(-math.atan2(c.rotation[1, 2], c.rotation[0, 2])) % two_pi for c in self.cameras]
        start = cw[min(range(len(cw)), key=lambda k: min(cw[k], two_pi - cw[k]))]
        return sorted(range(len(cw)), key=lambda k: (cw[k] - start) % two_pi)

    def reordered(self, order: Sequence[int]) -> Rig:
        """The same rig with its cameras in `order` (a permutation of camera indices)."""
        if sorted(order) != list(range(len(self.cameras))):
            raise RigError("order", f"must be a permutation of 0..{len(self.cameras) - 1} (got {list(order)})", "rig")
        return Rig(cameras=tuple(self.cameras[k] for k in order), root=self.root, extra=self.extra,
                   ego_to_world=self.ego_to_world)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], root: str | os.PathLike | None = None,
                  check_images: bool = False) -> Rig:
        """A rig from a rig.json object (docs/conventions.md "rig.json"); ``root``: the folder its files are relative
        to. RigError naming the field: a misspelt key first (check_keys: "camras", "cameras[0].cam_to_eg"), then
        the cameras (Camera.from_dict). Other unknown keys are kept (``extra``)."""
        if not isinstance(d, Mapping):
            raise RigError("rig", f"top level must be an object (got {type(d).__name__})")
        check_keys(d, RIG_KEYS, ("cameras",), KEPT_RIG_KEYS, "", "rig")
        cams = d.get("cameras")
        if not isinstance(cams, list):
            raise RigError("cameras", "must be a list", "rig")
        if not 1 <= len(cams) <= MAX_CAMERAS:
            raise RigError("cameras", f"must have 1..{MAX_CAMERAS} entries (got {len(cams)})", "rig")
        for i, c in enumerate(cams):
            if isinstance(c, Mapping):
                required = ("name", "width", "height", "cam_to_ego", *(("K",) if c.get("model", "pinhole") ==
                                                                        "pinhole" else ()))
                check_keys(c, RIG_CAMERA_KEYS, required, KEPT_CAMERA_KEYS, f"cameras[{i}].",
                           where_camera(c.get("name"), i))
        poses = [k for k in EGO_POSE_KEYS if k in d]
        ego = None
        if poses:
            try:
                ego = check_pose(d[poses[0]], "rig", poses[0])
            except CameraError as e:
                raise RigError(e.field, e.message, "rig") from None
        rig = cls(
            cameras=tuple(Camera.from_dict(c, i) for i, c in enumerate(cams)),
            root=None if root is None else Path(root),
            extra={k: v for k, v in d.items() if k != "cameras"},
            ego_to_world=ego,
        )
        if check_images:
            rig.check_images()
        return rig

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.extra)
        d["cameras"] = [c.to_dict() for c in self.cameras]
        return d

    def path(self, file: str) -> Path:
        """Resolve a file name of the rig (image, depth) against `root` (absolute names kept)."""
        p = Path(file)
        return p if p.is_absolute() or self.root is None else self.root / p

    def check_images(self) -> None:
        """Refuse a missing or unreadable image/depth file, or one whose size differs from the declared one.

        Reads only the file headers (OpenImageIO).
        """
        for c in self.cameras:
            for key in ("image", "depth"):
                name = getattr(c, key)
                if name is None:
                    continue
                w, h = image_size(self.path(name), key, where=c.where)
                if (w, h) != (c.width, c.height):
                    raise RigError(key, f"{name!r} is {w}x{h}, but width x height is "
                                   f"{c.width}x{c.height}", c.where)

    def load_images(self, native: bool = False) -> list[np.ndarray]:
        """Each camera's image as [H, W, 3] float32 RGB (8/16-bit scaled to 0..1; float files as stored); with
        ``native``, in its file's own type (decode_image: runtime.inference.as_rgb converts those in one pass)."""
        return [self.load_image(k, native) for k in range(len(self.cameras))]

    def load_image(self, k: int, native: bool = False) -> np.ndarray:
        """Camera k's image (load_images)."""
        c = self.cameras[k]
        if c.image is None:
            raise RigError("image", "is null, nothing to load", c.where)
        img = (decode_image if native else read_image)(self.path(c.image), "image", where=c.where)
        if img.shape[:2] != (c.height, c.width):
            raise RigError("image", f"is {img.shape[1]}x{img.shape[0]}, but width x height "
                           f"is {c.width}x{c.height}", c.where)
        return img

    def check_arrays(self, images: Sequence[np.ndarray], what: str = "image") -> None:
        """Refuse in-memory images (e.g. uploaded) that do not match the rig: one [H, W, C] (or [H, W]) array per
        camera, in rig order, of the declared size, with finite values."""
        if len(images) != len(self.cameras):
            raise RigError(f"{what}s", f"need {len(self.cameras)}, one per camera (got {len(images)})", "rig")
        for c, img in zip(self.cameras, images):
            a = np.asarray(img)
            if a.ndim not in (2, 3) or a.shape[:2] != (c.height, c.width):
                raise RigError(what, f"has shape {list(a.shape)}, but width x height is "
                               f"{c.width}x{c.height}", c.where)
            if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
                raise RigError(what, "has non-finite values", c.where)

    def load_depths(self) -> list[np.ndarray | None]:
        """Each camera's depth map [H, W] float32 metres (None where the camera has none)."""
        out: list[np.ndarray | None] = []
        for c in self.cameras:
            if c.depth is None:
                out.append(None)
                continue
            d = read_depth(self.path(c.depth), "depth", where=c.where)
            if d.shape != (c.height, c.width):
                raise RigError("depth", f"is {d.shape[1]}x{d.shape[0]}, but width x height "
                               f"is {c.width}x{c.height}", c.where)
            if not np.all(np.isfinite(d)):
                raise RigError("depth", "has non-finite values", c.where)
            out.append(d)
        return out


def load_rig(path: str | os.PathLike, check_images: bool = True) -> Rig:
    """Read and validate a rig.json; image/depth paths are relative to its folder."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise RigError("rig", f"cannot read {str(path)!r}: {exc.strerror or exc}") from exc
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RigError("rig", f"{str(path)!r} is not valid JSON ({exc.msg} at line {exc.lineno})") from exc
    return Rig.from_dict(d, root=path.parent, check_images=check_images)


def save_rig(rig: Rig, path: str | os.PathLike) -> None:
    """Write a rig.json (strict JSON: validated rigs hold no NaN/inf)."""
    Path(path).write_text(json.dumps(rig.to_dict(), indent=1, allow_nan=False) + "\n")


# -- image files -------------------------------------------------------------------------------------------------
#
# Every image the runtime reads (rig images, depth maps, ego masks, uploads) goes through _open_image and, for the
# pixels, _decode. ``what`` names the field in errors ("camera 'CAM_FRONT': image", "part 'CAM_FRONT'"); ``label``
# names the file after it (default: "file '<path>'"; the server passes e.g. "the image" so that no path of its store
# reaches a message).

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _label(path: Path, label: str | None) -> str:
    return f"file {str(path)!r}" if label is None else label


def _reason(text: str, path: Path) -> str:
    """A decoder's message as one line without the file's path: OpenImageIO appends ' ("<path>")' to libjpeg's
    messages and may return several lines (the first says what went wrong)."""
    p = str(path)
    line = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
    for s in {p, Path(p).name}:
        line = line.replace(f' ("{s}")', "").replace(f'"{s}"', "the file").replace(f"'{s}'", "the file")
    return line.replace(p, "the file")


def _why(reason: str) -> str:
    return f" ({reason})" if reason else ""


def _png_problem(path: Path, crc: bool) -> str | None:
    """Why a PNG file is broken in its chunk structure, or None (also for a file that is not a PNG). Walks the
    chunks (length, type, CRC) up to IEND: cut short, a chunk of an invalid type, IHDR's CRC (always) or, with
    ``crc``, any critical chunk's (IHDR, PLTE, IDAT, IEND; ancillary ones are libpng's to skip) not matching.
    Checked before libpng sees the file: libpng reports these by printing a stray 'libpng error: ...' line to
    stderr besides the error OpenImageIO returns (and a truncated PNG decodes nothing useful)."""
    import struct
    import zlib

    with open(path, "rb") as f:
        if f.read(8) != PNG_SIGNATURE:
            return None
        size = f.seek(0, 2)
        pos = 8
        while True:
            f.seek(pos)
            head = f.read(8)
            if len(head) < 8:
                return "the PNG ends before its IEND chunk"
            n, kind = struct.unpack(">I4s", head)
            if not kind.isalpha():
                return f"the PNG has a chunk of invalid type {kind.decode('latin-1')!r} at byte {pos}"
            name = kind.decode("ascii")
            if pos + 12 + n > size:
                return f"the PNG ends inside its {name} chunk"
            if kind == b"IHDR" or (crc and kind[:1].isupper()):
                c, left = zlib.crc32(kind), n
                while left:
                    block = f.read(min(left, 1 << 20))
                    c, left = zlib.crc32(block, c), left - len(block)
                if struct.unpack(">I", f.read(4))[0] != c & 0xFFFFFFFF:
                    return f"the PNG's {name} chunk fails its CRC"
            if kind == b"IEND":
                return None
            pos += 12 + n


def _jpeg_problem(path: Path) -> str | None:
    """Why a JPEG file is cut short, or None (also for a file that is not a JPEG). Its last scan must be followed by
    the end-of-image marker FF D9 (entropy-coded data never holds FF D9; bytes after the marker, a trailer some
    cameras append, are fine). libjpeg notices a missing end only when it needs bytes past the file's end: a file
    cut in its last few bytes can decode without a word."""
    import mmap

    with open(path, "rb") as f:
        if f.read(3) != b"\xff\xd8\xff":
            return None
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            sos = m.rfind(b"\xff\xda")
            if sos >= 0 and m.find(b"\xff\xd9", sos + 2) < 0:
                return "the JPEG ends before its end-of-image marker"
    return None


def image_size(path: Path, what: str, label: str | None = None, where: str | None = None) -> tuple[int, int]:
    """(width, height) from the file header (OpenImageIO; no pixel decoding). The file's structure is checked (a
    PNG's chunks, a JPEG's end marker), which finds most files cut short; read_image finds the rest."""
    inp = _open_image(path, what, label, where=where)
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def _open_image(path: Path, what: str, label: str | None = None, crc: bool = False, where: str | None = None):
    """An OpenImageIO ImageInput for `path` (caller closes it); RigError naming `what` if absent/unreadable."""
    import OpenImageIO as oiio

    if not Path(path).is_file():
        raise RigError(what, f"{_label(path, label)} does not exist", where)
    try:
        problem = _png_problem(path, crc) or _jpeg_problem(path)
    except OSError as exc:
        raise RigError(what, f"cannot read {_label(path, label)}{_why(exc.strerror or '')}", where) from None
    if problem is not None:
        raise RigError(what, f"{_label(path, label)} is cut short or corrupt ({problem})", where)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RigError(what, f"cannot read {_label(path, label)}{_why(_reason(oiio.geterror(), path))}", where)
    return inp


# libjpeg warnings about a file's metadata, not its pixels (such files decode whole; some cameras write them).
# OpenImageIO reports libjpeg's warnings as errors; any other one ("Premature end of JPEG file", "Corrupt JPEG
# data: ...") refuses the file.
_METADATA_WARNINGS = ("unknown JFIF revision number", "thumbnail image size does not match data length",
                      "Invalid SOS parameters for sequential JPEG", "Unknown Adobe color transform code",
                      "Corrupt JPEG data: bad ICC marker")


def _damage(problem: str) -> bool:
    """Whether a decoder's error text says the pixels are damaged (not just a metadata warning)."""
    return any(not any(w in line for w in _METADATA_WARNINGS) for line in problem.splitlines() if line.strip())


def _decode(path: Path, what: str, label: str | None = None, where: str | None = None) -> np.ndarray:
    """The pixels of an image file in the file's own type ([H, W] or [H, W, C]); RigError naming `what` when the
    file is missing, unreadable, cut short or corrupt. A cut JPEG "decodes" (libjpeg fills the rest with grey and
    only warns "Premature end of JPEG file"): a warning of the decoder about the pixels refuses the file."""
    inp = _open_image(path, what, label, crc=True, where=where)
    try:
        spec = inp.spec()
        # the file's own type (integers stay exact): without it OpenImageIO's Python read_image converts to float
        # and scales integers to 0..1, whatever `scale` says (a 16-bit depth PNG of 5000 mm read as 0.076)
        native = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
        problem = inp.geterror()
    finally:
        inp.close()
    if native is None or _damage(problem):
        raise RigError(what, f"{_label(path, label)} is cut short or corrupt"
                       f"{_why(_reason(problem, path) or 'the decoder returned no pixels')}", where)
    return np.asarray(native)


def verify_image(path: Path, what: str, label: str | None = None, where: str | None = None) -> None:
    """Decode an image file in full and drop the pixels: RigError (as read_image's) when it is cut short or
    corrupt. For checking an upload before a job is queued (read the header with image_size first: it refuses a
    decompression bomb without decoding)."""
    _decode(path, what, label, where)


def decode_image(path: Path, what: str, channels: int = 3, label: str | None = None,
                 where: str | None = None) -> np.ndarray:
    """An image file's pixels in the file's own type (uint8, uint16, float) as [H, W, channels] (RGB order; grey
    replicated, alpha dropped; possibly a view of the decoded array, not contiguous). RigError as read_image's."""
    a = _decode(path, what, label, where)
    if a.ndim == 2:
        a = a[..., None]
    n = a.shape[-1]
    if n >= channels:
        return a[..., :channels]
    if n == 1:
        return np.repeat(a, channels, axis=-1)
    raise RigError(what, f"{_label(path, label)} has {n} channels, expected {channels}", where)


def read_image(path: Path, what: str, channels: int = 3, scale: bool = True, label: str | None = None,
               where: str | None = None) -> np.ndarray:
    """Read an image file as float32 [H, W, channels] (RGB order; grey replicated, alpha dropped).

    Integer files are scaled to 0..1 when `scale` (8-bit /255, 16-bit /65535); float files (EXR, HDR) are
    returned as stored. Raises RigError naming `what` when the file is missing, unreadable, cut short or corrupt.
    """
    a = decode_image(path, what, channels, label, where)
    img = a.astype(np.float32)
    if scale and np.issubdtype(a.dtype, np.integer):
        img /= float(np.iinfo(a.dtype).max)
    return np.ascontiguousarray(img)


def read_depth(path: Path, what: str, label: str | None = None, where: str | None = None) -> np.ndarray:
    """A depth map file -> [H, W] float32 metres, the camera's depth (along the optical axis; along the pixel's ray
    for a fisheye or f-theta lens: Camera.depth_is_distance). Float files (EXR, TIFF) hold metres;
    integer files (16-bit PNG, the usual depth-camera export) hold millimetres (0 = no depth). RigError naming
    `what` when the file is missing or unreadable."""
    import OpenImageIO as oiio

    inp = _open_image(path, what, label, where=where)
    try:
        integer = inp.spec().format.basetype in (oiio.UINT8, oiio.UINT16, oiio.UINT32, oiio.INT16, oiio.INT32)
    finally:
        inp.close()
    d = read_image(path, what, channels=1, scale=False, label=label, where=where)[..., 0]
    return d * np.float32(0.001) if integer else d


def ring_rig(n: int = 6, hfov_deg: float = 70.0, width: int = 160, height: int = 90, ring_radius: float = 0.5,
             mount_height: float = 1.5, first_yaw_deg: float = 0.0, clockwise: bool = True) -> Rig:
    """A synthetic rig of n identical pinhole cameras on a horizontal ring, looking outwards.

    Camera k sits at ring_radius metres from (0, 0, mount_height) and looks at yaw first_yaw - k 360/n degrees
    (clockwise seen from above, the paper's F+ order) or + k 360/n (clockwise=False). Square pixels,
    principal point at the image centre ((W-1)/2, (H-1)/2). Names are "cam0".."cam{n-1}".
    """
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    cams = []
    for k in range(n):
        yaw = math.radians(first_yaw_deg + (-1 if clockwise else 1) * 360.0 * k / n)
        T = np.eye(4)
        T[:3, :3] = look_rotation(yaw)
        T[:3, 3] = [ring_radius * math.cos(yaw), ring_radius * math.sin(yaw), mount_height]
        cams.append(Camera(name=f"cam{k}", width=width, height=height, K=K, cam_to_ego=T))
    return Rig(cameras=tuple(cams))
