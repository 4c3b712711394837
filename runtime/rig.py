"""Camera rigs: the `rig.json` format, validation, projection and image loading.

Conventions (docs/conventions.md is the full statement):
- ego frame: x forward, y left, z up, metres;
- camera frame: OpenCV, x right, y down, z forward; `cam_to_ego` [4, 4] maps camera points to ego points;
- `K` in pixels, OpenCV: the centre of pixel column u is at x = u, the image spans [-0.5, W-0.5];
- equirectangular cameras: column -> azimuth about the camera's up axis (centre column = camera +z, columns grow
  towards camera +x), row 0 = zenith (camera -y), last row = nadir; their `K` is optional and unused.

Every check raises `RigError` with a message that names the camera and the field.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal

import numpy as np

from .rotations import ORTHO_TOL  # max |R^T R - I| entry accepted for a pose's rotation (the renderer's too)

MAX_CAMERAS = 16
MAX_SIZE = 16384
# K's structural zeros and ones and cam_to_ego's bottom row are compared with this absolute tolerance: JSON
# written by float code can carry 1e-16-level round-off, anything larger is a real (refused) parameter.
STRUCT_TOL = 1e-9
DISTORTION_LENGTHS = (4, 5, 8)  # OpenCV radial-tangential models (k1 k2 p1 p2 [k3 [k4 k5 k6]])
CAMERA_KEYS = ("name", "image", "width", "height", "K", "cam_to_ego", "distortion", "model", "depth")
MODELS = ("pinhole", "equirectangular")
IN_FRONT_EPS = 1e-6  # metres: a point needs camera z (pinhole) / distance (equirect) above this to project

CameraModel = Literal["pinhole", "equirectangular"]


class RigError(ValueError):
    """Invalid rig or camera. The message always names the camera (or 'rig') and the field."""


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


def _where(name: str | None, index: int | None = None) -> str:
    if name:
        return f"camera {name!r}"
    return f"camera #{index}" if index is not None else "camera"


@dataclass(frozen=True, eq=False)
class Camera:
    """One camera of a rig. Arrays are stored as read-only float64 copies; construction validates."""

    name: str
    width: int  # pixels
    height: int  # pixels
    K: np.ndarray | None  # [3, 3] pixels, OpenCV; required for pinhole, optional (unused) for equirectangular
    cam_to_ego: np.ndarray  # [4, 4] OpenCV camera (x right, y down, z fwd) -> ego (x fwd, y left, z up), metres
    model: CameraModel = "pinhole"
    distortion: tuple[float, ...] | None = None  # OpenCV k1 k2 p1 p2 [k3 [k4 k5 k6]]; None = undistorted
    image: str | None = None  # file relative to Rig.root
    depth: str | None = None  # optional depth map file: float metres or 16-bit millimetres, optical axis (pinhole)
    extra: Mapping[str, Any] = field(default_factory=dict)  # unknown keys, kept for the round trip

    def __post_init__(self) -> None:
        where = _where(self.name)
        if not isinstance(self.name, str) or not self.name:
            raise RigError(f"{where}: name must be a non-empty string")
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise RigError(f"{where}: {key} must be an integer (got {plain(v)!r})")
            if not 0 < int(v) <= MAX_SIZE:
                raise RigError(f"{where}: {key} must be in 1..{MAX_SIZE} (got {v})")
            object.__setattr__(self, key, int(v))
        if self.model not in MODELS:
            raise RigError(f"{where}: model must be one of {MODELS} (got {self.model!r})")
        if self.K is None:
            if self.model == "pinhole":
                raise RigError(f"{where}: K is required for a pinhole camera")
        else:
            object.__setattr__(self, "K", _freeze(_check_K(self.K, where)))
        object.__setattr__(self, "cam_to_ego", _freeze(_check_pose(self.cam_to_ego, where)))
        if self.distortion is not None:
            if self.model != "pinhole":
                raise RigError(f"{where}: distortion must be null for an equirectangular camera")
            d = _numbers(self.distortion, where, "distortion")
            if d.ndim != 1 or len(d) not in DISTORTION_LENGTHS:
                raise RigError(f"{where}: distortion must have {DISTORTION_LENGTHS} coefficients (got {d.shape})")
            object.__setattr__(self, "distortion", tuple(float(x) for x in d) if np.any(d) else None)
        for key in ("image", "depth"):
            v = getattr(self, key)
            if v is not None and (not isinstance(v, str) or not v):
                raise RigError(f"{where}: {key} must be a non-empty string or null (got {v!r})")
        object.__setattr__(self, "extra", MappingProxyType(dict(self.extra)))

    # -- geometry -------------------------------------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        """[3] camera centre, ego frame, metres."""
        return self.cam_to_ego[:3, 3]

    @property
    def rotation(self) -> np.ndarray:
        """[3, 3] camera-to-ego rotation (columns: camera x, y, z axes in ego)."""
        return self.cam_to_ego[:3, :3]

    @property
    def ego_to_cam(self) -> np.ndarray:
        """[4, 4] inverse of cam_to_ego (exact rigid inverse)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation.T
        out[:3, 3] = -self.rotation.T @ self.position
        return out

    @property
    def vertical_fov(self) -> float:
        """Vertical field of view, radians: 2*atan(H / (2 fy)) for pinhole, pi for equirectangular."""
        if self.model == "equirectangular":
            return math.pi
        return 2.0 * math.atan(self.height / (2.0 * self.K[1, 1]))

    @property
    def horizontal_fov(self) -> float:
        """Horizontal field of view, radians: 2*atan(W / (2 fx)) for pinhole, 2 pi for equirectangular."""
        if self.model == "equirectangular":
            return 2.0 * math.pi
        return 2.0 * math.atan(self.width / (2.0 * self.K[0, 0]))

    def project(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project ego points into the image.

        points_ego: [..., 3] metres, ego frame.
        Returns uv [..., 2] pixels (OpenCV: pixel u's centre at u), z [...] metres (camera-frame z for pinhole,
        distance from the camera centre for equirectangular), in_front [...] bool (z > 1e-6 m). uv of points
        not in front is finite but meaningless. Bounds are not checked (see `inside`).
        """
        p = np.asarray(points_ego, dtype=np.float64)
        q = (p - self.position) @ self.rotation  # camera frame: R^T (p - t) for row vectors
        if self.model == "equirectangular":
            uv, dist = _equirect_project(q, self.width, self.height)
            return uv, dist, dist > IN_FRONT_EPS
        z = q[..., 2]
        in_front = z > IN_FRONT_EPS
        zs = np.where(in_front, z, 1.0)
        x, y = q[..., 0] / zs, q[..., 1] / zs
        if self.distortion is not None:
            x, y = _distort(x, y, self.distortion)
        K = self.K
        uv = np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1)
        return uv, z, in_front

    def inside(self, uv: np.ndarray) -> np.ndarray:
        """[...] bool: uv [..., 2] within the image area [-0.5, W-0.5] x [-0.5, H-0.5] (pixel edges)."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_rays(self, uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel positions, ego frame.

        uv: [..., 2] OpenCV pixel coordinates; default all pixel centres, shape [H, W, 2].
        Returns origins [..., 3] (the camera centre) and unit directions [..., 3], both ego frame. For a
        pinhole camera, direction = normalise(R @ inv(K) @ [u, v, 1]) (distortion removed with OpenCV).
        """
        if uv is None:
            vv, uu = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
            uv = np.stack([uu, vv], axis=-1).astype(np.float64)
        uv = np.asarray(uv, dtype=np.float64)
        if self.model == "equirectangular":
            d = _equirect_dirs(uv, self.width, self.height)
        else:
            K = self.K
            if self.distortion is not None:
                import cv2

                flat = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, np.asarray(self.distortion)).reshape(uv.shape)
                x, y = flat[..., 0], flat[..., 1]
            else:
                x = (uv[..., 0] - K[0, 2]) / K[0, 0]
                y = (uv[..., 1] - K[1, 2]) / K[1, 1]
            d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d = d @ self.rotation.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.position, d.shape).copy(), d

    def replace(self, **changes: Any) -> Camera:
        """A copy with some fields changed (validated again)."""
        kw = {k: getattr(self, k) for k in self.__dataclass_fields__}
        kw.update(changes)
        return Camera(**kw)

    # -- JSON -----------------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], index: int | None = None) -> Camera:
        """Parse one `cameras[]` entry of rig.json (see docs/conventions.md). Unknown keys go to `extra`."""
        if not isinstance(d, Mapping):
            raise RigError(f"{_where(None, index)}: entry must be an object (got {type(d).__name__})")
        name = d.get("name")
        where = _where(name if isinstance(name, str) else None, index)
        if not isinstance(name, str) or not name:
            raise RigError(f"{where}: name must be a non-empty string (got {name!r})")
        for key in ("width", "height", "cam_to_ego"):
            if key not in d:
                raise RigError(f"{where}: {key} is missing")
        model = d.get("model", "pinhole")
        K = d.get("K")
        if K is None and model == "pinhole":
            raise RigError(f"{where}: K is missing")
        return cls(
            name=name,
            width=d["width"],
            height=d["height"],
            K=None if K is None else _numbers(K, where, "K"),
            cam_to_ego=_numbers(d["cam_to_ego"], where, "cam_to_ego"),
            model=model,
            distortion=d.get("distortion"),
            image=d.get("image"),
            depth=d.get("depth"),
            extra={k: v for k, v in d.items() if k not in CAMERA_KEYS},
        )

    def resized(self, width: int, height: int) -> Camera:
        """The same camera imaging at ``width`` x ``height`` pixels (an image resampled to that size). With the
        OpenCV pixel-centre convention (column u spans [u - 1/2, u + 1/2]) a scale s = width / self.width maps
        u -> s (u + 1/2) - 1/2: fx' = s fx, cx' = s (cx + 1/2) - 1/2 (likewise v, fy, cy with height). Distortion
        acts on normalised coordinates and stays; an equirectangular camera needs no K. Files are dropped (the
        caller resamples the arrays)."""
        K = None
        if self.K is not None:
            sx, sy = width / self.width, height / self.height
            K = self.K.copy()
            K[0, 0], K[0, 2] = sx * K[0, 0], sx * (K[0, 2] + 0.5) - 0.5
            K[1, 1], K[1, 2] = sy * K[1, 1], sy * (K[1, 2] + 0.5) - 0.5
        return Camera(name=self.name, width=width, height=height, K=K, cam_to_ego=self.cam_to_ego,
                      model=self.model, distortion=self.distortion, extra=dict(self.extra))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name}
        if self.image is not None:
            d["image"] = self.image
        d.update(width=self.width, height=self.height)
        if self.K is not None:
            d["K"] = self.K.tolist()
        d["cam_to_ego"] = self.cam_to_ego.tolist()
        d["distortion"] = None if self.distortion is None else list(self.distortion)
        if self.model != "pinhole":
            d["model"] = self.model
        if self.depth is not None:
            d["depth"] = self.depth
        d.update(self.extra)
        return d


@dataclass(frozen=True, eq=False)
class Rig:
    """A set of 1..16 uniquely named cameras in one ego frame, plus the folder their files are relative to."""

    cameras: tuple[Camera, ...]
    root: Path | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)  # top-level keys, kept for the round trip

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if not 1 <= len(cams) <= MAX_CAMERAS:
            raise RigError(f"rig: cameras must have 1..{MAX_CAMERAS} entries (got {len(cams)})")
        seen: set[str] = set()
        for c in cams:
            if not isinstance(c, Camera):
                raise RigError(f"rig: cameras must be Camera objects (got {type(c).__name__})")
            if c.name in seen:
                raise RigError(f"camera {c.name!r}: name is a duplicate")
            seen.add(c.name)
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "root", None if self.root is None else Path(self.root))
        object.__setattr__(self, "extra", MappingProxyType(dict(self.extra)))

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
            raise RigError(f"rig: order must be a permutation of 0..{len(self.cameras) - 1} (got {list(order)})")
        return Rig(cameras=tuple(self.cameras[k] for k in order), root=self.root, extra=self.extra)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], root: str | os.PathLike | None = None,
                  check_images: bool = False) -> Rig:
        if not isinstance(d, Mapping):
            raise RigError(f"rig: top level must be an object (got {type(d).__name__})")
        cams = d.get("cameras")
        if not isinstance(cams, list):
            raise RigError("rig: cameras must be a list")
        if not 1 <= len(cams) <= MAX_CAMERAS:
            raise RigError(f"rig: cameras must have 1..{MAX_CAMERAS} entries (got {len(cams)})")
        rig = cls(
            cameras=tuple(Camera.from_dict(c, i) for i, c in enumerate(cams)),
            root=None if root is None else Path(root),
            extra={k: v for k, v in d.items() if k != "cameras"},
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
                w, h = image_size(self.path(name), f"camera {c.name!r}: {key}")
                if (w, h) != (c.width, c.height):
                    raise RigError(f"camera {c.name!r}: {key} {name!r} is {w}x{h}, but width x height is "
                                   f"{c.width}x{c.height}")

    def load_images(self) -> list[np.ndarray]:
        """Each camera's image as [H, W, 3] float32 RGB (8/16-bit scaled to 0..1; float files as stored)."""
        out = []
        for c in self.cameras:
            if c.image is None:
                raise RigError(f"camera {c.name!r}: image is null, nothing to load")
            img = read_image(self.path(c.image), f"camera {c.name!r}: image")
            if img.shape[:2] != (c.height, c.width):
                raise RigError(f"camera {c.name!r}: image is {img.shape[1]}x{img.shape[0]}, but width x height "
                               f"is {c.width}x{c.height}")
            out.append(img)
        return out

    def check_arrays(self, images: Sequence[np.ndarray], what: str = "image") -> None:
        """Refuse in-memory images (e.g. uploaded) that do not match the rig: one [H, W, C] (or [H, W]) array per
        camera, in rig order, of the declared size, with finite values."""
        if len(images) != len(self.cameras):
            raise RigError(f"rig: {what}s: need {len(self.cameras)}, one per camera (got {len(images)})")
        for c, img in zip(self.cameras, images):
            a = np.asarray(img)
            if a.ndim not in (2, 3) or a.shape[:2] != (c.height, c.width):
                raise RigError(f"camera {c.name!r}: {what} has shape {list(a.shape)}, but width x height is "
                               f"{c.width}x{c.height}")
            if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
                raise RigError(f"camera {c.name!r}: {what} has non-finite values")

    def load_depths(self) -> list[np.ndarray | None]:
        """Each camera's depth map [H, W] float32 metres (None where the camera has none)."""
        out: list[np.ndarray | None] = []
        for c in self.cameras:
            if c.depth is None:
                out.append(None)
                continue
            d = read_depth(self.path(c.depth), f"camera {c.name!r}: depth")
            if d.shape != (c.height, c.width):
                raise RigError(f"camera {c.name!r}: depth is {d.shape[1]}x{d.shape[0]}, but width x height "
                               f"is {c.width}x{c.height}")
            if not np.all(np.isfinite(d)):
                raise RigError(f"camera {c.name!r}: depth has non-finite values")
            out.append(d)
        return out


def load_rig(path: str | os.PathLike, check_images: bool = True) -> Rig:
    """Read and validate a rig.json; image/depth paths are relative to its folder."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise RigError(f"rig: cannot read {str(path)!r}: {exc.strerror or exc}") from exc
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RigError(f"rig: {str(path)!r} is not valid JSON ({exc.msg} at line {exc.lineno})") from exc
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


def image_size(path: Path, what: str, label: str | None = None) -> tuple[int, int]:
    """(width, height) from the file header (OpenImageIO; no pixel decoding). The file's structure is checked (a
    PNG's chunks, a JPEG's end marker), which finds most files cut short; read_image finds the rest."""
    inp = _open_image(path, what, label)
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def _open_image(path: Path, what: str, label: str | None = None, crc: bool = False):
    """An OpenImageIO ImageInput for `path` (caller closes it); RigError naming `what` if absent/unreadable."""
    import OpenImageIO as oiio

    if not Path(path).is_file():
        raise RigError(f"{what}: {_label(path, label)} does not exist")
    try:
        problem = _png_problem(path, crc) or _jpeg_problem(path)
    except OSError as exc:
        raise RigError(f"{what}: cannot read {_label(path, label)}{_why(exc.strerror or '')}") from None
    if problem is not None:
        raise RigError(f"{what}: {_label(path, label)} is cut short or corrupt ({problem})")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RigError(f"{what}: cannot read {_label(path, label)}{_why(_reason(oiio.geterror(), path))}")
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


def _decode(path: Path, what: str, label: str | None = None) -> np.ndarray:
    """The pixels of an image file in the file's own type ([H, W] or [H, W, C]); RigError naming `what` when the
    file is missing, unreadable, cut short or corrupt. A cut JPEG "decodes" (libjpeg fills the rest with grey and
    only warns "Premature end of JPEG file"): a warning of the decoder about the pixels refuses the file."""
    inp = _open_image(path, what, label, crc=True)
    try:
        spec = inp.spec()
        # the file's own type (integers stay exact): without it OpenImageIO's Python read_image converts to float
        # and scales integers to 0..1, whatever `scale` says (a 16-bit depth PNG of 5000 mm read as 0.076)
        native = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
        problem = inp.geterror()
    finally:
        inp.close()
    if native is None or _damage(problem):
        raise RigError(f"{what}: {_label(path, label)} is cut short or corrupt"
                       f"{_why(_reason(problem, path) or 'the decoder returned no pixels')}")
    return np.asarray(native)


def verify_image(path: Path, what: str, label: str | None = None) -> None:
    """Decode an image file in full and drop the pixels: RigError (as read_image's) when it is cut short or
    corrupt. For checking an upload before a job is queued (read the header with image_size first: it refuses a
    decompression bomb without decoding)."""
    _decode(path, what, label)


def read_image(path: Path, what: str, channels: int = 3, scale: bool = True, label: str | None = None) -> np.ndarray:
    """Read an image file as float32 [H, W, channels] (RGB order; grey replicated, alpha dropped).

    Integer files are scaled to 0..1 when `scale` (8-bit /255, 16-bit /65535); float files (EXR, HDR) are
    returned as stored. Raises RigError naming `what` when the file is missing, unreadable, cut short or corrupt.
    """
    a = _decode(path, what, label)
    if a.ndim == 2:
        a = a[..., None]
    if np.issubdtype(a.dtype, np.integer):
        img = a.astype(np.float32)
        if scale:
            img /= float(np.iinfo(a.dtype).max)
    else:
        img = a.astype(np.float32)
    n = img.shape[-1]
    if n >= channels:
        img = img[..., :channels]
    elif n == 1:
        img = np.repeat(img, channels, axis=-1)
    else:
        raise RigError(f"{what}: {_label(path, label)} has {n} channels, expected {channels}")
    return np.ascontiguousarray(img)


def read_depth(path: Path, what: str, label: str | None = None) -> np.ndarray:
    """A depth map file -> [H, W] float32 metres along the optical axis. Float files (EXR, TIFF) hold metres;
    integer files (16-bit PNG, the usual depth-camera export) hold millimetres (0 = no depth). RigError naming
    `what` when the file is missing or unreadable."""
    import OpenImageIO as oiio

    inp = _open_image(path, what, label)
    try:
        integer = inp.spec().format.basetype in (oiio.UINT8, oiio.UINT16, oiio.UINT32, oiio.INT16, oiio.INT32)
    finally:
        inp.close()
    d = read_image(path, what, channels=1, scale=False, label=label)[..., 0]
    return d * np.float32(0.001) if integer else d


# -- validation helpers ------------------------------------------------------------------------------------------

def plain(value: Any) -> Any:
    """``value`` for an error message's ``{...!r}``: numpy scalars and arrays as plain Python numbers and lists
    (numpy 2 writes a scalar as ``np.float64(-633.0)``); anything else unchanged. The validators' one place for it."""
    return value.tolist() if isinstance(value, (np.generic, np.ndarray)) else value


def _numbers(value: Any, where: str, key: str) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{where}: {key} must be numbers (got {plain(value)!r:.80})") from None
    if not np.all(np.isfinite(a)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0]) if a.ndim else ()
        idx = "".join(f"[{i}]" for i in bad)
        raise RigError(f"{where}: {key}{idx} is not finite")
    return a


def _check_K(K: Any, where: str) -> np.ndarray:
    K = _numbers(K, where, "K")
    if K.shape != (3, 3):
        raise RigError(f"{where}: K must be 3x3 (got shape {K.shape})")
    for (r, c), want in {(0, 1): 0.0, (1, 0): 0.0, (2, 0): 0.0, (2, 1): 0.0, (2, 2): 1.0}.items():
        if abs(K[r, c] - want) > STRUCT_TOL:
            raise RigError(f"{where}: K[{r}][{c}] must be {want:g} (got {plain(K[r, c])!r})")
    if not K[0, 0] > 0:
        raise RigError(f"{where}: K[0][0] (fx) must be > 0 (got {plain(K[0, 0])!r})")
    if not K[1, 1] > 0:
        raise RigError(f"{where}: K[1][1] (fy) must be > 0 (got {plain(K[1, 1])!r})")
    K = K.copy()
    K[0, 1] = K[1, 0] = K[2, 0] = K[2, 1] = 0.0
    K[2, 2] = 1.0
    return K


def _check_pose(T: Any, where: str, key: str = "cam_to_ego") -> np.ndarray:
    """A validated rigid 4x4 transform (``key`` names the field in errors: cam_to_ego, lidar_to_ego)."""
    T = _numbers(T, where, key)
    if T.shape != (4, 4):
        raise RigError(f"{where}: {key} must be 4x4 (got shape {T.shape})")
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > STRUCT_TOL:
        raise RigError(f"{where}: {key} bottom row must be [0, 0, 0, 1] (got {T[3].tolist()})")
    R = T[:3, :3]
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ORTHO_TOL:
        raise RigError(f"{where}: {key} rotation is not orthonormal (max |R^T R - I| = {err:.3g} > "
                       f"{ORTHO_TOL})")
    det = float(np.linalg.det(R))
    if det < 0:
        raise RigError(f"{where}: {key} rotation has det {det:.4f}, must be +1 (a reflection)")
    T = T.copy()
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


# -- projection models -------------------------------------------------------------------------------------------

def _distort(x: np.ndarray, y: np.ndarray, d: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV radial-tangential distortion of normalised coordinates (same formula as cv2.projectPoints)."""
    k1, k2, p1, p2 = d[:4]
    k3 = d[4] if len(d) > 4 else 0.0
    k4, k5, k6 = d[5:8] if len(d) > 5 else (0.0, 0.0, 0.0)
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _equirect_dist(q: np.ndarray) -> np.ndarray:
    return np.linalg.norm(q, axis=-1)


def _equirect_project(q: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [..., 3] -> (uv [..., 2], distance [...]).

    azimuth lon = atan2(x, z) in (-pi, pi] (0 = optical axis, + to the right); polar angle from the up axis
    (camera -y) colat = acos(-y / |q|) in [0, pi]. u = (lon / 2pi + 1/2) W - 1/2, v = (colat / pi) H - 1/2, so
    the image's outer pixel edges are lon = -pi/+pi and the zenith/nadir.
    """
    dist = _equirect_dist(q)
    lon = np.arctan2(q[..., 0], q[..., 2])
    colat = np.arccos(np.clip(-q[..., 1] / np.where(dist > 0, dist, 1.0), -1.0, 1.0))
    uv = np.stack([(lon / (2 * np.pi) + 0.5) * width - 0.5, colat / np.pi * height - 0.5], axis=-1)
    return uv, dist


def _equirect_dirs(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Inverse of _equirect_project: pixel coordinates [..., 2] -> unit camera-frame directions [..., 3]."""
    lon = ((uv[..., 0] + 0.5) / width - 0.5) * 2 * np.pi
    colat = (uv[..., 1] + 0.5) / height * np.pi
    s = np.sin(colat)
    return np.stack([s * np.sin(lon), -np.cos(colat), s * np.cos(lon)], axis=-1)


def look_rotation(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """[3, 3] cam_to_ego rotation of an upright OpenCV camera looking at ego azimuth `yaw` (radians, 0 = ego
    forward, counter-clockwise positive seen from above) and elevation `pitch` (radians, + looks up)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    fwd = np.array([cp * cy, cp * sy, sp])
    right = np.array([sy, -cy, 0.0])
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd], axis=1)


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
