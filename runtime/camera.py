"""The one camera type of the runtime: input cameras of a rig, render cameras, the views and the converters all
use `Camera`, validated by one validator.

Conventions (docs/conventions.md is the full statement):
- ego frame: x forward, y left, z up, metres. A scene's frame is the ego frame of the rig it was reconstructed
  from, so a render pose is a `cam_to_ego` too (the one name of the pose: camera -> ego);
- camera frame: OpenCV, x right, y down, z forward; `cam_to_ego` [4, 4] maps camera points to ego points;
- `K` in pixels, OpenCV: the centre of pixel column u is at x = u, the image spans [-0.5, W-0.5];
- models: "pinhole" (any camera with K: an ideal pinhole, or a real lens in `distortion`, a `runtime.lenses.Lens`:
  "opencv" (rational, tangential, thin prism), "opencv_fisheye" or "ftheta") and "equirectangular" (a full 360x180
  panorama: column -> azimuth about the camera's up axis, centre column = camera +z, columns grow towards camera
  +x; row 0 = zenith (camera -y), last row = nadir; `K` optional and unused). `Camera.lens_model` names the five.

Every check raises `CameraError(field, message, where)`: ``field`` is the camera field at fault ("K[0][0]",
"cam_to_ego", "width", "distortion[1]", "distortion.max_angle_deg", ...), ``where`` names the camera
("camera 'CAM_FRONT'") when it has a name.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

import numpy as np
from xyzcyl.common.poses import STRUCT_TOL, PoseError, pose_matrix
from xyzcyl.common.wire import MAX_RENDER_PIXELS, MAX_SIZE, render_limit

from .errors import CameraError, plain
from .lenses import IN_FRONT_EPS, Lens, project, unproject
from .rotations import ORTHO_TOL  # max |R^T R - I| entry accepted for a pose's rotation

CAMERA_KEYS = ("name", "image", "width", "height", "K", "cam_to_ego", "distortion", "model", "depth")
MODELS = ("pinhole", "equirectangular")

CameraModel = Literal["pinhole", "equirectangular"]


def where_camera(name: Any, index: int | None = None) -> str | None:
    """How messages name a camera: "camera 'CAM_FRONT'", "camera #2", or None for an anonymous render camera."""
    if isinstance(name, str) and name:
        return f"camera {name!r}"
    return f"camera #{index}" if index is not None else None


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


class PicklableExtra:
    """Pickling for a frozen dataclass whose ``extra`` is a read-only MappingProxyType (which pickle refuses): sent
    as a dict and wrapped again (a drive's frames go to keyframe worker processes, runtime.drive)."""

    def __getstate__(self) -> dict:
        return {**self.__dict__, "extra": dict(self.extra)}

    def __setstate__(self, state: dict) -> None:
        for key, value in state.items():
            object.__setattr__(self, key, value)
        object.__setattr__(self, "extra", MappingProxyType(dict(state["extra"])))


@dataclass(frozen=True, eq=False, kw_only=True)
class Camera(PicklableExtra):
    """One camera. Arrays are stored as read-only float64 copies; construction validates every field.

    Keyword-only: ``Camera(K=K, cam_to_ego=T, width=1600, height=900)`` (a pinhole render camera),
    ``Camera(model="equirectangular", cam_to_ego=T, width=2048, height=1024)``, a camera with a lens
    (``distortion=(k1, k2, p1, p2)`` or ``{"model": "opencv_fisheye", "k1": ..., "max_angle_deg": 95}``), or a rig
    entry with its name and files."""

    width: int  # pixels
    height: int  # pixels
    cam_to_ego: np.ndarray  # [4, 4] OpenCV camera (x right, y down, z fwd) -> ego (x fwd, y left, z up), metres
    K: np.ndarray | None = None  # [3, 3] pixels, OpenCV; required for pinhole, optional (unused) for equirectangular
    model: CameraModel = "pinhole"
    # the lens (pinhole model only): None = ideal pinhole. Given as a Lens, OpenCV's distCoeffs list (k1 k2 p1 p2
    # [k3 [k4 k5 k6 [s1 s2 s3 s4]]]; all zero = None) or rig.json's {"model": ...} object; stored as a Lens
    distortion: Lens | None = None
    name: str | None = None  # a rig camera's name (unique in its rig); None for a render camera
    image: str | None = None  # file relative to Rig.root
    depth: str | None = None  # optional depth map file: float metres or 16-bit millimetres, optical axis (pinhole)
    extra: Mapping[str, Any] = field(default_factory=dict)  # unknown rig.json keys, kept for the round trip

    def __post_init__(self) -> None:
        where = where_camera(self.name)
        if self.name is not None and (not isinstance(self.name, str) or not self.name):
            raise CameraError("name", f"must be a non-empty string (got {plain(self.name)!r})", where)
        for key in ("width", "height"):
            object.__setattr__(self, key, check_size(getattr(self, key), key, where))
        if self.model not in MODELS:
            raise CameraError("model", f"must be one of {MODELS} (got {self.model!r})", where)
        if self.K is None:
            if self.model == "pinhole":
                raise CameraError("K", "is required for a pinhole camera", where)
        else:
            object.__setattr__(self, "K", _freeze(check_K(self.K, where)))
        object.__setattr__(self, "cam_to_ego", _freeze(check_pose(self.cam_to_ego, where)))
        if self.distortion is not None:
            if self.model != "pinhole":
                raise CameraError("distortion", "must be null for an equirectangular camera", where)
            try:
                object.__setattr__(self, "distortion", Lens.from_json(self.distortion))
            except CameraError as e:
                raise CameraError(e.field, e.message, where) from None
        for key in ("image", "depth"):
            v = getattr(self, key)
            if v is not None and (not isinstance(v, str) or not v):
                raise CameraError(key, f"must be a non-empty string or null (got {v!r})", where)
        object.__setattr__(self, "extra", MappingProxyType(dict(self.extra)))

    # -- geometry -------------------------------------------------------------------------------------------
    @property
    def where(self) -> str | None:
        """How messages name this camera ("camera 'CAM_FRONT'"), None without a name."""
        return where_camera(self.name)

    @property
    def is_equirect(self) -> bool:
        return self.model == "equirectangular"

    @property
    def is_ideal(self) -> bool:
        """No lens: an ideal pinhole or an equirectangular camera (the same as ``distortion is None``)."""
        return self.distortion is None

    @property
    def lens_model(self) -> str:
        """"pinhole" (ideal), "opencv", "opencv_fisheye", "ftheta" or "equirectangular"."""
        return self.distortion.model if self.distortion is not None else self.model

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
        """Vertical field of view, radians: 2*atan(H / (2 fy)) for pinhole (an opencv lens ignored), pi for
        equirectangular; with a fisheye or f-theta lens the angles from the optical axis of the rays through the
        top and bottom edges' points at u = cx, added (max_angle where the edge lies beyond the image circle)."""
        if self.is_equirect:
            return math.pi
        if self.distortion is not None and self.distortion.model != "opencv":
            cx = self.K[0, 2]
            return self._edge_angles([[cx, -0.5], [cx, self.height - 0.5]])
        return 2.0 * math.atan(self.height / (2.0 * self.K[1, 1]))

    @property
    def horizontal_fov(self) -> float:
        """Horizontal field of view, radians: 2*atan(W / (2 fx)) for pinhole (an opencv lens ignored), 2 pi for
        equirectangular; fisheye and f-theta: as vertical_fov through the left and right edges at v = cy."""
        if self.is_equirect:
            return 2.0 * math.pi
        if self.distortion is not None and self.distortion.model != "opencv":
            cy = self.K[1, 2]
            return self._edge_angles([[-0.5, cy], [self.width - 0.5, cy]])
        return 2.0 * math.atan(self.width / (2.0 * self.K[0, 0]))

    def _edge_angles(self, uv: list[list[float]]) -> float:
        d, valid = unproject(self.K, self.distortion, np.array(uv, np.float64))
        theta = np.where(valid, np.arccos(np.clip(d[:, 2], -1.0, 1.0)), self.distortion.max_angle)
        return float(theta.sum())

    @property
    def depth_is_distance(self) -> bool:
        """Whether this camera's depth is the distance from its centre along the pixel's ray (equirectangular and
        a fisheye or f-theta lens: cameras that can image at or beyond 90 degrees from the axis, where camera z is
        0 or negative) rather than camera z (an ideal pinhole, an opencv lens). Depth maps of the camera (files,
        LiDAR, the network's depth head, the detail layer) hold this depth (docs/conventions.md "Depth")."""
        return self.is_equirect or (self.distortion is not None and self.distortion.images_beyond_90)

    @property
    def paraxial_focal(self) -> tuple[float, float]:
        """(fx, fy) pixels per radian at the optical axis: K's for an ideal pinhole, the lens's
        (Lens.paraxial_focal) otherwise; W / 2pi and H / pi for equirectangular."""
        if self.is_equirect:
            return self.width / (2.0 * math.pi), self.height / math.pi
        if self.distortion is None:
            return float(self.K[0, 0]), float(self.K[1, 1])
        return self.distortion.paraxial_focal(self.K)

    def project_depth(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`project` with the camera's depth (depth_is_distance: the distance from the camera centre, else camera
        z): (uv [..., 2], depth [...], in_front [...])."""
        uv, z, front = self.project(points_ego)
        if self.depth_is_distance and not self.is_equirect:
            z = np.linalg.norm(np.asarray(points_ego, np.float64) - self.position, axis=-1)
        return uv, z, front

    def depth_rays(self, uv: np.ndarray | None = None) -> np.ndarray:
        """[..., 3] camera-frame vectors r with point = depth * r for a pixel's point at the camera's depth
        (project_depth): unit rays when depth_is_distance, else the ray scaled to z = 1. uv: [..., 2] pixels,
        default all pixel centres [H, W, 2]. NaN for pixels no ray reaches."""
        if uv is None:
            vv, uu = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
            uv = np.stack([uu, vv], axis=-1).astype(np.float64)
        uv = np.asarray(uv, dtype=np.float64)
        d = _equirect_dirs(uv, self.width, self.height) if self.is_equirect else \
            unproject(self.K, self.distortion, uv)[0]
        if self.depth_is_distance:
            return d
        with np.errstate(divide="ignore", invalid="ignore"):
            return d / d[..., 2:3]

    def project(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project ego points into the image.

        points_ego: [..., 3] metres, ego frame.
        Returns uv [..., 2] pixels (OpenCV: pixel u's centre at u), z [...] metres (camera-frame z for pinhole,
        distance from the camera centre for equirectangular), in_front [...] bool: the point projects (ideal
        pinhole and opencv lens: z > 1e-6 m; fisheye and f-theta lens: distance > 1e-6 m and its angle from the
        optical axis <= the lens's max_angle, so z may be <= 0 beyond 90 degrees; equirectangular: distance >
        1e-6 m). uv of points not in front is finite but meaningless. Bounds are not checked (see `inside`).
        """
        p = np.asarray(points_ego, dtype=np.float64)
        q = (p - self.position) @ self.rotation  # camera frame: R^T (p - t) for row vectors
        if self.is_equirect:
            uv, dist = _equirect_project(q, self.width, self.height)
            return uv, dist, dist > IN_FRONT_EPS
        uv, in_front = project(self.K, self.distortion, q)
        return uv, q[..., 2], in_front

    def inside(self, uv: np.ndarray) -> np.ndarray:
        """[...] bool: uv [..., 2] within the image area [-0.5, W-0.5] x [-0.5, H-0.5] (pixel edges)."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_rays(self, uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixel positions, ego frame.

        uv: [..., 2] OpenCV pixel coordinates; default all pixel centres, shape [H, W, 2].
        Returns origins [..., 3] (the camera centre) and unit directions [..., 3], both ego frame. For a
        pinhole camera, direction = normalise(R @ inv(K) @ [u, v, 1]); with a lens, R @ its inverse
        (runtime.lenses.unproject): NaN directions for pixels no ray reaches (outside a fisheye / f-theta image
        circle at max_angle, beyond an opencv lens's fold).
        """
        if uv is None:
            vv, uu = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
            uv = np.stack([uu, vv], axis=-1).astype(np.float64)
        uv = np.asarray(uv, dtype=np.float64)
        if self.is_equirect:
            d = _equirect_dirs(uv, self.width, self.height)
        else:
            d = unproject(self.K, self.distortion, uv)[0]
        d = d @ self.rotation.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.position, d.shape).copy(), d

    def replace(self, **changes: Any) -> Camera:
        """A copy with some fields changed (validated again)."""
        kw = {k: getattr(self, k) for k in self.__dataclass_fields__}
        kw.update(changes)
        return Camera(**kw)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera imaging at ``width`` x ``height`` pixels (an image resampled to that size). With the
        OpenCV pixel-centre convention (column u spans [u - 1/2, u + 1/2]) a scale s = width / self.width maps
        u -> s (u + 1/2) - 1/2: fx' = s fx, cx' = s (cx + 1/2) - 1/2 (likewise v, fy, cy with height). An opencv or
        fisheye lens acts on normalised coordinates and stays; an f-theta lens's pixel distances scale
        (Lens.resized); an equirectangular camera needs no K. Files are dropped (the caller resamples the
        arrays)."""
        K = None
        sx, sy = width / self.width, height / self.height
        if self.K is not None:
            K = self.K.copy()
            K[0, 0], K[0, 2] = sx * K[0, 0], sx * (K[0, 2] + 0.5) - 0.5
            K[1, 1], K[1, 2] = sy * K[1, 1], sy * (K[1, 2] + 0.5) - 0.5
        return Camera(name=self.name, width=width, height=height, K=K, cam_to_ego=self.cam_to_ego,
                      model=self.model, distortion=None if self.distortion is None else self.distortion.resized(sx, sy),
                      extra=dict(self.extra))

    # -- JSON -----------------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], index: int | None = None) -> Camera:
        """Parse one `cameras[]` entry of rig.json (see docs/conventions.md). Unknown keys go to `extra`."""
        if not isinstance(d, Mapping):
            raise CameraError("entry", f"must be an object (got {type(d).__name__})", where_camera(None, index))
        name = d.get("name")
        where = where_camera(name, index)
        if not isinstance(name, str) or not name:
            raise CameraError("name", f"must be a non-empty string (got {plain(name)!r})", where)
        for key in ("width", "height", "cam_to_ego"):
            if key not in d:
                raise CameraError(key, "is missing", where)
        model = d.get("model", "pinhole")
        K = d.get("K")
        if K is None and model == "pinhole":
            raise CameraError("K", "is missing", where)
        return cls(
            name=name,
            width=d["width"],
            height=d["height"],
            K=None if K is None else numbers(K, "K", where),
            cam_to_ego=d["cam_to_ego"],
            model=model,
            distortion=d.get("distortion"),
            image=d.get("image"),
            depth=d.get("depth"),
            extra={k: v for k, v in d.items() if k not in CAMERA_KEYS},
        )

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {} if self.name is None else {"name": self.name}
        if self.image is not None:
            d["image"] = self.image
        d.update(width=self.width, height=self.height)
        if self.K is not None:
            d["K"] = self.K.tolist()
        d["cam_to_ego"] = self.cam_to_ego.tolist()
        d["distortion"] = None if self.distortion is None else self.distortion.to_json()
        if self.model != "pinhole":
            d["model"] = self.model
        if self.depth is not None:
            d["depth"] = self.depth
        d.update(self.extra)
        return d


# -- validators (the one place for each check) -------------------------------------------------------------------

def check_render_size(width: int, height: int, field: str = "width", max_side: int = MAX_SIZE,
                      max_pixels: int = MAX_RENDER_PIXELS) -> None:
    """Refuse a rendered view of width x height pixels over the render limit (CameraError naming ``field``): one
    rule and one message for every front end (CLI, HTTP GET and batch, gRPC, the library's render); a server may
    lower ``max_side`` (its max_render_side)."""
    if max(width, height) > max_side or width * height > max_pixels:
        raise CameraError(field, f"a view of {width}x{height} is over {render_limit(max_side, max_pixels)}")


def check_size(v: Any, key: str, where: str | None = None) -> int:
    """An image dimension ``key`` ("width" / "height"): an integer (2.0 accepted, 2.5 and True not) in
    1..MAX_SIZE."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)) or float(v) != int(v) or not 0 < int(v) <= MAX_SIZE:
        text = repr(plain(v))
        raise CameraError(key, f"must be an integer in 1..{MAX_SIZE} (got {text if len(text) <= 60 else text[:57] + '...'})",
                          where)
    return int(v)


def numbers(value: Any, key: str, where: str | None = None) -> np.ndarray:
    """``value`` as a float64 array of finite numbers; the field of a non-finite entry names its index."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError(key, f"must be numbers (got {plain(value)!r:.80})", where) from None
    if not np.all(np.isfinite(a)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0]) if a.ndim else ()
        raise CameraError(key + "".join(f"[{i}]" for i in bad), "is not finite", where)
    return a


def check_K(K: Any, where: str | None = None) -> np.ndarray:
    """[3, 3] pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (structural entries exact
    up to STRUCT_TOL, then set exactly)."""
    K = numbers(K, "K", where)
    if K.shape != (3, 3):
        raise CameraError("K", f"must be 3x3 (got shape {list(K.shape)})", where)
    for (r, c), want in {(0, 1): 0.0, (1, 0): 0.0, (2, 0): 0.0, (2, 1): 0.0, (2, 2): 1.0}.items():
        if abs(K[r, c] - want) > STRUCT_TOL:
            raise CameraError(f"K[{r}][{c}]", f"must be {want:g} (got {plain(K[r, c])!r})", where)
    if not K[0, 0] > 0:
        raise CameraError("K[0][0]", f"fx must be > 0 (got {plain(K[0, 0])!r})", where)
    if not K[1, 1] > 0:
        raise CameraError("K[1][1]", f"fy must be > 0 (got {plain(K[1, 1])!r})", where)
    K = K.copy()
    K[0, 1] = K[1, 0] = K[2, 0] = K[2, 1] = 0.0
    K[2, 2] = 1.0
    return K


def check_pose(T: Any, where: str | None = None, key: str = "cam_to_ego") -> np.ndarray:
    """A validated rigid 4x4 transform (``key`` names the field in errors: cam_to_ego, lidar_to_ego): finite,
    bottom row [0, 0, 0, 1] (to STRUCT_TOL, then exact), rotation orthonormal to ORTHO_TOL with det +1."""
    try:
        T = pose_matrix(T, key)
    except PoseError as e:
        raise CameraError(e.field, e.message, where) from None
    if np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) > STRUCT_TOL:
        raise CameraError(key, f"bottom row must be [0, 0, 0, 1] (got {T[3].tolist()})", where)
    R = T[:3, :3]
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ORTHO_TOL:
        raise CameraError(key, f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {ORTHO_TOL})", where)
    det = float(np.linalg.det(R))
    if det < 0:
        raise CameraError(key, f"rotation has det {det:.4f}, must be +1 (a reflection)", where)
    T = T.copy()
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


# -- projection models -------------------------------------------------------------------------------------------

def _equirect_project(q: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [..., 3] -> (uv [..., 2], distance [...]).

    azimuth lon = atan2(x, z) in (-pi, pi] (0 = optical axis, + to the right); polar angle from the up axis
    (camera -y) colat = acos(-y / |q|) in [0, pi]. u = (lon / 2pi + 1/2) W - 1/2, v = (colat / pi) H - 1/2, so
    the image's outer pixel edges are lon = -pi/+pi and the zenith/nadir.
    """
    dist = np.linalg.norm(q, axis=-1)
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


def pinhole_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """[3, 3] K of a pinhole camera (pixels, OpenCV pixel centres)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])



def rig_camera(cam: Camera, forward: float = 0.0, width: int | None = None, height: int | None = None):
    """A render camera for a rig camera (pinhole: K, size and its lens, which the renderer draws (issue 28);
    equirectangular), moved ``forward`` metres along ego x, optionally at another size (K and an f-theta lens
    scaled with Camera.resized). Name and files are dropped."""
    if width is not None or height is not None:
        cam = cam.resized(cam.width if width is None else width, cam.height if height is None else height)
    T = np.array(cam.cam_to_ego, dtype=np.float64)
    T[0, 3] += float(forward)
    return Camera(width=cam.width, height=cam.height, cam_to_ego=T, K=cam.K, model=cam.model,
                  distortion=cam.distortion)

__all__ = [
    "rig_camera",
    "CAMERA_KEYS",
    "IN_FRONT_EPS",
    "MAX_RENDER_PIXELS",
    "MAX_SIZE",
    "MODELS",
    "STRUCT_TOL",
    "Camera",
    "CameraError",
    "CameraModel",
    "check_K",
    "check_pose",
    "check_render_size",
    "render_limit",
    "check_size",
    "look_rotation",
    "numbers",
    "pinhole_K",
    "where_camera",
]
