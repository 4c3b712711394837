"""One function per foreign camera convention, into and out of the project's rig model (runtime/rig.py).

- nerfstudio / instant-ngp `transforms.json` (camera-to-world in OpenGL axes: x right, y up, z back; COLMAP
  pixel convention: pixel k's centre at k + 0.5)            -> rig_from_nerfstudio / rig_to_nerfstudio
- nerfstudio `camera_path.json` (the viewer's exported render path, read by `ns-render camera-path`; same axes
  and pixel convention, vertical FoV)                        -> cameras_from_nerfstudio_path / cameras_to_nerfstudio_path
- CARLA camera sensors (Unreal, left-handed: x forward, y right, z up; pitch/yaw/roll in degrees; horizontal
  FoV; image_size_x/y)                                       -> camera_from_carla / camera_to_carla
- nuScenes `calibrated_sensor` records (translation, rotation wxyz, camera_intrinsic; already OpenCV camera
  axes and the ego frame)                                    -> camera_from_nuscenes / camera_to_nuscenes
- the paper's Waymo completion (5 cameras -> 8 with mirrored virtual cameras)  -> complete_waymo_rig
docs/conventions.md derives each mapping.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from xyzcyl.common.poses import PoseError, pose_matrix

from .camera import MAX_SIZE, Camera
from .errors import RigError, plain
from .lenses import fisheye_max_angle_deg
from .rig import Rig
from .rotations import quat_to_rotmat, rotmat_to_quat

# OpenGL camera (x right, y up, z back) <-> OpenCV camera (x right, y down, z forward): flip y and z.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# Unreal/CARLA camera actor axes (x forward, y right, z up) from OpenCV camera axes: columns are the images of
# OpenCV x (-> UE y), y (-> UE -z) and z (-> UE x).
UE_FROM_CV = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# Ego (x forward, y left, z up) from CARLA vehicle axes (x forward, y right, z up): negate y.
EGO_FROM_CARLA = np.diag([1.0, -1.0, 1.0])
WAYMO_NAMES = {"front": "FRONT", "front_left": "FRONT_LEFT", "front_right": "FRONT_RIGHT",
               "side_left": "SIDE_LEFT", "side_right": "SIDE_RIGHT"}
_NS_DIST = ("k1", "k2", "p1", "p2", "k3")
_NS_FISHEYE_DIST = ("k1", "k2", "k3", "k4")   # nerfstudio OPENCV_FISHEYE (cv2.fisheye's k1..k4)  # nerfstudio keys in OpenCV coefficient order
_CARLA_TOL_PX = 1e-3  # principal point must be within this of the image centre to be a CARLA camera


class ConversionError(RigError):
    """A foreign record that cannot be converted: ``field`` the field at fault, as a JSON path inside ``where``,
    the record ("transforms.json: frames[3]", "camera_path.json", "carla sensor FRONT", "camera 'CAM_FRONT'");
    a camera's own check (RigError) keeps its field, its camera named after the record."""


# -- small rotation helpers ----------------------------------------------------------------------------------

def quat_wxyz_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z) (normalised here) -> [3, 3] rotation matrix."""
    return quat_to_rotmat(np.asarray(q, dtype=np.float64))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> unit quaternion (w, x, y, z) with w >= 0 (runtime.rotations.rotmat_to_quat)."""
    return rotmat_to_quat(R)


def _pose(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _num(record: Mapping[str, Any], key: str, where: str, path: str = "") -> float:
    """``record[key]`` as a float; ConversionError with field ``path + key`` (``path``: the record's place inside
    ``where``, e.g. "transform.location.")."""
    if key not in record:
        raise ConversionError(path + key, "is missing", where)
    v = record[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConversionError(path + key, f"must be a finite number (got {plain(v)!r})", where)
    return float(v)


def _from_camera(exc: RigError, where: str) -> ConversionError:
    """A camera's own check (RigError naming the camera) as raised by a converter: the camera after the record."""
    return ConversionError(exc.field, exc.message, f"{where}: {exc.where}" if exc.where else where)


# -- nerfstudio ----------------------------------------------------------------------------------------------

def rig_from_nerfstudio(transforms: Mapping[str, Any], root: str | Path | None = None) -> Rig:
    """nerfstudio `transforms.json` (dict) -> Rig, world frame taken as the ego frame.

    Intrinsics fl_x, fl_y, cx, cy, w, h (and OpenCV k1 k2 p1 p2 k3, or k1..k4 for a fisheye) at the top level or
    per frame; camera_model PINHOLE / OPENCV / SIMPLE_PINHOLE / OPENCV_FISHEYE / EQUIRECTANGULAR. An
    OPENCV_FISHEYE frame becomes an opencv_fisheye lens whose max_angle_deg (nerfstudio has none) is the widest its
    k1..k4 allow, up to 180 (runtime.lenses.fisheye_max_angle_deg). transform_matrix is camera-to-world in
    OpenGL camera axes, so cam_to_ego = transform_matrix @ diag(1, -1, -1, 1). nerfstudio puts pixel k's centre
    at k + 0.5, OpenCV at k: cx_opencv = cx - 0.5, cy_opencv = cy - 0.5. Camera names: the frame's "name" if
    present (written by rig_to_nerfstudio), else the file name without extension.
    """
    frames = transforms.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ConversionError("frames", "must be a non-empty list", "transforms.json")
    cams = []
    used: set[str] = set()
    for k, fr in enumerate(frames):
        where = f"transforms.json: frames[{k}]"
        if not isinstance(fr, Mapping):
            raise ConversionError(f"frames[{k}]", "must be an object", "transforms.json")
        merged = {**{key: v for key, v in transforms.items() if key != "frames"}, **fr}
        model = str(merged.get("camera_model", "OPENCV")).upper()
        if model not in ("PINHOLE", "OPENCV", "SIMPLE_PINHOLE", "OPENCV_FISHEYE", "EQUIRECTANGULAR"):
            raise ConversionError("camera_model", f"{model!r} is not supported (PINHOLE, OPENCV, SIMPLE_PINHOLE, "
                                                  "OPENCV_FISHEYE, EQUIRECTANGULAR)", where)
        if "transform_matrix" not in fr:
            raise ConversionError("transform_matrix", "is missing", where)
        try:
            c2w = np.array(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ConversionError("transform_matrix", "must be 4x4 numbers", where) from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4):
            raise ConversionError("transform_matrix", f"must be 4x4 (got shape {c2w.shape})", where)
        w, h = _num(merged, "w", where), _num(merged, "h", where)
        if w != int(w) or h != int(h):
            raise ConversionError("w" if w != int(w) else "h", f"w and h must be integers (got {w}, {h})", where)
        file_path = fr.get("file_path")
        name = fr.get("name") or (Path(file_path).stem if file_path else f"camera_{k}")
        if name in used:
            name = f"{name}_{k}"
        used.add(name)
        extra = {key: v for key, v in fr.items()
                 if key not in ("file_path", "transform_matrix", "name", "depth_file_path", "camera_model",
                                "fl_x", "fl_y", "cx", "cy", "w", "h", *_NS_DIST, "k4")}
        K, distortion, cam_model = None, None, "pinhole"
        if model == "EQUIRECTANGULAR":
            cam_model = "equirectangular"
        else:
            fx = _num(merged, "fl_x", where)
            fy = _num(merged, "fl_y", where) if "fl_y" in merged else fx
            cx, cy = _num(merged, "cx", where) - 0.5, _num(merged, "cy", where) - 0.5
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            if model == "OPENCV_FISHEYE":
                k = [_num(merged, key, where) if key in merged else 0.0 for key in _NS_FISHEYE_DIST]
                distortion = {"model": "opencv_fisheye", **dict(zip(_NS_FISHEYE_DIST, k)),
                              "max_angle_deg": fisheye_max_angle_deg(k)}
            else:
                coeffs = [float(merged.get(key, 0.0)) for key in _NS_DIST]
                distortion = tuple(coeffs) if any(coeffs) else None
        try:
            cams.append(Camera(name=name, width=int(w), height=int(h), K=K, cam_to_ego=c2w @ GL_FROM_CV,
                               model=cam_model, distortion=distortion, image=file_path,
                               depth=fr.get("depth_file_path"), extra=extra))
        except RigError as exc:
            raise _from_camera(exc, where) from None
    top = {key: v for key, v in transforms.items()
           if key not in ("frames", "camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", *_NS_DIST, "k4")}
    return Rig(cameras=tuple(cams), root=None if root is None else Path(root), extra=top)


def rig_to_nerfstudio(rig: Rig) -> dict[str, Any]:
    """Rig -> nerfstudio `transforms.json` dict with per-frame intrinsics (inverse of rig_from_nerfstudio)."""
    frames = []
    for cam in rig.cameras:
        fr: dict[str, Any] = {"name": cam.name, "w": cam.width, "h": cam.height}
        if cam.image is not None:
            fr["file_path"] = cam.image
        if cam.depth is not None:
            fr["depth_file_path"] = cam.depth
        if cam.model == "equirectangular":
            fr["camera_model"] = "EQUIRECTANGULAR"
        else:
            K = cam.K
            fr.update(camera_model="OPENCV", fl_x=K[0, 0], fl_y=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5)
            lens = cam.distortion
            if lens is not None and lens.model == "opencv_fisheye":     # nerfstudio keeps no max angle
                fisheye = lens.to_json()
                fr["camera_model"] = "OPENCV_FISHEYE"
                fr.update({key: float(fisheye[key]) for key in _NS_FISHEYE_DIST})
                lens = None
            elif lens is not None and lens.model != "opencv":
                raise ConversionError("distortion", f"an {lens.model} lens; this writer knows nerfstudio OPENCV "
                                                    "(k1 k2 p1 p2 k3) and OPENCV_FISHEYE (k1..k4) only", cam.where)
            d = () if lens is None else lens.opencv_coefficients()
            if len(d) > 5:
                raise ConversionError("distortion", f"has {len(d)} coefficients; nerfstudio OPENCV holds k1 k2 p1 "
                                                    "p2 k3 only", cam.where)
            fr.update({key: float(v) for key, v in zip(_NS_DIST, d)})
        fr["transform_matrix"] = (cam.cam_to_ego @ GL_FROM_CV).tolist()
        fr.update(cam.extra)
        frames.append(fr)
    return {**dict(rig.extra), "frames": frames}


# -- nerfstudio camera paths --------------------------------------------------------------------------------

_NS_PATH = "camera_path.json"
_NS_PATH_TYPES = ("perspective", "fisheye", "equirectangular")
# nerfstudio's FISHEYE camera (cameras.py): the equidistant fisheye theta = r / f (no distortion terms in a camera
# path), rays for r / f up to pi -- our opencv_fisheye lens with k1..k4 = 0 and max_angle_deg 180
_NS_FISHEYE = {"model": "opencv_fisheye", "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "max_angle_deg": 180.0}
_CENTRE_TOL_PX = _CARLA_TOL_PX  # a camera path's principal point must be this close to the image centre


def _path_error(field: str, detail: str) -> ConversionError:
    return ConversionError(field, detail, _NS_PATH)


def _path_size(doc: Mapping[str, Any], key: str) -> int:
    v = doc.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v) \
            or not 0 < int(v) <= MAX_SIZE:
        raise _path_error(key, f"must be an integer in 1..{MAX_SIZE} (got {plain(v)!r})")
    return int(v)


def _path_pose(v: Any, field: str) -> np.ndarray:
    """16 numbers row-major (nerfstudio's form: torch.tensor(c2w).view(4, 4)) or a nested [4, 4] list
    (common.poses.pose_matrix, the one reader of a pose's numbers)."""
    try:
        return pose_matrix(v, field)
    except PoseError as e:
        raise _path_error(e.field, e.message) from None


def _is_num(x: Any) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float))


def cameras_from_nerfstudio_path(doc: Mapping[str, Any]) -> list[Camera]:
    """nerfstudio `camera_path.json` (dict) -> one Camera per frame, named frame_00000, frame_00001, ...; the
    path's world frame is taken as the ego frame (as for transforms.json).

    The fields read are those of nerfstudio's own reader (nerfstudio/cameras/camera_paths.py,
    get_path_from_json, used by `ns-render camera-path`):
    - render_width, render_height: the image size of every frame (pixels);
    - camera_type: "perspective" (default when absent), "fisheye" (nerfstudio's equidistant fisheye, theta = r / f
      up to 180 degrees from the axis: an opencv_fisheye lens with k1..k4 = 0, max_angle_deg 180; f from fov as
      for perspective) or "equirectangular" (omnidirectional-stereo and VR180 are refused);
    - camera_path: [{"camera_to_world": 16 numbers, row-major [4, 4] camera -> world with OpenGL camera axes
      (x right, y up, z back), "fov": VERTICAL field of view in degrees (three.js PerspectiveCamera),
      "aspect": ignored, as nerfstudio ignores it (the size is render_width x render_height)}, ...].
    Perspective intrinsics as nerfstudio builds them: fx = fy = (H/2) / tan(fov/2), principal point (W/2, H/2)
    with pixel k's centre at k + 0.5, i.e. OpenCV ((W-1)/2, (H-1)/2). cam_to_ego = camera_to_world @ GL_FROM_CV.
    Equirectangular frames ignore fov (nerfstudio's EQUIRECTANGULAR has our angular layout, docs/conventions.md).
    Other keys (seconds, fps, keyframes, crop, render_time, ...) are ignored. Errors: ConversionError with
    ``field`` = the JSON path ("render_width", "camera_path[2].fov", ...).
    """
    if not isinstance(doc, Mapping):
        raise _path_error("camera_path", "the document must be an object")
    W, H = _path_size(doc, "render_width"), _path_size(doc, "render_height")
    ctype = doc.get("camera_type", "perspective")
    if ctype not in _NS_PATH_TYPES:
        raise _path_error("camera_type", f"must be one of {', '.join(_NS_PATH_TYPES)} (got {ctype!r})")
    frames = doc.get("camera_path")
    if not isinstance(frames, list) or not frames:
        raise _path_error("camera_path", "must be a non-empty list")
    cams = []
    for k, fr in enumerate(frames):
        where = f"camera_path[{k}]"
        if not isinstance(fr, Mapping):
            raise _path_error(where, "must be an object")
        if "camera_to_world" not in fr:
            raise _path_error(f"{where}.camera_to_world", "is missing")
        c2w = _path_pose(fr["camera_to_world"], f"{where}.camera_to_world")
        K, model, lens = None, "pinhole", _NS_FISHEYE if ctype == "fisheye" else None
        if ctype == "equirectangular":
            model = "equirectangular"
        else:
            fov = fr.get("fov")
            if not _is_num(fov) or not 0 < fov < 180:
                raise _path_error(f"{where}.fov", f"must be a vertical field of view in (0, 180) degrees "
                                                  f"(got {fov!r})")
            f = (H / 2.0) / math.tan(math.radians(fov) / 2.0)
            K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
        try:
            cams.append(Camera(name=f"frame_{k:05d}", width=W, height=H, K=K, cam_to_ego=c2w @ GL_FROM_CV,
                               model=model, distortion=lens))
        except RigError as exc:  # the pose checks (bottom row, orthonormal rotation, det +1) of cam_to_ego
            raise _path_error(f"{where}.camera_to_world", exc.message) from None
    return cams


def _path_type(cam: Camera) -> str:
    """A camera's nerfstudio camera_type: perspective (an ideal pinhole), fisheye (the equidistant lens
    _NS_FISHEYE) or equirectangular; ConversionError for any other lens."""
    if cam.model == "equirectangular":
        return "equirectangular"
    if cam.distortion is None:
        return "perspective"
    if cam.distortion.to_json() == _NS_FISHEYE:
        return "fisheye"
    raise ConversionError("distortion", "a camera path holds ideal pinholes, nerfstudio's equidistant fisheye "
                                        f"(opencv_fisheye, k1..k4 = 0, max_angle_deg 180) or panoramas; got "
                                        f"{cam.distortion.to_json()}", f"camera {cam.name!r}")


def cameras_to_nerfstudio_path(cameras: Sequence[Camera], fps: float = 24.0) -> dict[str, Any]:
    """Cameras -> nerfstudio `camera_path.json` dict (inverse of cameras_from_nerfstudio_path).

    All cameras share one size and one model (the file has one render_width x render_height and one
    camera_type). Pinholes must be undistorted with fx = fy and the principal point at the image centre
    ((W-1)/2, (H-1)/2 within 1e-3 px), what a three.js camera expresses. Writes per frame camera_to_world
    (16 numbers, row-major, OpenGL axes), fov (vertical degrees; pinholes only) and aspect (W/H), and
    seconds = len / fps and fps (ns-render reads "seconds" for the video length)."""
    if not cameras:
        raise ConversionError("cameras", "need at least one camera", _NS_PATH)
    first = cameras[0]
    W, H, model = first.width, first.height, _path_type(first)
    frames = []
    for cam in cameras:
        where = f"camera {cam.name!r}"
        if (cam.width, cam.height, _path_type(cam)) != (W, H, model):
            raise ConversionError("width/height/model", f"a camera path has one size and model ({W}x{H} {model}; "
                                                        f"got {cam.width}x{cam.height} {_path_type(cam)})", where)
        fr: dict[str, Any] = {"camera_to_world": (cam.cam_to_ego @ GL_FROM_CV).reshape(-1).tolist()}
        if model != "equirectangular":
            K = cam.K
            if abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0]:
                raise ConversionError("K", "fx != fy, a camera path has square pixels", where)
            if abs(K[0, 2] - (W - 1) / 2) > _CENTRE_TOL_PX or abs(K[1, 2] - (H - 1) / 2) > _CENTRE_TOL_PX:
                raise ConversionError("K", "principal point must be the image centre ((W-1)/2, (H-1)/2)", where)
            fr["fov"] = math.degrees(2.0 * math.atan(H / (2.0 * K[1, 1])))   # from K: a fisheye's f too
        fr["aspect"] = W / H
        frames.append(fr)
    if not (math.isfinite(fps) and fps > 0):
        raise ConversionError("fps", f"must be > 0 (got {fps})", _NS_PATH)
    return {"camera_type": model,
            "render_width": W, "render_height": H, "fps": fps, "seconds": len(frames) / fps,
            "camera_path": frames}


# -- CARLA ---------------------------------------------------------------------------------------------------

def _carla_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """CARLA's Transform rotation (degrees) as a [3, 3] matrix, actor axes -> parent axes (CARLA's
    carla::geom::Transform::GetMatrix: yaw about z, pitch about y, roll about x, left-handed Unreal frame)."""
    p, y, r = (math.radians(a) for a in (pitch, yaw, roll))
    cp, sp, cy, sy, cr, sr = math.cos(p), math.sin(p), math.cos(y), math.sin(y), math.cos(r), math.sin(r)
    return np.array([
        [cp * cy, cy * sp * sr - sy * cr, -(cy * sp * cr + sy * sr)],
        [cp * sy, sy * sp * sr + cy * cr, cy * sr - sy * sp * cr],
        [sp, -cp * sr, cp * cr],
    ])


def camera_from_carla(sensor: Mapping[str, Any], name: str | None = None, image: str | None = None) -> Camera:
    """A CARLA camera sensor, relative to its vehicle, -> Camera in the ego frame.

    sensor: {"transform": {"location": {"x", "y", "z"} metres, "rotation": {"pitch", "yaw", "roll"} degrees},
             "fov": horizontal FoV degrees, "image_size_x": W, "image_size_y": H} (CARLA blueprint attribute
             names; an optional "name"). CARLA is left-handed (x forward, y right, z up); ego is y left, so
    cam_to_ego = [diag(1,-1,1) M(pitch,yaw,roll) UE_FROM_CV | diag(1,-1,1) location] (det +1).
    K: f = W / (2 tan(fov/2)) for both axes, principal point at the image centre ((W-1)/2, (H-1)/2) in
    OpenCV pixel coordinates (CARLA's examples use W/2, H/2: half a pixel off).
    """
    where = f"carla sensor {name or sensor.get('name') or ''!s}".rstrip()
    tf = sensor.get("transform")
    if not isinstance(tf, Mapping) or not isinstance(tf.get("location"), Mapping) \
            or not isinstance(tf.get("rotation"), Mapping):
        raise ConversionError("transform", "must hold location {x, y, z} and rotation {pitch, yaw, roll}", where)
    loc = [_num(tf["location"], k, where, "transform.location.") for k in ("x", "y", "z")]
    rot = [_num(tf["rotation"], k, where, "transform.rotation.") for k in ("pitch", "yaw", "roll")]
    fov = _num(sensor, "fov", where)
    if not 0 < fov < 180:
        raise ConversionError("fov", f"must be in (0, 180) degrees (got {fov})", where)
    W, H = _num(sensor, "image_size_x", where), _num(sensor, "image_size_y", where)
    if W != int(W) or H != int(H):
        raise ConversionError("image_size_x" if W != int(W) else "image_size_y",
                              f"image_size_x/y must be integers (got {W}, {H})", where)
    W, H = int(W), int(H)
    f = W / (2.0 * math.tan(math.radians(fov) / 2.0))
    K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    R = EGO_FROM_CARLA @ _carla_matrix(*rot) @ UE_FROM_CV
    extra = {k: v for k, v in sensor.items() if k not in ("transform", "fov", "image_size_x", "image_size_y", "name")}
    return Camera(name=name or str(sensor.get("name") or "carla_camera"), width=W, height=H, K=K,
                  cam_to_ego=_pose(R, EGO_FROM_CARLA @ np.array(loc)), image=image, extra=extra)


def camera_to_carla(camera: Camera) -> dict[str, Any]:
    """Camera -> CARLA sensor dict (inverse of camera_from_carla). Refuses cameras CARLA cannot express:
    non-square pixels, off-centre principal point (> 1e-3 px), distortion, equirectangular."""
    where = f"camera {camera.name!r}"
    if camera.model != "pinhole" or camera.distortion is not None:
        raise ConversionError("model" if camera.model != "pinhole" else "distortion",
                              "CARLA cameras are undistorted pinholes", where)
    K, W, H = camera.K, camera.width, camera.height
    if abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0]:
        raise ConversionError("K", "fx != fy, CARLA has square pixels", where)
    if abs(K[0, 2] - (W - 1) / 2) > _CARLA_TOL_PX or abs(K[1, 2] - (H - 1) / 2) > _CARLA_TOL_PX:
        raise ConversionError("K", "principal point must be the image centre ((W-1)/2, (H-1)/2) for CARLA", where)
    M = EGO_FROM_CARLA @ camera.rotation @ UE_FROM_CV.T
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, M[2, 0]))))
    if math.hypot(M[0, 0], M[1, 0]) > 1e-9:
        yaw = math.degrees(math.atan2(M[1, 0], M[0, 0]))
        roll = math.degrees(math.atan2(-M[2, 1], M[2, 2]))
    else:  # looking straight up/down: yaw and roll share one axis; put it all in yaw
        yaw, roll = math.degrees(math.atan2(-M[0, 1], M[1, 1])), 0.0
    x, y, z = (EGO_FROM_CARLA @ camera.position).tolist()
    return {"name": camera.name,
            "transform": {"location": {"x": x, "y": y, "z": z}, "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
            "fov": math.degrees(camera.horizontal_fov), "image_size_x": W, "image_size_y": H, **camera.extra}


# -- nuScenes ------------------------------------------------------------------------------------------------

def camera_from_nuscenes(record: Mapping[str, Any], name: str, width: int = 1600, height: int = 900,
                         image: str | None = None) -> Camera:
    """nuScenes `calibrated_sensor` record (camera) -> Camera. The record's translation [3] metres and rotation
    (w, x, y, z) map the OpenCV camera frame to the ego frame; camera_intrinsic is K. Image size is not in the
    record (sample_data holds it): 1600 x 900 for every nuScenes camera. Other keys (token, sensor_token)
    are kept in `extra`."""
    where = f"nuscenes calibrated_sensor {name!r}"
    for key in ("translation", "rotation", "camera_intrinsic"):
        if key not in record:
            raise ConversionError(key, "is missing", where)
    try:
        t = np.array(record["translation"], dtype=np.float64)
        q = np.array(record["rotation"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConversionError("translation/rotation", "must be numbers", where) from None
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ConversionError("translation", "must be 3 finite numbers", where)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or not abs(np.linalg.norm(q) - 1.0) < 1e-3:
        raise ConversionError("rotation", "must be a unit quaternion (w, x, y, z)", where)
    extra = {k: v for k, v in record.items() if k not in ("translation", "rotation", "camera_intrinsic")}
    try:
        return Camera(name=name, width=width, height=height, K=record["camera_intrinsic"],
                      cam_to_ego=_pose(quat_wxyz_to_matrix(q), t), image=image, extra=extra)
    except RigError as exc:
        raise _from_camera(exc, where) from None


def camera_to_nuscenes(camera: Camera) -> dict[str, Any]:
    """Camera -> nuScenes calibrated_sensor-style record (inverse of camera_from_nuscenes; w >= 0)."""
    if camera.model != "pinhole":
        raise ConversionError("model", "nuScenes cameras are pinholes", camera.where)
    return {**camera.extra, "translation": camera.position.tolist(),
            "rotation": matrix_to_quat_wxyz(camera.rotation).tolist(), "camera_intrinsic": camera.K.tolist()}


# -- Waymo completion ----------------------------------------------------------------------------------------

def mirror_camera(camera: Camera, plane_x: float, name: str) -> Camera:
    """The virtual camera that sees, in the horizontally flipped image, the world mirrored across the plane
    x = plane_x (ego frame, perpendicular to ego x).

    A point P seen at pixel (u, v) by `camera` is seen at (W-1-u, v) by the result after mirroring the point to
    S P + (2 plane_x, 0, 0), S = diag(-1, 1, 1). Pose: R' = S R F, t' = S t + (2 plane_x, 0, 0) with
    F = diag(-1, 1, 1) in the camera frame (det +1 again); K: cx' = W-1-cx.
    """
    if camera.model != "pinhole" or camera.distortion is not None:
        raise ConversionError("model" if camera.model != "pinhole" else "distortion",
                              "only undistorted pinhole cameras can be mirrored", camera.where)
    S = np.diag([-1.0, 1.0, 1.0])
    R = S @ camera.rotation @ S  # S doubles as the camera-frame x flip F
    t = S @ camera.position + [2.0 * plane_x, 0.0, 0.0]
    K = camera.K.copy()
    K[0, 2] = camera.width - 1 - K[0, 2]
    return Camera(name=name, width=camera.width, height=camera.height, K=K, cam_to_ego=_pose(R, t),
                  extra={"virtual": f"mirror of {camera.name} across x = {plane_x:.6g}"})


def complete_waymo_rig(rig: Rig, images: Sequence[np.ndarray], names: Mapping[str, str] = WAYMO_NAMES
                       ) -> tuple[Rig, list[np.ndarray]]:
    """The paper's zero-shot completion of Waymo's 5 cameras to 8 (appendix, "More Zero-shot Visualization").

    rig: holds the cameras named names["front"], ["front_left"], ["front_right"], ["side_left"],
    ["side_right"] (other cameras are refused); images: one [H, W, C] array per rig camera, rig order.
    All five are mirrored across the lateral plane x = mean x of the five camera centres (mirror_camera, with
    horizontally flipped images). The 3 mirrored front cameras become REAR, REAR_LEFT, REAR_RIGHT; the 2
    mirrored side cameras replace the real side cameras (the paper's "flip the side images along the vertical
    centre line": exact when a side camera looks perpendicular to x). Output order is clockwise seen from
    above starting at the front (FRONT, FRONT_RIGHT, SIDE_RIGHT, REAR_RIGHT, REAR, REAR_LEFT, SIDE_LEFT,
    FRONT_LEFT), the F+ order. Virtual cameras have image = None; their arrays are in the returned list.
    """
    roles = ("front", "front_left", "front_right", "side_left", "side_right")
    if set(rig.names) != {names[r] for r in roles} or len(rig) != 5:
        raise ConversionError("cameras", f"must be exactly {[names[r] for r in roles]} (got {rig.names})", "rig")
    if len(images) != len(rig):
        raise ConversionError("images", f"need {len(rig)} images, one per camera (got {len(images)})")
    by_role = {r: rig.camera(names[r]) for r in roles}
    img = {r: np.asarray(images[rig.names.index(names[r])]) for r in roles}
    for r in roles:
        if img[r].shape[:2] != (by_role[r].height, by_role[r].width):
            raise ConversionError("image", f"is {img[r].shape[1]}x{img[r].shape[0]}, but width x height is "
                                           f"{by_role[r].width}x{by_role[r].height}", by_role[r].where)
    plane_x = float(np.mean([c.position[0] for c in by_role.values()]))
    virtual = {"rear": ("front", "REAR"), "rear_left": ("front_left", "REAR_LEFT"),
               "rear_right": ("front_right", "REAR_RIGHT"), "side_left": ("side_left", names["side_left"]),
               "side_right": ("side_right", names["side_right"])}
    cams = {r: by_role[r] for r in ("front", "front_left", "front_right")}
    imgs = {r: img[r] for r in cams}
    for r, (src, nm) in virtual.items():
        cams[r] = mirror_camera(by_role[src], plane_x, nm)
        imgs[r] = np.ascontiguousarray(img[src][:, ::-1])
    order = ("front", "front_right", "side_right", "rear_right", "rear", "rear_left", "side_left", "front_left")
    out = Rig(cameras=tuple(cams[r] for r in order), root=rig.root,
              extra={**rig.extra, "waymo_completion": f"mirrored across x = {plane_x:.6g} (docs/conventions.md)"})
    return out, [imgs[r] for r in order]
