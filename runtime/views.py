"""Render requests: what "render this view of the scene" means, independent of the transport (the HTTP server in
server/, a later gRPC front end). No HTTP concepts here: errors are ViewError naming the request field at fault.

    request = ViewRequest(camera_from_opencv(cam_to_ego, 1600, 900, fov=70), output="rgb", format="png")
    data = render_request(scene, request)          # bytes of a PNG, request.media_type "image/png"
    etag = request.key()                           # sha256 of the request's canonical description

A ViewRequest holds a runtime.render camera in the ego frame (x forward, y left, z up, metres; OpenCV camera axes
x right, y down, z forward; docs/conventions.md), the output (rgb | depth | alpha) and its encoding
(png | jpeg | exr). The camera constructors accept the project's OpenCV convention (camera_from_opencv), CARLA
sensor poses (camera_from_carla_pose, through runtime.convert.camera_from_carla), an input camera of the scene's
rig (camera_from_rig; optionally through another lens) and batches: a {"cameras": [...]} list mixing those, or a
nerfstudio camera_path.json (cameras_from_batch, through runtime.convert.cameras_from_nerfstudio_path). A camera
move (common.poses.CameraMove: forward, left, up metres along ego x, y, z, yaw degrees to the left) is applied to
an input camera's or an explicit pose by move_camera, the one place every front end's move goes through.
encode_view turns the renderer's float32 arrays into file bytes; render_request = runtime.scene.render_view +
encode_view. docs/inference.md ("Render requests") states the conventions and encodings.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from xyzcyl.common.media import exr_bytes
from xyzcyl.common.poses import MOVE_NAMES, CameraMove, MoveError

from . import convert
from .camera import (
    MAX_SIZE,
    STRUCT_TOL,
    Camera,
    CameraError,
    check_render_size,
    check_size,
    pinhole_K,
    render_limit,
)
from .errors import FieldError
from .numba_cache import njit
from .rig import Rig
from .scene import Scene, render_view, rig_camera

OUTPUTS = ("rgb", "depth", "alpha", "all")   # all: R G B A Z in one EXR (xyzcyl render's .exr default)
FORMATS = ("png", "jpeg", "exr")
MEDIA_TYPES = {"png": "image/png", "jpeg": "image/jpeg", "exr": "image/x-exr"}
EXTENSIONS = {"png": ".png", "jpeg": ".jpg", "exr": ".exr"}
# PNG encoder (encode_png): one PNG filter on every row (numba), then ISA-L deflate (the isal package) at
# PNG_COMPRESSION. Chosen by measurement on rendered views of a real
# PandaSet scene (docs/inference.md "Encodings" has the table; 2 shared cores): rgb 1600x900 encode_view 10 ms /
# 1.87 MB (Up) against 60 ms / 1.91 MB for the former OpenCV path (float64 numpy conversion, zlib level 1, RLE,
# SUB). OpenCV / zlib at levels 1-3 with any filter and strategy took 34-92 ms; Paeth instead of Up is 7 %
# smaller for +2.5 ms (row_filter="paeth"); Sub compresses alpha best.
PNG_COMPRESSION = 1        # ISA-L level (0..3); 1: as small as 2 and 3 here, 17 % smaller than 0 at the same speed
PNG_FILTERS = {"rgb": "up", "depth": "up", "alpha": "sub"}
DEPTH_PNG_SCALE = 1000.0  # depth PNG: 16-bit unsigned millimetres (metres x 1000), 0 = no surface
DEPTH_PNG_MAX = 65535     # uint16 ceiling: depths beyond 65.535 m saturate there
EXR_CHANNELS = {"rgb": ("R", "G", "B"), "depth": ("Z",), "alpha": ("A",), "all": ("R", "G", "B", "A", "Z")}
KEY_DECIMALS = 9          # key(): K and cam_to_ego entries rounded to 1e-9 (pixels, metres / unitless)
KEY_VERSION = 2           # bump when the canonical description changes (invalidates caches and ETags)


class ViewError(FieldError):
    """A render request that cannot be honoured. ``field``: the request field at fault (e.g. "cam_to_ego",
    "fov", "width", "format", "cameras[3].fov", "camera_path[2].camera_to_world"); str(e) = "<field>: <message>"."""


# ------------------------------------------------------------------------------------------- field parsing


def _short(v: Any) -> str:
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _number(v: Any, field: str) -> float:
    if not _is_number(v) or not math.isfinite(float(v)):
        raise ViewError(field, f"must be a finite number (got {_short(v)})")
    return float(v)


def _size(v: Any, field: str) -> int:
    """A rendered view's dimension (runtime.camera.check_size: an integer, 2.0 accepted, 2.5 not, in 1..16384; over
    that, the render limit's message, as for too many pixels: resolve_camera)."""
    try:
        return check_size(v, field)
    except CameraError as e:
        if _is_number(v) and math.isfinite(float(v)) and float(v) == int(v) and int(v) > MAX_SIZE:
            raise ViewError(field, f"{int(v)} pixels is over {render_limit()}") from None
        raise ViewError(field, e.message) from None


def _matrix(v: Any, field: str, rows: int, cols: int) -> np.ndarray:
    """[rows, cols] float64 from rows*cols numbers (row-major) or a nested [rows][cols] list / array."""
    if isinstance(v, np.ndarray) and v.dtype.kind in "iuf" and v.size == rows * cols and v.ndim in (1, 2) \
            and (v.ndim == 1 or v.shape == (rows, cols)):
        m = v.astype(np.float64).reshape(rows, cols)
    elif isinstance(v, (list, tuple)) and len(v) == rows * cols and all(_is_number(x) for x in v):
        m = np.array(v, dtype=np.float64).reshape(rows, cols)
    elif isinstance(v, (list, tuple)) and len(v) == rows and all(
            isinstance(r, (list, tuple)) and len(r) == cols and all(_is_number(x) for x in r) for r in v):
        m = np.array(v, dtype=np.float64)
    else:
        raise ViewError(field, f"must be {rows * cols} numbers (row-major) or a [{rows}, {cols}] array "
                               f"(got {_short(v)})")
    if not np.all(np.isfinite(m)):
        raise ViewError(field, f"{int(np.count_nonzero(~np.isfinite(m)))} non-finite entries")
    return m


def _camera(build, fields: Mapping[str, str]):
    """Run a camera constructor; its CameraError (field "cam_to_ego", "K[0][0]", "width", ...) becomes a ViewError
    naming the request field that the camera's field (its root name) maps to in ``fields``."""
    try:
        return build()
    except CameraError as e:    # "distortion.k1" -> "cameras[2].distortion.k1": the sub-path is kept
        root = e.root_field
        name = fields[root] + e.field[len(root):] if root in fields else fields["*"]
        raise ViewError(name, e.message) from None


def _from_conversion(e: convert.ConversionError, field: str | None = None) -> ViewError:
    """runtime.convert's error as a ViewError naming ``field``, else the converter's own field (the JSON path
    of a camera_path.json document, which is the request's)."""
    return ViewError(field or e.field, e.message)


# ------------------------------------------------------------------------------------------- view specs

CARLA_KEYS = ("x", "y", "z", "pitch", "yaw", "roll")
_POSES = ('camera=NAME, cam_to_ego=16 numbers (+ fx/fy/cx/cy or fov), or CARLA x,y,z,pitch,yaw,roll (+ fov)')


def move_camera(camera: Camera, move: CameraMove) -> Camera:
    """``camera`` (a render camera, ego frame) moved by ``move``: its cam_to_ego turned ``move.yaw`` degrees to the
    left about the vertical through the camera's centre, then shifted (forward, left, up) metres along ego x, y, z
    (CameraMove.apply); K, size and lens are kept. No move: the camera itself. The one place a move is applied:
    `xyzcyl render`, the GET render query and the batch items all come here through ViewSpec."""
    if not move:
        return camera
    return camera.replace(cam_to_ego=move.apply(camera.cam_to_ego))


@dataclass(frozen=True, kw_only=True)
class ViewSpec:
    """One view as a user states it -- a GET query, an item of a batch, the flags of ``xyzcyl render`` -- before it
    is resolved against a scene's rig. Every transport fills one ViewSpec and resolves it here: one parser, one set
    of checks and messages.

    Exactly one pose:
    - ``camera``: an input camera of the scene's rig (its K, size, lens and pose; width / height optional: the
      camera resized, one side given -> the other follows its aspect ratio), optionally with ``distortion``: the
      camera's pose and (resized) K through that lens instead of its own (the lens as given, at the rendered size;
      ``[0, 0, 0, 0]``: an ideal pinhole);
    - ``cam_to_ego`` (16 numbers row-major or [4, 4], OpenCV camera -> ego, metres) with width, height and either
      ``K`` ([3, 3] or 9 numbers, no skew), ``fx`` (``fy`` defaults to fx, ``cx``, ``cy`` to the image centre
      ((W-1)/2, (H-1)/2), OpenCV pixel centres) or ``fov`` (HORIZONTAL degrees in (0, 180), square pixels,
      centred principal point; with a lens, the fov of its paraxial pinhole), and optionally ``distortion``: a
      lens as rig.json writes one (runtime.lenses: an OpenCV coefficient list, or {"model": "opencv" |
      "opencv_fisheye" | "ftheta", ...}); or, with ``model="equirectangular"``, no intrinsics (a full 360x180
      panorama);
    - ``carla``: a CARLA sensor pose {x, y, z (metres), pitch, yaw, roll (degrees)} relative to the vehicle,
      with ``fov`` and width, height (runtime.convert.camera_from_carla).
    ``move``: a camera move applied to the ``camera`` or ``cam_to_ego`` pose (move_camera): a CameraMove, or a
    mapping {forward, left, up (metres along ego x, y, z), yaw (degrees to the left)} of values as the user gave
    them, checked here (common.poses.CameraMove: finite numbers, |shift| <= 1000 m, |yaw| <= 360 degrees). A
    CARLA pose takes no move (its own x, y, z and yaw say where it is): refused naming the move's first field.
    ``output`` / ``format`` / ``quality``: as ViewRequest.
    ``names``: the name each attribute has in the transport, for errors -- the query parameter, the JSON path
    ("cameras[2].fov", "cameras[0].transform.location.x"), the CLI flag ("--cam-to-world"), and for the move's
    fields under "move.<key>" ("move.yaw": "--yaw"); an attribute not listed keeps its own name. Every refusal is
    a ViewError naming the field by that name."""

    camera: str | None = None
    cam_to_ego: Any = None
    K: Any = None
    fx: Any = None
    fy: Any = None
    cx: Any = None
    cy: Any = None
    fov: Any = None
    distortion: Any = None
    carla: Mapping[str, Any] | None = None
    move: CameraMove | Mapping[str, Any] | None = None
    model: str = "pinhole"
    width: Any = None
    height: Any = None
    output: str = "rgb"
    format: str = "png"
    quality: Any = 90
    names: Mapping[str, str] = field(default_factory=dict)

    def name(self, attr: str) -> str:
        """The transport's name of attribute ``attr`` (for errors)."""
        return self.names.get(attr, attr)

    def move_name(self, key: str) -> str:
        """The transport's name of the move's field ``key`` ("forward", "yaw"): ``names["move.<key>"]``, else the
        key itself (a CARLA item's "yaw" in ``names`` is its transform's, not the move's)."""
        return self.names.get(f"move.{key}", key)

    def resolve_camera(self, rig: Rig | None = None) -> Camera:
        """The render camera (ego frame) the spec describes; ``rig``: the scene's rig (needed for ``camera``). A view
        over the render limit (runtime.camera.check_render_size) is refused here, before anything is rendered."""
        cam = self._resolve(rig)
        try:
            check_render_size(cam.width, cam.height)
        except CameraError as e:
            raise ViewError(self.name("width" if cam.width >= cam.height else "height"), e.message) from None
        return cam

    def _resolve(self, rig: Rig | None) -> Camera:
        carla = dict(self.carla) if self.carla else {}
        modes = [m for m, on in (("camera", self.camera is not None), ("cam_to_ego", self.cam_to_ego is not None),
                                 ("carla", bool(carla))) if on]
        if len(modes) != 1:
            second = modes[1] if len(modes) > 1 else "camera"
            raise ViewError(self.name(next(iter(carla), "x")) if second == "carla" else self.name(second),
                            f"give exactly one pose: {_POSES}; got {' and '.join(modes) or 'none'}")
        if self.distortion is not None and self.cam_to_ego is None and self.camera is None:
            raise ViewError(self.name("distortion"), "a lens goes with cam_to_ego (and K / fx / fov) or an input "
                                                     "camera; a CARLA camera has none")
        move = self._move()
        if modes[0] == "carla":
            if move:
                first = next(iter(move.values()))       # the first field that is set
                raise ViewError(self.move_name(first), "a CARLA pose takes no camera move: change its x, y, z and "
                                                       "yaw (moves go with camera or cam_to_ego)")
            return self._carla(carla)
        cam = self._rig_camera(rig) if modes[0] == "camera" else self._opencv()
        try:
            return move_camera(cam, move)
        except CameraError as e:         # not expected: a turn about the vertical keeps the pose a rotation
            raise ViewError(self.move_name(next(iter(move.values()))), e.message) from None

    def request(self, rig: Rig | None = None) -> ViewRequest:
        """The ViewRequest: the resolved camera with output, format and quality (errors named by ``names``)."""
        cam = self.resolve_camera(rig)
        try:
            return ViewRequest(cam, self.output, self.format, self.quality)
        except ViewError as e:
            raise ViewError(self.name(e.field), e.message) from None

    # -- the three poses ----------------------------------------------------------------------------------------
    def _size(self, attr: str) -> int:
        return _size(getattr(self, attr), self.name(attr))

    def _move(self) -> CameraMove:
        """The CameraMove of ``move`` (ViewError naming the transport's name of a field that cannot be used)."""
        if self.move is None or isinstance(self.move, CameraMove):
            return self.move or CameraMove()
        if not isinstance(self.move, Mapping):
            raise ViewError(self.name("move"), f"must be an object {{{', '.join(MOVE_NAMES)}}} (got "
                                               f"{_short(self.move)})")
        try:
            return CameraMove.from_values(self.move)
        except MoveError as e:
            raise ViewError(self.move_name(e.field), e.message) from None

    def _rig_camera(self, rig: Rig | None) -> Camera:
        if rig is None:
            raise ViewError(self.name("camera"), "input cameras need a scene's rig (none given)")
        name = self.camera
        if not isinstance(name, str) or name not in rig.names:
            raise ViewError(self.name("camera"), f"no camera {_short(name)} in the scene's rig "
                                                 f"(cameras: {', '.join(rig.names)})")
        cam = rig.camera(name)
        w = None if self.width is None else self._size("width")
        h = None if self.height is None else self._size("height")
        if w is not None and h is None:   # one side given: the other follows the camera's aspect ratio
            h = _size(max(1, round(w * cam.height / cam.width)), self.name("width"))
        elif h is not None and w is None:
            w = _size(max(1, round(h * cam.width / cam.height)), self.name("height"))
        lens = self.distortion

        def build() -> Camera:    # with a lens: the input camera's pose and (resized) K through that lens
            c = rig_camera(cam, width=w, height=h)
            return c if lens is None else c.replace(distortion=lens)

        return _camera(build, {"width": self.name("width"), "height": self.name("height"),
                               "distortion": self.name("distortion"), "*": self.name("camera")})

    def _opencv(self) -> Camera:
        for attr in ("width", "height"):
            if getattr(self, attr) is None:
                raise ViewError(self.name(attr), "is required with cam_to_ego")
        W, H = self._size("width"), self._size("height")
        T = _matrix(self.cam_to_ego, self.name("cam_to_ego"), 4, 4)
        fields = {"cam_to_ego": self.name("cam_to_ego"), "width": self.name("width"), "height": self.name("height"),
                  "*": self.name("cam_to_ego")}
        if self.model == "equirectangular":
            for attr in ("K", "fx", "fy", "cx", "cy", "fov", "distortion"):
                if getattr(self, attr) is not None:
                    raise ViewError(self.name(attr), "an equirectangular panorama takes no intrinsics")
            return _camera(lambda: Camera(model="equirectangular", cam_to_ego=T, width=W, height=H), fields)
        if self.model != "pinhole":
            raise ViewError(self.name("model"), f"must be pinhole or equirectangular (got {_short(self.model)})")
        fx, fy, cx, cy = self.fx, self.fy, self.cx, self.cy
        if self.K is not None:
            for attr in ("fx", "fy", "cx", "cy", "fov"):
                if getattr(self, attr) is not None:
                    raise ViewError(self.name(attr), "cannot be combined with K")
            K = _matrix(self.K, self.name("K"), 3, 3)
            if abs(K[0, 1]) > STRUCT_TOL or abs(K[1, 0]) > STRUCT_TOL or np.any(np.abs(K[2] - [0, 0, 1]) > STRUCT_TOL):
                raise ViewError(self.name("K"), "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
            fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            names = dict.fromkeys(("fx", "fy", "cx", "cy"), self.name("K"))
        else:
            names = {k: self.name(k) for k in ("fx", "fy", "cx", "cy")}
        if (fx is None) == (self.fov is None):
            raise ViewError(self.name("fov"), "give exactly one of fx (focal length, pixels; with optional fy, cx, "
                                              "cy) and fov (horizontal degrees)")
        if self.fov is not None:
            for key, v in (("fy", fy), ("cx", cx), ("cy", cy)):
                if v is not None:
                    raise ViewError(names[key], "cannot be combined with fov (square pixels, centred principal "
                                                "point)")
            fx = fy = W / (2.0 * math.tan(math.radians(self._fov()) / 2.0))
        else:
            fx = _number(fx, names["fx"])
            fy = fx if fy is None else _number(fy, names["fy"])
            for key, v in (("fx", fx), ("fy", fy)):
                if v <= 0:
                    raise ViewError(names[key], f"focal length must be > 0 pixels (got {v})")
        # OpenCV pixel centres: column u's centre is at x = u, so the image centre is ((W-1)/2, (H-1)/2).
        cx = (W - 1) / 2.0 if cx is None else _number(cx, names["cx"])
        cy = (H - 1) / 2.0 if cy is None else _number(cy, names["cy"])
        K = pinhole_K(fx, fy, cx, cy)
        return _camera(lambda: Camera(K=K, cam_to_ego=T, width=W, height=H, distortion=self.distortion),
                       dict(fields, K=names["fx"], distortion=self.name("distortion")))

    def _fov(self) -> float:
        deg = _number(self.fov, self.name("fov"))
        if not 0.0 < deg < 180.0:
            raise ViewError(self.name("fov"), f"must be a horizontal field of view in (0, 180) degrees (got {deg})")
        return deg

    def _carla(self, carla: Mapping[str, Any]) -> Camera:
        missing = [k for k in CARLA_KEYS if carla.get(k) is None] + [k for k in ("fov", "width", "height")
                                                                     if getattr(self, k) is None]
        if missing:
            raise ViewError(self.name(missing[0]), f"a CARLA pose needs x, y, z, pitch, yaw, roll, fov, width, "
                                                   f"height; missing {', '.join(missing)}")
        pose = {k: _number(carla[k], self.name(k)) for k in CARLA_KEYS}
        deg = self._fov()
        W, H = self._size("width"), self._size("height")
        sensor = {"transform": {"location": {k: pose[k] for k in ("x", "y", "z")},
                                "rotation": {k: pose[k] for k in ("pitch", "yaw", "roll")}},
                  "fov": deg, "image_size_x": W, "image_size_y": H}
        try:
            cam = convert.camera_from_carla(sensor)
        except convert.ConversionError as e:  # not expected: every number was checked above
            raise _from_conversion(e, self.name("fov")) from None
        return rig_camera(cam)


def camera_from_opencv(cam_to_ego, width, height, fx=None, fy=None, cx=None, cy=None, fov=None) -> Camera:
    """A pinhole camera in the project's convention (ViewSpec's cam_to_ego pose): cam_to_ego 16 numbers row-major
    or [4, 4], OpenCV camera -> ego, metres, validated (bottom row, orthonormal rotation with det +1) and kept as
    given; width, height pixels in 1..16384; exactly one of fx [fy cx cy] (pixels) and fov (horizontal degrees).
    Errors: ViewError naming the argument ("cam_to_ego", "width", "fov", "fx", ...)."""
    return ViewSpec(cam_to_ego=cam_to_ego, width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy,
                    fov=fov).resolve_camera()


def camera_from_carla_pose(x, y, z, pitch, yaw, roll, fov, width, height) -> Camera:
    """A CARLA camera sensor's transform relative to its vehicle (CARLA's left-handed axes: x forward, y right,
    z up, metres; pitch (up +), yaw (right +), roll degrees), fov = horizontal degrees, width x height pixels
    (CARLA's image_size_x / image_size_y) -> pinhole camera in the ego frame. The conversion is
    runtime.convert.camera_from_carla (the project's one CARLA converter; docs/conventions.md derives it): f =
    W / (2 tan(fov/2)) for x and y, principal point ((W-1)/2, (H-1)/2). Errors: ViewError naming the argument."""
    carla = dict(zip(CARLA_KEYS, (x, y, z, pitch, yaw, roll)))
    return ViewSpec(carla=carla, fov=fov, width=width, height=height).resolve_camera()


def camera_from_rig(rig: Rig, name: str, width: int | None = None, height: int | None = None) -> Camera:
    """The scene rig's input camera ``name`` as a render camera (runtime.scene.rig_camera: K, lens and pose;
    equirectangular cameras stay equirectangular), optionally at width x height pixels (K
    scaled with the pixel-centre convention of Camera.resized). Only one of width / height given: the other
    follows the camera's aspect ratio (rounded). Unknown name -> ViewError("camera", "no camera 'x' in the
    scene's rig (cameras: a, b)")."""
    return ViewSpec(camera=name, width=width, height=height).resolve_camera(rig)


# ------------------------------------------------------------------------------------------- batches

_ITEM_KINDS = ('{"K", "cam_to_ego", "width", "height"[, "distortion"]} (OpenCV), {"fov", "cam_to_ego", "width", "height"} '
               '(OpenCV, horizontal degrees), {"transform", "fov", "image_size_x", "image_size_y"} (CARLA sensor) '
               'or {"camera"[, "width", "height", "distortion"]} (an input camera of the scene); the OpenCV and '
               'input-camera items also take a move: "forward", "left", "up" (metres), "yaw" (degrees to the left)')
_OPENCV_K_KEYS = ("K", "cam_to_ego", "width", "height", "distortion", "name", *MOVE_NAMES)
_OPENCV_FOV_KEYS = ("fov", "cam_to_ego", "width", "height", "distortion", "name", *MOVE_NAMES)
_RIG_KEYS = ("camera", "width", "height", "distortion", "name", *MOVE_NAMES)


def _get(item: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in item:
        raise ViewError(f"{where}.{key}" if where else key, "is missing")
    return item[key]


def _only(item: Mapping[str, Any], allowed: tuple[str, ...], where: str, kind: str) -> None:
    for key in item:
        if key not in allowed:
            raise ViewError(f"{where}.{key}", f"unknown field ({kind} takes {', '.join(allowed)})")


def _move_names(where: str) -> dict[str, str]:
    """ViewSpec.names of an item's move keys: "move.forward" -> "cameras[2].forward"."""
    return {f"move.{k}": f"{where}.{k}" for k in MOVE_NAMES}


def spec_from_item(item: Any, where: str) -> ViewSpec:
    """The ViewSpec of one batch item (cameras_from_batch states the item kinds); ``where`` is its JSON path
    ("cameras[2]"), the prefix of every error's field."""
    if not isinstance(item, Mapping):
        raise ViewError(where, f"must be an object: {_ITEM_KINDS}")
    move = {k: item[k] for k in MOVE_NAMES if k in item}
    if "camera" in item:
        _only(item, _RIG_KEYS, where, "an input camera")
        return ViewSpec(camera=item["camera"], width=item.get("width"), height=item.get("height"),
                        distortion=item.get("distortion"), move=move,
                        names={**{k: f"{where}.{k}" for k in ("camera", "width", "height", "distortion")},
                               **_move_names(where)})
    if "transform" in item:   # a CARLA sensor; its other blueprint attributes (sensor_tick, ...) are ignored
        tf = item["transform"]
        if not isinstance(tf, Mapping):
            raise ViewError(f"{where}.transform", 'must be {"location": {x, y, z}, "rotation": {pitch, yaw, roll}}')
        loc = _get(tf, "location", f"{where}.transform")
        rot = _get(tf, "rotation", f"{where}.transform")
        for key, sub, keys in (("location", loc, "x, y, z"), ("rotation", rot, "pitch, yaw, roll")):
            if not isinstance(sub, Mapping):
                raise ViewError(f"{where}.transform.{key}", f"must be an object {{{keys}}}")
        names = {k: f"{where}.transform.location.{k}" for k in ("x", "y", "z")}
        names.update({k: f"{where}.transform.rotation.{k}" for k in ("pitch", "yaw", "roll")})
        names.update(fov=f"{where}.fov", width=f"{where}.image_size_x", height=f"{where}.image_size_y")
        names.update(_move_names(where))
        carla = {k: _get(loc, k, f"{where}.transform.location") for k in ("x", "y", "z")}
        carla.update({k: _get(rot, k, f"{where}.transform.rotation") for k in ("pitch", "yaw", "roll")})
        return ViewSpec(carla=carla, fov=_get(item, "fov", where), width=_get(item, "image_size_x", where),
                        height=_get(item, "image_size_y", where), move=move, names=names)
    names = {**{k: f"{where}.{k}" for k in ("cam_to_ego", "width", "height", "fov", "K", "distortion")},
             **_move_names(where)}
    if "K" in item:
        _only(item, _OPENCV_K_KEYS, where, "an OpenCV camera with K")
        return ViewSpec(cam_to_ego=_get(item, "cam_to_ego", where), K=item["K"], width=_get(item, "width", where),
                        height=_get(item, "height", where), distortion=item.get("distortion"), move=move,
                        names=names)
    if "fov" in item:
        _only(item, _OPENCV_FOV_KEYS, where, "an OpenCV camera with fov")
        return ViewSpec(cam_to_ego=_get(item, "cam_to_ego", where), fov=item["fov"],
                        width=_get(item, "width", where), height=_get(item, "height", where),
                        distortion=item.get("distortion"), move=move, names=names)
    raise ViewError(where, f"expected one of {_ITEM_KINDS}")


def _check_count(field: str, n: int, max_frames: int | None) -> None:
    if max_frames is not None and n > max_frames:
        raise ViewError(field, f"{n} cameras, more than the {max_frames} allowed in one request")


def cameras_from_batch(doc: Mapping[str, Any], rig: Rig | None = None, max_frames: int | None = None
                       ) -> list[Camera]:
    """The cameras of a batch request (all in the ego frame), in order. ``doc`` is either

    (a) {"cameras": [item, ...]}, each item one of
        {"K": [[3x3]] or 9 numbers, "cam_to_ego": [[4x4]] or 16 numbers, "width", "height"}   OpenCV K (pixels)
        {"fov": degrees, "cam_to_ego", "width", "height"}      OpenCV, HORIZONTAL fov, centred principal point
        {"transform": {"location": {x, y, z}, "rotation": {pitch, yaw, roll}}, "fov", "image_size_x",
         "image_size_y"}                                       a CARLA sensor (runtime.convert.camera_from_carla)
        {"camera": "CAM_FRONT"[, "width", "height", "distortion"]}   an input camera of ``rig`` (camera_from_rig;
                                                               with "distortion": its pose and K through that lens)
      (an optional "name" is allowed in the OpenCV and input-camera items, and a camera move "forward", "left",
      "up" (metres along ego x, y, z), "yaw" (degrees to the left), applied by move_camera; CARLA items may carry
      CARLA's other sensor attributes but no move; other keys are refused, so a misspelt field is not silently
      dropped); or
    (b) a nerfstudio camera_path.json: {"render_width", "render_height", ["camera_type"], "camera_path":
        [{"camera_to_world": 16 numbers row-major, OpenGL camera axes, world = ego; "fov": VERTICAL degrees;
        "aspect" (ignored)}, ...]} (runtime.convert.cameras_from_nerfstudio_path states what nerfstudio's
        reader does with each field).
    Other top-level keys are left to the caller (e.g. output, format). An empty list, more than ``max_frames``
    cameras, wrong types or missing keys -> ViewError whose field is the JSON path ("cameras",
    "cameras[2].K", "camera_path[0].fov", "render_width")."""
    if not isinstance(doc, Mapping):
        raise ViewError("cameras", 'the request must be an object with "cameras" (a list) or a nerfstudio '
                                   'camera path ("camera_path")')
    if "cameras" in doc and "camera_path" in doc:
        raise ViewError("cameras", 'give "cameras" or a nerfstudio "camera_path", not both')
    if "camera_path" in doc:
        frames = doc["camera_path"]
        if isinstance(frames, list):
            _check_count("camera_path", len(frames), max_frames)
        try:
            cams = convert.cameras_from_nerfstudio_path(doc)
        except convert.ConversionError as e:
            raise _from_conversion(e) from None
        return [rig_camera(c) for c in cams]
    items = _get(doc, "cameras", "")
    if not isinstance(items, (list, tuple)) or not items:
        raise ViewError("cameras", f"must be a non-empty list (got {_short(items)})")
    _check_count("cameras", len(items), max_frames)
    return [spec_from_item(item, f"cameras[{i}]").resolve_camera(rig) for i, item in enumerate(items)]


# ------------------------------------------------------------------------------------------- requests


@dataclass(frozen=True, eq=False)
class ViewRequest:
    """One view to render and how to encode it. Compare requests with key() (the camera holds arrays)."""

    camera: Camera   # a render camera (runtime.camera; any lens), ego frame: cam_to_ego, metres
    output: str = "rgb"      # rgb | depth | alpha
    format: str = "png"      # png | jpeg | exr (jpeg cannot hold depth)
    quality: int = 90        # JPEG quality 1..100 (kept, and part of key(), for every format)

    def __post_init__(self) -> None:
        if not isinstance(self.camera, Camera):
            raise ViewError("camera", f"expected a runtime.camera.Camera, got {type(self.camera).__name__}")
        if not isinstance(self.output, str) or self.output not in OUTPUTS:
            raise ViewError("output", f"must be one of {', '.join(OUTPUTS)} (got {_short(self.output)})")
        if not isinstance(self.format, str) or self.format not in FORMATS:
            raise ViewError("format", f"must be one of {', '.join(FORMATS)} (got {_short(self.format)})")
        q = self.quality
        if isinstance(q, (bool, np.bool_)) or not isinstance(q, (int, np.integer)) or not 1 <= int(q) <= 100:
            raise ViewError("quality", f"must be an integer in 1..100 (got {_short(q)})")
        object.__setattr__(self, "quality", int(q))
        if self.output == "all" and self.format != "exr":
            raise ViewError("output", "all (R G B A Z float32 channels) needs format exr")
        if self.format == "jpeg" and self.output == "depth":
            raise ViewError("format", "jpeg cannot hold depth (8-bit, lossy): use png (16-bit millimetres) or exr "
                                      "(float32 metres)")

    @property
    def media_type(self) -> str:
        """image/png, image/jpeg or image/x-exr."""
        return MEDIA_TYPES[self.format]

    @property
    def extension(self) -> str:
        """.png, .jpg or .exr."""
        return EXTENSIONS[self.format]

    @property
    def pixels(self) -> int:
        return self.camera.width * self.camera.height

    def description(self) -> dict[str, Any]:
        """The canonical description key() hashes: camera model, K (None for equirectangular) and cam_to_ego
        (row-major, rounded to 1e-9, -0.0 written as 0.0), width, height, output, format, quality."""
        c = self.camera

        def rounded(a) -> list[float]:
            return [float(x) + 0.0 for x in np.round(np.asarray(a, np.float64), KEY_DECIMALS).ravel()]

        pinhole = not c.is_equirect
        return {"v": KEY_VERSION, "camera": c.model,
                "K": rounded(c.K) if pinhole else None, "cam_to_ego": rounded(c.cam_to_ego),
                "distortion": None if c.distortion is None else c.distortion.to_json(),
                "width": c.width, "height": c.height, "output": self.output, "format": self.format,
                "quality": self.quality}

    def key(self) -> str:
        """sha256 hex of description() as compact sorted JSON: equal requests give equal keys, any difference
        (beyond the 1e-9 rounding) a different key. It describes the request only: a cache or ETag combines it
        with the scene's identity."""
        text = json.dumps(self.description(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()


# ------------------------------------------------------------------------------------------- encoding


def _plane(a: Any, what: str, shape: tuple[int, ...]) -> np.ndarray:
    if a is None:
        raise ValueError(f"{what}: needed for this request, got None")
    a = np.asarray(a)
    if a.shape != shape:
        raise ValueError(f"{what}: expected shape {list(shape)} (the request's camera), got {list(a.shape)}")
    return a


@njit(inline="always")
def _q8(v):
    x = np.float64(v) * 255.0            # exact for float32 inputs: their products with 255 fit a float64
    if not x > 0.0:                      # NaN and <= 0
        return np.uint8(0)
    if x >= 255.0:
        return np.uint8(255)
    return np.uint8(np.rint(x))          # round half to even, as np.rint


@njit(cache=True, nogil=True)
def _u8_kernel(a, out):
    for i in range(a.size):
        out[i] = _q8(a[i])


@njit(cache=True, nogil=True)
def _u8_bgr_kernel(a, out):
    for i in range(a.size // 3):
        out[3 * i] = _q8(a[3 * i + 2])
        out[3 * i + 1] = _q8(a[3 * i + 1])
        out[3 * i + 2] = _q8(a[3 * i])


def _u8(a: np.ndarray, bgr: bool = False) -> np.ndarray:
    """0..1 floats -> uint8 of the same shape: round(255 x) clipped to 0..255 (halves to even, as np.rint), NaN
    -> 0. Exactly the float64 numpy reference clip(rint(float64(x) * 255), 0, 255) with NaN -> 0 (float32
    arithmetic, as runtime.imageio.write_png once used, is off by one level for ~6 in a million values near
    k + 1/2), in one numba pass: 1.6 ms for 1600x900x3 where numpy's five float64 passes took 10-13 ms.
    Single-threaded on purpose, as the other encoding kernels: a parallel numba kernel measured 0.8 ms on idle
    cores but 4-7 ms whenever another process held a core (its threads wait to be scheduled), 0.25-0.75 ms
    serial on the same loaded machine. bgr: [..., 3] input, channels written in reverse order (OpenCV's BGR) in
    the same pass (0.1-0.3 ms less than a cvtColor afterwards)."""
    a = np.ascontiguousarray(a)
    out = np.empty(a.shape, np.uint8)
    if bgr:
        if a.shape[-1:] != (3,):
            raise ValueError(f"_u8: bgr needs [..., 3] channels, got {list(a.shape)}")
        _u8_bgr_kernel(a.reshape(-1), out.reshape(-1))
    else:
        _u8_kernel(a.reshape(-1), out.reshape(-1))
    return out


@njit(inline="always")
def _mm16(v):
    d = np.float64(v)
    if not (d > 0.0 and d < np.inf):     # no surface: 0, negative, NaN, +-inf
        return np.uint16(0)
    mm = np.rint(d * 1000.0)             # DEPTH_PNG_SCALE
    if mm < 1.0:                         # a surface nearer than 0.5 mm is still a surface
        return np.uint16(1)
    if mm > 65535.0:                     # DEPTH_PNG_MAX
        return np.uint16(65535)
    return np.uint16(mm)


@njit(cache=True, nogil=True)
def _mm16_kernel(d, out):
    for i in range(d.size):
        out[i] = _mm16(d[i])


def depth_to_mm16(depth: np.ndarray) -> np.ndarray:
    """[H, W] metres -> uint16 millimetres: round(1000 d) (float64, exact; halves to even) clipped to 0..65535
    (depths beyond 65.535 m saturate at 65535); 0 = no surface (depth 0, negative or non-finite); a surface
    closer than 0.5 mm reads 1 mm, so it never looks like "no surface". One numba pass (single-threaded: _u8)
    instead of numpy's float64 temporaries: 14 ms -> 3 ms for 1600x900 on loaded cores."""
    d = np.ascontiguousarray(depth)
    out = np.empty(d.shape, np.uint16)
    _mm16_kernel(d.reshape(-1), out.reshape(-1))
    return out


_PNG_FILTER_TYPES = {"none": 0, "sub": 1, "up": 2, "paeth": 4}   # PNG filter type bytes (no "average": unused)
_PNG_COLOUR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}                      # channels -> grey, grey+alpha, RGB, RGBA


@njit(cache=True, nogil=True)
def _png_filter_rows(raw, bpp, ftype, out):
    """raw [H, R] uint8, the image's bytes in PNG order (R = width x bytes per pixel; 16-bit samples
    big-endian) -> out [H, 1 + R]: each row's filter type byte, then the row filtered by that type (PNG spec
    9.2; bpp = bytes per pixel, 1..8). Unsigned loop indices and branch-free Paeth let LLVM vectorise the loops:
    Paeth on 1600x900 RGB takes ~2 ms, 15 ms written with signed indices."""
    H, R = raw.shape
    n = np.uint64(R)
    p = np.uint64(min(bpp, R))
    for y in range(H):
        cur = raw[y]
        o = out[y, 1:]
        out[y, 0] = ftype
        if ftype == 0 or (ftype == 2 and y == 0):            # None; Up on the first row (above = zeros)
            for i in range(n):
                o[i] = cur[i]
        elif ftype == 1 or y == 0:                           # Sub; Paeth's first row (b = c = 0: predictor a)
            for i in range(p):
                o[i] = cur[i]
            for i in range(p, n):
                o[i] = (np.int16(cur[i]) - np.int16(cur[i - p])) & 255
        else:
            up = raw[y - 1]
            m = n if ftype == 2 else p                       # Up; Paeth's first pixel (a = c = 0: predictor b)
            for i in range(m):
                o[i] = (np.int16(cur[i]) - np.int16(up[i])) & 255
            if ftype == 4:
                for i in range(p, n):
                    a = np.int16(cur[i - p])
                    b = np.int16(up[i])
                    c = np.int16(up[i - p])
                    pa = b - c                               # p - a, with p = a + b - c
                    pb = a - c                               # p - b
                    pc = pa + pb                             # p - c
                    pa = pa if pa >= 0 else -pa
                    pb = pb if pb >= 0 else -pb
                    pc = pc if pc >= 0 else -pc
                    t = b if pb <= pc else c
                    pred = a if (pa <= pb) & (pa <= pc) else t
                    o[i] = (np.int16(cur[i]) - pred) & 255


def _chunk(tag: bytes, pieces: list[bytes]) -> list[bytes]:
    from isal import isal_zlib

    crc = isal_zlib.crc32(tag)
    for p in pieces:
        crc = isal_zlib.crc32(p, crc)
    return [sum(len(p) for p in pieces).to_bytes(4, "big"), tag, *pieces, crc.to_bytes(4, "big")]


def encode_png(img: np.ndarray, row_filter: str = "up", level: int | None = None) -> bytes:
    """A PNG file of ``img``: uint8 or uint16, [H, W] (grey) or [H, W, C] with C = 1 (grey), 2 (grey + alpha),
    3 (RGB, in that order: no BGR swap) or 4 (RGBA); lossless, non-interlaced, one IDAT chunk, no ancillary
    chunks. Every row uses ``row_filter`` ("up", "sub", "paeth" or "none"; PNG_FILTERS has the measured
    choice per output; no per-row adaptive choice, which costs a pass per candidate filter), then ISA-L deflates
    the rows at ``level`` (0..3, default PNG_COMPRESSION) in one piece on the calling thread (compressing parts on
    several threads measured 12.8 -> 9.2 ms at 1600x900, not worth a thread pool in every process). The runtime's
    one PNG writer: encode_view (the service) and runtime.imageio.write_png (`xyzcyl render`, the scene's background preview) use it."""
    from isal import isal_zlib

    a = np.asarray(img)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3) or (a.ndim == 3 and not 1 <= a.shape[2] <= 4):
        raise ValueError(f"encode_png: expected uint8 or uint16 [H, W] or [H, W, 1..4], got {a.dtype} "
                         f"{list(a.shape)}")
    H, W = a.shape[:2]
    C = 1 if a.ndim == 2 else a.shape[2]
    if H == 0 or W == 0:
        raise ValueError(f"encode_png: empty image {list(a.shape)}")
    if row_filter not in _PNG_FILTER_TYPES:
        raise ValueError(f"encode_png: row_filter must be one of {', '.join(_PNG_FILTER_TYPES)}, got "
                         f"{row_filter!r}")
    level = PNG_COMPRESSION if level is None else level
    if level not in (0, 1, 2, 3):
        raise ValueError(f"encode_png: level must be an ISA-L level 0..3, got {level!r}")
    wide = a.dtype == np.uint16
    a = np.ascontiguousarray(a, dtype=">u2" if wide else np.uint8)    # PNG's 16-bit samples are big-endian
    raw = a.view(np.uint8).reshape(H, -1)
    rows = np.empty((H, 1 + raw.shape[1]), np.uint8)
    _png_filter_rows(raw, C * (2 if wide else 1), _PNG_FILTER_TYPES[row_filter], rows)
    ihdr = W.to_bytes(4, "big") + H.to_bytes(4, "big") + bytes([16 if wide else 8, _PNG_COLOUR_TYPES[C], 0, 0, 0])
    return b"".join([b"\x89PNG\r\n\x1a\n", *_chunk(b"IHDR", [ihdr]),
                     *_chunk(b"IDAT", [isal_zlib.compress(rows, level)]), *_chunk(b"IEND", [])])


def encode_view(rgb, depth, alpha, request: ViewRequest) -> bytes:
    """The bytes of the file ``request`` asks for (request.media_type); only the array of request.output is
    needed (the others may be None).

    rgb [H, W, 3] float32 0..1, depth [H, W] float32 metres along the optical axis (0 = nothing), alpha [H, W]
    float32 0..1 (runtime.scene.render_view's outputs); H x W must be the request camera's size.
    - rgb:   png 8-bit RGB (_u8: round(255 x), clipped, NaN 0; encode_png, Up filter), jpeg 8-bit RGB
             (request.quality, OpenCV's libjpeg-turbo, default 4:2:0 chroma subsampling, no Huffman
             optimisation), exr float32 channels R G B (as rendered, not clipped);
    - depth: png 16-bit grey millimetres (depth_to_mm16: 0 = no surface, saturates at 65.535 m; Up), exr
             float32 channel Z metres;
    - alpha: png (Sub filter) / jpeg 8-bit grey (round(255 a)), exr float32 channel A;
    - all:   exr float32 channels R G B A Z (all three arrays needed)."""
    H, W = request.camera.height, request.camera.width
    out, fmt = request.output, request.format
    if out == "rgb":
        a = _plane(rgb, "rgb", (H, W, 3))
    elif out == "all":
        a = np.dstack([_plane(rgb, "rgb", (H, W, 3)), _plane(alpha, "alpha", (H, W)), _plane(depth, "depth", (H, W))])
    else:
        a = _plane(depth if out == "depth" else alpha, out, (H, W))
    if fmt == "exr":
        # uncompressed: OpenEXR's zip took 0.36 s for a 1600x900 RGB view (more than the render), saving ~5 %
        return exr_bytes(a.reshape(H, W, -1), EXR_CHANNELS[out], compression="none")
    if fmt == "png":
        return encode_png(depth_to_mm16(a) if out == "depth" else _u8(a), PNG_FILTERS[out])
    import cv2

    img = _u8(a, bgr=out == "rgb")       # jpeg (ViewRequest refuses jpeg depth); OpenCV's encoders take BGR
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, request.quality])
    if not ok:
        raise OSError(f"OpenCV could not encode a {W}x{H} {out} {fmt}")
    return buf.tobytes()


def render_request(scene: Scene, request: ViewRequest, **options) -> bytes:
    """Render ``request.camera`` with runtime.scene.render_view (Gaussians over the background panorama;
    ``options`` are the renderer's RenderOptions) and encode it with encode_view."""
    rgb, depth, alpha = render_view(scene, request.camera, **options)
    return encode_view(rgb, depth, alpha, request)


__all__ = [
    "DEPTH_PNG_MAX",
    "DEPTH_PNG_SCALE",
    "FORMATS",
    "OUTPUTS",
    "PNG_COMPRESSION",
    "PNG_FILTERS",
    "ViewError",
    "ViewRequest",
    "ViewSpec",
    "camera_from_carla_pose",
    "camera_from_opencv",
    "camera_from_rig",
    "cameras_from_batch",
    "depth_to_mm16",
    "encode_png",
    "encode_view",
    "move_camera",
    "render_request",
    "spec_from_item",
]
