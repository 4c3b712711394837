"""The SensorsimService's messages to and from the runtime's terms: poses, cameras, render requests. No gRPC here
(only the generated message classes), no I/O: every function is a pure conversion, and every refusal is a
common.wire.ViewError naming the protocol field at fault (``camera_intrinsics.opencv_pinhole_param
.focal_length_x``, ``sensor_pose.start_pose.quat``, ``items[2].request.resolution_w``), which the servicer answers
as INVALID_ARGUMENT.

The frame chain (docs/simulators.md states it for users):

    cam_to_ego = inv(E) @ S_mid @ A

- S_mid: the request's ``sensor_pose`` (camera -> the scene's local frame: AlpaSim's per-scene ENU frame) at the
  middle of the exposure: translation halfway, rotation halfway along the arc between start_pose and end_pose
  (a rolling shutter is rendered as a global one at mid-exposure; end_pose unset: start_pose);
- E: the scene's ``ego_to_world`` (rig.json; ``ego_to_global`` accepted too): where the ego of the reconstructed
  rig stood in that local frame (identity when the rig has none: the local frame is then the scene's ego frame);
- A = CAMERA_AXES: the protocol's camera frame -> ours. Both are OpenCV's (x right, y down, z forward; NuRec and
  AlpaSim's renderers take the sensor pose as an OpenCV camera-to-world), so A is the identity, kept in the formula
  so that the chain reads whole;
- cam_to_ego: our camera -> ego (docs/conventions.md "Frames and cameras"), the pose of a render camera.

LiDAR (render_lidar; docs/simulators.md "LiDAR"): lidar_to_ego = inv(E) @ S @ LIDAR_AXES for each of the spin's
start_pose and end_pose (the LiDAR frame: x forward, y left, z up, the sensor's own; LIDAR_AXES the identity, as
CAMERA_AXES), and the points are answered in the end-of-spin LiDAR frame.

get_available_cameras answers each rig camera's cam_to_ego @ inv(A) as the camera -> rig pose (the protocol's
``rig_to_camera``, named the other way round): AlpaSim's rig frame (x forward, y left, z up) has our ego frame's
axes, and its origin is then ours (the rig's, e.g. the rear axle on the ground for nuScenes-style rigs).

Time (docs/simulators.md "Time"): a request's exposure [frame_start_us, frame_end_us] (microseconds on the rigs'
clock, the clock of a drive's frames' ``timestamp_s``) is rendered at its middle, (start + end) / 2 / 1e6 seconds,
passed on as the view's time as GET's ``time=`` is; both unset (0): no time (the scene's start). The scene decides
what a time changes (runtime.scene.Scene.gaussians_at: a drive's moving objects; a static scene ignores it).
get_available_trajectories answers the scene's frames (runtime.scene.Scene.timeline) as the rig's poses in the
local frame at their times: the same frame chain read the other way, so a trajectory pose composed with a camera's
``rig_to_camera`` is a sensor pose that renders that frame's camera.

Intrinsics: a CameraSpec holds the camera at its native resolution (camera_intrinsics.resolution_w x _h); the
request's resolution_w x resolution_h is the image asked for, and the camera is rescaled to it with
runtime.camera.Camera.resized (pixel centres: cx' = sx (cx + 1/2) - 1/2, fx' = sx fx; the f-theta polynomials as
NVIDIA's ncore scales them). Principal points count from the first pixel's centre, as ours (docs/conventions.md
"Lens models"). Lenses become the rig.json lens objects of runtime.lenses: opencv_pinhole_param with non-zero
coefficients an "opencv" lens, opencv_fisheye_param an "opencv_fisheye" lens, ftheta_param an "ftheta" lens."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from pydantic import ValidationError
from xyzcyl.common.errors import FieldError
from xyzcyl.common.wire import ActorEdit, ViewError
from xyzcyl.runtime.camera import Camera, check_render_size, pinhole_K
from xyzcyl.runtime.lenses import FISHEYE_NAMES, OPENCV_NAMES, fisheye_max_angle_deg
from xyzcyl.runtime.lidarsim import PROTO_MODELS, LidarRequest, LidarSweep, lidar_model
from xyzcyl.runtime.rig import Rig
from xyzcyl.runtime.rotations import quat_to_rotmat, rotmat_to_quat
from xyzcyl.runtime.views import ViewRequest

from . import common_pb2, sensorsim_pb2

CAMERA_AXES = np.eye(4)             # the protocol's camera frame -> ours: both OpenCV (module docstring)
LIDAR_AXES = np.eye(4)              # the protocol's LiDAR frame -> ours: both x forward, y left, z up (module docstring)
QUAT_NORM_TOL = 1e-2                # a quaternion whose norm is off 1 by more is refused, not silently normalised
FORMATS = {sensorsim_pb2.PNG: "png", sensorsim_pb2.JPEG: "jpeg", sensorsim_pb2.UNDEFINED: "png"}
DEFAULT_QUALITY = 90                # image_quality 0 (unset)
PARAMS = ("opencv_pinhole_param", "opencv_fisheye_param", "ftheta_param")
_REFERENCE = {sensorsim_pb2.FthetaCameraParam.PIXELDIST_TO_ANGLE: "pixeldist_to_angle",
              sensorsim_pb2.FthetaCameraParam.ANGLE_TO_PIXELDIST: "angle_to_pixeldist"}
_REFERENCE_BACK = {v: k for k, v in _REFERENCE.items()}
_RADIAL = ("k1", "k2", "k3", "k4", "k5", "k6")


# ------------------------------------------------------------------------------------------- poses

def pose_matrix(pose: common_pb2.Pose, field: str) -> np.ndarray:
    """[4, 4] float64 of a common.Pose (child -> parent: R(quat) p + vec). ViewError naming ``field`` (or its
    ``.quat`` / ``.vec``) for non-finite numbers or a quaternion that is not of unit norm (a zero one: unset)."""
    q = np.array([pose.quat.w, pose.quat.x, pose.quat.y, pose.quat.z], dtype=np.float64)
    t = np.array([pose.vec.x, pose.vec.y, pose.vec.z], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise ViewError(f"{field}.vec", f"must be finite (got {t.tolist()})")
    n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else math.nan
    if n == 0.0:
        raise ViewError(f"{field}.quat", "is zero (the pose is not set)")
    if not abs(n - 1.0) <= QUAT_NORM_TOL:
        raise ViewError(f"{field}.quat", f"must be a unit quaternion (w, x, y, z) (got norm {n:.6g})")
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(q)
    T[:3, 3] = t
    return T


def _is_set(pose: common_pb2.Pose) -> bool:
    q = pose.quat
    return any(v != 0.0 for v in (q.w, q.x, q.y, q.z, pose.vec.x, pose.vec.y, pose.vec.z))


def mid_exposure(pair: sensorsim_pb2.PosePair, field: str) -> np.ndarray:
    """[4, 4] the pose at the middle of the exposure: translation halfway between start_pose and end_pose,
    rotation halfway along the shorter arc (the normalised sum of the two unit quaternions, made to agree in sign,
    is the slerp at t = 1/2). end_pose unset (all zero): start_pose."""
    start = pose_matrix(pair.start_pose, f"{field}.start_pose")
    if not _is_set(pair.end_pose):
        return start
    end = pose_matrix(pair.end_pose, f"{field}.end_pose")
    q0, q1 = rotmat_to_quat(start[:3, :3]), rotmat_to_quat(end[:3, :3])
    if float(q0 @ q1) < 0:
        q1 = -q1
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(q0 + q1)
    T[:3, 3] = 0.5 * (start[:3, 3] + end[:3, 3])
    return T


def exposure_time(start_us: int, end_us: int, prefix: str = "") -> float | None:
    """Seconds on the rigs' clock of an exposure [start_us, end_us] (microseconds; the protocol's frame_start_us,
    frame_end_us): its middle. Both 0 (unset): None (no time); end 0: the start. ViewError naming
    ``frame_end_us`` when the exposure ends before it starts."""
    start, end = int(start_us), int(end_us)
    if start == 0 and end == 0:
        return None
    if end == 0:
        return start / 1e6
    if end < start:
        raise ViewError(f"{prefix}frame_end_us", f"{end} is before frame_start_us {start} (microseconds)")
    return (start + end) / 2e6       # integers added exactly; one rounding to float64 (0.2 us at 1.6e9 s)


def trajectory_message(times_s: np.ndarray, poses: np.ndarray) -> common_pb2.Trajectory:
    """A common.Trajectory of rig -> local frame poses ([F, 4, 4]) at ``times_s`` ([F], seconds on the rigs' clock;
    written as whole microseconds)."""
    return common_pb2.Trajectory(poses=[
        common_pb2.PoseAtTime(pose=pose_message(T), timestamp_us=max(0, round(float(t) * 1e6)))
        for t, T in zip(np.asarray(times_s, np.float64), np.asarray(poses, np.float64))])


def pose_message(T: np.ndarray) -> common_pb2.Pose:
    """A common.Pose of a rigid [4, 4] (float32 on the wire)."""
    w, x, y, z = (float(v) for v in rotmat_to_quat(np.asarray(T, np.float64)[:3, :3]))
    tx, ty, tz = (float(v) for v in np.asarray(T, np.float64)[:3, 3])
    return common_pb2.Pose(vec=common_pb2.Vec3(x=tx, y=ty, z=tz), quat=common_pb2.Quat(w=w, x=x, y=y, z=z))


def scene_ego_to_world(rig: Rig) -> np.ndarray:
    """[4, 4] the scene's ego pose in the simulator's local frame: the rig's ``ego_to_world`` (or
    ``ego_to_global``), identity when it has none (POST /v1/scenes checked it: server/uploads.py)."""
    return np.eye(4) if rig.ego_to_world is None else rig.ego_to_world


def cam_to_ego(sensor_pose: np.ndarray, ego_pose: np.ndarray) -> np.ndarray:
    """The frame chain (module docstring): inv(ego_to_world) @ sensor pose @ CAMERA_AXES."""
    return np.linalg.inv(ego_pose) @ sensor_pose @ CAMERA_AXES


def actor_edits(objects, ego_pose: np.ndarray, prefix: str = "") -> tuple[ActorEdit, ...]:
    """A request's ``dynamic_objects`` as the view's actor edits (common.wire.ActorEdit): each listed track drawn at
    its box pose at the middle of the exposure (mid_exposure of its pose_pair: box -> local frame), in the scene's
    frame (inv(ego_to_world) @ that pose). Tracks the request does not list are drawn where the recording has them,
    as NVIDIA's renderer draws them (docs/simulators.md "Actors"). ViewError naming
    ``dynamic_objects[i].track_id`` / ``.pose_pair``; the scene checks the ids and how far the poses are
    (runtime.scene.Scene.check_actors: rename_actor_field names its errors by these fields)."""
    out = []
    E_inv = np.linalg.inv(ego_pose)
    for i, obj in enumerate(objects):
        where = f"{prefix}dynamic_objects[{i}]"
        if not obj.track_id:
            raise ViewError(f"{where}.track_id", "is empty: give a track id of the scene (its actors)")
        if not obj.HasField("pose_pair"):
            raise ViewError(f"{where}.pose_pair", "is not set (the object's box pose at the exposure's start and "
                                                  "end)")
        T = E_inv @ mid_exposure(obj.pose_pair, f"{where}.pose_pair")
        try:
            out.append(ActorEdit(id=obj.track_id, pose=tuple(float(x) for x in T.ravel())))
        except ValidationError as e:
            first = e.errors()[0]
            key = {"id": "track_id", "pose": "pose_pair"}.get(str(first["loc"][0]) if first["loc"] else "", "")
            raise ViewError(f"{where}.{key or 'track_id'}", first["msg"]) from None
    return tuple(out)


def rename_actor_field(field: str) -> str:
    """The protocol field of a scene's refusal of an actor edit ("dynamic_objects[2].id" -> ".track_id", ".pose"
    -> ".pose_pair")."""
    for ours, theirs in ((".id", ".track_id"), (".pose", ".pose_pair")):
        if field.endswith(ours):
            return field[: -len(ours)] + theirs
    return field


# ------------------------------------------------------------------------------------------- cameras: rig -> spec

def camera_spec(cam: Camera) -> sensorsim_pb2.CameraSpec | None:
    """A rig camera as the protocol's CameraSpec at its native resolution (None for an equirectangular camera,
    which the protocol cannot describe). The shutter is GLOBAL: the renderer draws every pixel at one pose."""
    spec = sensorsim_pb2.CameraSpec(logical_id=cam.name or "", resolution_w=cam.width, resolution_h=cam.height,
                                    shutter_type=sensorsim_pb2.GLOBAL)
    if cam.is_equirect:
        return None
    fx, fy, cx, cy = (float(cam.K[0, 0]), float(cam.K[1, 1]), float(cam.K[0, 2]), float(cam.K[1, 2]))
    lens = cam.distortion
    if lens is None or lens.model == "opencv":
        p = spec.opencv_pinhole_param
        p.focal_length_x, p.focal_length_y, p.principal_point_x, p.principal_point_y = fx, fy, cx, cy
        if lens is not None:
            c = dict(zip(OPENCV_NAMES, lens.coeffs))
            p.radial_coeffs.extend(c[k] for k in _RADIAL)
            p.tangential_coeffs.extend((c["p1"], c["p2"]))
            p.thin_prism_coeffs.extend(c[k] for k in ("s1", "s2", "s3", "s4"))
    elif lens.model == "opencv_fisheye":
        p = spec.opencv_fisheye_param
        p.focal_length_x, p.focal_length_y, p.principal_point_x, p.principal_point_y = fx, fy, cx, cy
        p.radial_coeffs.extend(lens.coeffs)
        p.max_angle = math.radians(lens.max_angle_deg)
    else:
        p = spec.ftheta_param
        p.principal_point_x, p.principal_point_y = cx, cy
        p.pixeldist_to_angle_poly.extend(lens.pixeldist_to_angle_poly)
        p.angle_to_pixeldist_poly.extend(lens.angle_to_pixeldist_poly)
        if lens.reference_poly is not None:
            p.reference_poly = _REFERENCE_BACK[lens.reference_poly]
        p.max_angle = math.radians(lens.max_angle_deg)
        c, d, e = lens.linear_cde
        p.linear_cde.CopyFrom(sensorsim_pb2.LinearCde(linear_c=c, linear_d=d, linear_e=e))
    return spec


def available_cameras(rig: Rig) -> list[sensorsim_pb2.AvailableCamerasReturn.AvailableCamera]:
    """Every camera of the scene's rig the protocol can describe, with its camera -> rig pose (module
    docstring)."""
    out = []
    for cam in rig.cameras:
        spec = camera_spec(cam)
        if spec is not None:
            pose = pose_message(np.asarray(cam.cam_to_ego, np.float64) @ np.linalg.inv(CAMERA_AXES))
            out.append(sensorsim_pb2.AvailableCamerasReturn.AvailableCamera(intrinsics=spec, rig_to_camera=pose,
                                                                              logical_id=cam.name or ""))
    return out


# ------------------------------------------------------------------------------------------- requests -> views

def _coeffs(values, names: tuple[str, ...], field: str) -> dict[str, float]:
    if len(values) > len(names):
        raise ViewError(field, f"at most {len(names)} coefficients ({', '.join(names)}; got {len(values)})")
    return dict(zip(names, (float(v) for v in values)))


def _lens(which: str, p: Any, field: str) -> tuple[tuple[float, float, float, float], dict[str, Any] | None,
                                                   Mapping[str, str]]:
    """(fx, fy, cx, cy) at the native resolution, the rig.json lens object (None: an ideal pinhole) and how the
    lens's rig.json fields map back to the protocol's (for errors)."""
    if which == "opencv_pinhole_param":
        c = {**_coeffs(p.radial_coeffs, _RADIAL, f"{field}.radial_coeffs"),
             **_coeffs(p.tangential_coeffs, ("p1", "p2"), f"{field}.tangential_coeffs"),
             **_coeffs(p.thin_prism_coeffs, ("s1", "s2", "s3", "s4"), f"{field}.thin_prism_coeffs")}
        lens = {"model": "opencv", **c} if any(v != 0.0 for v in c.values()) else None
        back = {**{k: f"{field}.radial_coeffs[{i}]" for i, k in enumerate(_RADIAL)},
                "p1": f"{field}.tangential_coeffs[0]", "p2": f"{field}.tangential_coeffs[1]",
                **{f"s{i + 1}": f"{field}.thin_prism_coeffs[{i}]" for i in range(4)}}
        return (p.focal_length_x, p.focal_length_y, p.principal_point_x, p.principal_point_y), lens, back
    if which == "opencv_fisheye_param":
        k = _coeffs(p.radial_coeffs, FISHEYE_NAMES, f"{field}.radial_coeffs")
        ks = [k.get(n, 0.0) for n in FISHEYE_NAMES]
        if not all(math.isfinite(v) for v in ks):
            raise ViewError(f"{field}.radial_coeffs", f"must be finite (got {ks})")
        # max_angle 0 (unset): the widest the coefficients allow, as for nerfstudio's OPENCV_FISHEYE
        angle = math.degrees(p.max_angle) if p.max_angle else fisheye_max_angle_deg(ks)
        lens = {"model": "opencv_fisheye", **dict(zip(FISHEYE_NAMES, ks)), "max_angle_deg": angle}
        back = {**{n: f"{field}.radial_coeffs[{i}]" for i, n in enumerate(FISHEYE_NAMES)},
                "max_angle_deg": f"{field}.max_angle"}
        return (p.focal_length_x, p.focal_length_y, p.principal_point_x, p.principal_point_y), lens, back
    fw, bw = [float(v) for v in p.angle_to_pixeldist_poly], [float(v) for v in p.pixeldist_to_angle_poly]
    lens = {"model": "ftheta", "max_angle_deg": math.degrees(p.max_angle)}
    if p.reference_poly in _REFERENCE:
        lens["reference_poly"] = _REFERENCE[p.reference_poly]
    if fw:
        lens["angle_to_pixeldist_poly"] = fw
    if bw:
        lens["pixeldist_to_angle_poly"] = bw
    cde = p.linear_cde
    if p.HasField("linear_cde") and (cde.linear_c, cde.linear_d, cde.linear_e) != (0.0, 0.0, 0.0):
        lens["linear_cde"] = [cde.linear_c, cde.linear_d, cde.linear_e]
    # K's focal length is the lens's paraxial one (docs/conventions.md "Lens models"): the renderer of an
    # ideal camera and the background need one; the lens itself does not use it
    ref = lens.get("reference_poly") or ("angle_to_pixeldist" if fw else "pixeldist_to_angle")
    poly = fw if ref == "angle_to_pixeldist" else bw
    slope = poly[1] if len(poly) > 1 else 0.0
    f = (slope if ref == "angle_to_pixeldist" else 1.0 / slope) if slope > 0 and math.isfinite(slope) else 1.0
    back = {"max_angle_deg": f"{field}.max_angle", "reference_poly": f"{field}.reference_poly",
            "angle_to_pixeldist_poly": f"{field}.angle_to_pixeldist_poly",
            "pixeldist_to_angle_poly": f"{field}.pixeldist_to_angle_poly", "linear_cde": f"{field}.linear_cde"}
    return (f, f, p.principal_point_x, p.principal_point_y), lens, back


def _lens_field(e: FieldError, back: Mapping[str, str], param: str) -> str:
    """The protocol field of a runtime lens error ("distortion.k1" -> "...radial_coeffs[0]")."""
    sub = e.field.removeprefix("distortion").lstrip(".")
    name, _, rest = sub.partition("[")
    if name in back:
        return back[name] + (f"[{rest}" if rest else "")
    return param


def _size(req: sensorsim_pb2.RGBRenderRequest, spec: sensorsim_pb2.CameraSpec, p: str) -> tuple[int, int, int, int]:
    """(native W, H, asked W, H): a size not asked (0) is the native one, one side asked follows the native aspect;
    a camera without a native size is taken at the size asked (no rescale)."""
    nw, nh, w, h = spec.resolution_w, spec.resolution_h, req.resolution_w, req.resolution_h
    if not nw or not nh:
        if not w or not h:
            raise ViewError(f"{p}resolution_w", "is 0, and so is the camera's (camera_intrinsics.resolution_w x "
                                                "resolution_h): give the image size")
        return w, h, w, h
    if w and not h:
        h = max(1, round(w * nh / nw))
    elif h and not w:
        w = max(1, round(h * nw / nh))
    return nw, nh, w or nw, h or nh


def quality(value: float, field: str) -> int:
    """JPEG quality 1..100 of the protocol's float: 0 (unset) -> DEFAULT_QUALITY, (0, 1] a fraction (some clients
    send 0.95), (1, 100] a percentage (AlpaSim sends 95)."""
    q = float(value)
    if q == 0.0:
        return DEFAULT_QUALITY
    if not (math.isfinite(q) and 0.0 < q <= 100.0):
        raise ViewError(field, f"must be in (0, 1] (a fraction) or (1, 100] (a percentage) (got {q:g})")
    return max(1, min(100, round(q * 100 if q <= 1.0 else q)))


def view_request(req: sensorsim_pb2.RGBRenderRequest, ego_pose: np.ndarray, prefix: str = "") -> ViewRequest:
    """The runtime ViewRequest of an RGBRenderRequest: its camera (made here, in the ego frame, from the protocol's
    intrinsics and mid-exposure pose; no rig needed), PNG or JPEG, the quality and the mid-exposure time
    (exposure_time). ``ego_pose``: the scene's
    ego_to_world; ``prefix``: the request's path in the call ("items[2].request."). Refusals (ViewError) name the
    protocol field; a view over the render limit names resolution_w / resolution_h."""
    p = prefix
    ci = req.camera_intrinsics
    which = ci.WhichOneof("camera_param")
    if not req.HasField("camera_intrinsics") or which is None:
        raise ViewError(f"{p}camera_intrinsics.camera_param", f"is not set: give one of {', '.join(PARAMS)}")
    param = f"{p}camera_intrinsics.{which}"
    if ci.WhichOneof("external_distortion") is not None:
        raise ViewError(f"{p}camera_intrinsics.bivariate_windshield_model_param",
                        "windshield distortion is not supported")
    if req.insert_ego_mask:
        raise ViewError(f"{p}insert_ego_mask", "this renderer has no ego masks (get_available_ego_masks lists none)")
    fmt = FORMATS.get(req.image_format)
    if fmt is None:
        known = sensorsim_pb2.ImageFormat.values()
        what = sensorsim_pb2.ImageFormat.Name(req.image_format) if req.image_format in known else req.image_format
        raise ViewError(f"{p}image_format", f"{what} is not supported: PNG or JPEG")
    q = quality(req.image_quality, f"{p}image_quality")
    if not req.HasField("sensor_pose"):
        raise ViewError(f"{p}sensor_pose", "is not set (the camera's pose at the exposure's start and end)")
    T = cam_to_ego(mid_exposure(req.sensor_pose, f"{p}sensor_pose"), ego_pose)
    time_s = exposure_time(req.frame_start_us, req.frame_end_us, p)
    nw, nh, w, h = _size(req, ci, p)
    (fx, fy, cx, cy), lens, back = _lens(which, getattr(ci, which), param)
    names = {"fx": f"{param}.focal_length_x", "fy": f"{param}.focal_length_y", "cx": f"{param}.principal_point_x",
             "cy": f"{param}.principal_point_y"}
    for key, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if not math.isfinite(v) or (key in ("fx", "fy") and v <= 0):
            raise ViewError(names[key], f"must be finite{' and > 0' if key in ('fx', 'fy') else ''} (got {v})")
    try:
        cam = Camera(K=pinhole_K(fx, fy, cx, cy), cam_to_ego=T, width=nw, height=nh, distortion=lens)
    except FieldError as e:
        if e.root_field == "distortion":
            raise ViewError(_lens_field(e, back, param), e.message) from None
        field = {"width": f"{p}camera_intrinsics.resolution_w", "height": f"{p}camera_intrinsics.resolution_h",
                 "cam_to_ego": f"{p}sensor_pose"}.get(e.root_field, param)
        raise ViewError(field, e.message) from None
    if (w, h) != (nw, nh):
        try:
            cam = cam.resized(w, h)
        except FieldError as e:
            raise ViewError(f"{p}resolution_{'h' if e.root_field == 'height' else 'w'}", e.message) from None
    try:
        check_render_size(cam.width, cam.height)
    except FieldError as e:
        raise ViewError(f"{p}resolution_{'w' if cam.width >= cam.height else 'h'}", e.message) from None
    return ViewRequest(cam, "rgb", fmt, q, time_s, actor_edits(req.dynamic_objects, ego_pose, p))

# ------------------------------------------------------------------------------------------- LiDAR

def lidar_request(req: sensorsim_pb2.LidarRenderRequest, ego_pose: np.ndarray, prefix: str = "") -> LidarRequest:
    """The runtime LidarRequest of a LidarRenderRequest (runtime.lidarsim; docs/simulators.md "LiDAR"): the model of
    ``lidar_config.lidar_type`` (PANDAR128, AT128: nominal layouts), the LiDAR's pose at the spin's start and end in
    the scene's frame (``lidar_to_ego`` = inv(ego_to_world) @ sensor pose @ LIDAR_AXES, each of start_pose and
    end_pose; end_pose unset: the LiDAR is still), the time of the middle of the spin (exposure_time of
    frame_start_us..frame_end_us) and the actor edits of ``dynamic_objects`` (at the middle of the spin, as RGB's).
    ViewError naming the protocol field."""
    p = prefix
    kind = req.lidar_config.lidar_type
    if kind not in range(len(PROTO_MODELS)):
        raise ViewError(f"{p}lidar_config.lidar_type", f"{kind} is not a LidarDeviceType (PANDAR128 = 0, AT128 = 1)")
    if not req.HasField("sensor_pose"):
        raise ViewError(f"{p}sensor_pose", "is not set (the LiDAR's pose at the spin's start and end)")
    start = pose_matrix(req.sensor_pose.start_pose, f"{p}sensor_pose.start_pose")
    end = (pose_matrix(req.sensor_pose.end_pose, f"{p}sensor_pose.end_pose") if _is_set(req.sensor_pose.end_pose)
           else start)
    E_inv = np.linalg.inv(ego_pose)
    time_s = exposure_time(req.frame_start_us, req.frame_end_us, p)
    return LidarRequest(lidar_model(PROTO_MODELS[kind]), E_inv @ start @ LIDAR_AXES, E_inv @ end @ LIDAR_AXES,
                        time_s, actor_edits(req.dynamic_objects, ego_pose, p))


def lidar_return(sweep: LidarSweep) -> sensorsim_pb2.LidarRenderReturn:
    """A LidarRenderReturn of a sweep: num_points and the points (x, y, z in the end-of-spin LiDAR frame, metres) and
    intensities ([0, 1], runtime.lidarsim's luminance proxy) as little-endian float32 buffers. The repeated
    point_xyzs / point_intensities stay empty: AlpaSim's and CARLA's clients read the buffers first (and fall back
    to the repeated fields), NVIDIA's NRE answers the buffers alone, and both forms of a Pandar128 sweep (7.4 MB)
    would pass gRPC's default 4 MB receive limit where the buffers alone (3.7 MB at most) do not."""
    xyz = np.ascontiguousarray(sweep.points, dtype="<f4")
    inten = np.ascontiguousarray(sweep.intensity, dtype="<f4")
    return sensorsim_pb2.LidarRenderReturn(num_points=len(sweep), point_xyzs_buffer=xyz.tobytes(),
                                           point_intensities_buffer=inten.tobytes())


__all__ = ["CAMERA_AXES", "LIDAR_AXES", "actor_edits", "lidar_request", "lidar_return", "available_cameras", "rename_actor_field", "cam_to_ego", "camera_spec", "exposure_time", "mid_exposure",
           "pose_matrix", "pose_message", "quality", "scene_ego_to_world", "trajectory_message", "view_request"]
