"""Camera rigs for synthetic scenes (inputs) and the target cameras of the two task settings.

Mount convention: a camera mount is (name, position xyz m in the ego frame, yaw, pitch, roll in degrees,
horizontal FoV deg or normalised intrinsics). cam_to_ego = [Rz(yaw) Ry(-pitch) Rx(roll) R0 | position] with
R0 the camera-to-ego rotation of a camera looking along ego +x (camera x -> ego -y, y -> -z, z -> +x); yaw is
counter-clockwise seen from above, pitch > 0 looks up.

Presets (all pinhole, images of the requested width x height):
- "nuscenes": the mounts and intrinsics of the nuScenes sample in ../shared/data/real/nuscenes_ca9a282c
  (rounded to 1 mm / 0.001 deg / 1e-5), intrinsics scaled to the requested size (fx * W/1600, fy * H/900);
  its real FoVs are 64.3-65.0 deg (front/side) and 89.3 deg (back) horizontally.
- "carla-centric": the same mounts with the nominal FoVs of the paper's Carla-Centric set: 5 x 70 deg and 110 deg
  (back), square pixels, principal point at the image centre.
- "pandaset": the mounts and intrinsics of ../shared/data/real/pandaset_002_00 (front 52 deg + 5 x 92 deg real
  FoVs), scaled like nuscenes.
- "waymo": 5 cameras (front, front-left/right at +-45 deg, side-left/right at +-90 deg), 50 deg each.
- "once": 6 ring cameras every 60 deg, 90 deg each (the ONCE ring; its wide-angle camera is left out).
- "argoverse": 7 ring cameras every 360/7 deg, 69 deg each.
- any rig JSON file (shared format): its mounts, with K scaled from its image size to the requested size.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.errors import RigError

R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """[3,3] camera-to-ego rotation of a mount (see module docstring)."""
    a, b, c = (math.radians(x) for x in (yaw_deg, pitch_deg, roll_deg))
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[math.cos(-b), 0, math.sin(-b)], [0, 1, 0], [-math.sin(-b), 0, math.cos(-b)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    return Rz @ Ry @ Rx @ R0


def pose(position, yaw_deg, pitch_deg=0.0, roll_deg=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation(yaw_deg, pitch_deg, roll_deg)
    T[:3, 3] = position
    return T


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_to_ego [4,4] of a camera at `eye` looking at `target` (ego metres), image up = ego +z side."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:
        x = np.array([0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def K_from_fov(hfov_deg: float, width: int, height: int) -> np.ndarray:
    """Square pixels, principal point at the image centre ((W-1)/2, (H-1)/2)."""
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def K_scaled(fxn: float, fyn: float, cxn: float, cyn: float, width: int, height: int) -> np.ndarray:
    """From normalised intrinsics (fx/W, fy/H, (cx+0.5)/W, (cy+0.5)/H)."""
    return np.array([[fxn * width, 0.0, cxn * width - 0.5], [0.0, fyn * height, cyn * height - 0.5], [0, 0, 1.0]])


# name, x, y, z (m), yaw, pitch, roll (deg), fx/W, fy/H, (cx+.5)/W, (cy+.5)/H   -- from the real samples' rig.json
NUSCENES = (
    ("CAM_FRONT", 1.701, 0.016, 1.511, 0.325, -0.323, -0.046, 0.79151, 1.40713, 0.51048, 0.54667),
    ("CAM_FRONT_RIGHT", 1.551, -0.493, 1.496, -56.397, -0.782, 0.519, 0.78803, 1.40094, 0.50529, 0.55093),
    ("CAM_BACK_RIGHT", 1.015, -0.481, 1.562, -110.789, -0.932, 0.619, 0.78720, 1.39946, 0.50485, 0.55744),
    ("CAM_BACK", 0.028, 0.003, 1.579, 179.857, 0.959, 0.229, 0.50576, 0.89913, 0.51857, 0.53586),
    ("CAM_BACK_LEFT", 1.036, 0.485, 1.591, 108.597, -0.917, -0.215, 0.78546, 1.39638, 0.49538, 0.54808),
    ("CAM_FRONT_LEFT", 1.524, 0.495, 1.509, 55.161, 0.140, 0.121, 0.79537, 1.41400, 0.51695, 0.53361),
)
PANDASET = (
    ("front_camera", 0.847, -0.001, 1.807, 0.251, 0.186, -1.080, 1.02605, 1.82408, 0.50547, 0.44796),
    ("front_right_camera", 1.484, -0.602, 1.603, -57.812, 0.867, 0.567, 0.48440, 0.86114, 0.50289, 0.42955),
    ("right_camera", 0.590, -0.695, 1.552, -88.595, 0.874, 0.147, 0.48049, 0.85410, 0.49248, 0.47970),
    ("back_camera", -0.264, -0.033, 1.650, -178.267, 0.190, 0.205, 0.48618, 0.86544, 0.46717, 0.47024),
    ("left_camera", 0.543, 0.535, 1.577, 91.558, 0.946, -0.435, 0.48461, 0.86119, 0.51676, 0.50195),
    ("front_left_camera", 1.509, 0.644, 1.531, 57.751, 0.221, 0.079, 0.48429, 0.86117, 0.50660, 0.47084),
)
# name, x, y, z, yaw, pitch, roll, hfov
WAYMO = (
    ("FRONT", 1.54, 0.0, 2.12, 0.0, 0.0, 0.0, 50.0),
    ("FRONT_LEFT", 1.50, 0.10, 2.12, 45.0, 0.0, 0.0, 50.0),
    ("FRONT_RIGHT", 1.50, -0.10, 2.12, -45.0, 0.0, 0.0, 50.0),
    ("SIDE_LEFT", 1.43, 0.11, 2.12, 90.0, 0.0, 0.0, 50.0),
    ("SIDE_RIGHT", 1.43, -0.11, 2.12, -90.0, 0.0, 0.0, 50.0),
)
ONCE = tuple((f"cam0{i + 1}", 1.0 + 0.5 * math.cos(math.radians(60 * i)), 0.5 * math.sin(math.radians(60 * i)),
              1.75, 60.0 * i if i < 4 else 60.0 * i - 360.0, 0.0, 0.0, 90.0) for i in range(6))
ARGOVERSE = tuple((n, 1.2 + 0.4 * math.cos(math.radians(a)), 0.4 * math.sin(math.radians(a)), 1.75, a, 0.0, 0.0,
                   69.0)
                  for n, a in (("ring_front_center", 0.0), ("ring_front_left", 360 / 7),
                               ("ring_side_left", 720 / 7), ("ring_rear_left", 1080 / 7),
                               ("ring_rear_right", -1080 / 7), ("ring_side_right", -720 / 7),
                               ("ring_front_right", -360 / 7)))
CARLA_FOV = {"CAM_BACK": 110.0}  # others 70

PRESETS = ("nuscenes", "carla-centric", "pandaset", "waymo", "once", "argoverse")


def base_rig(name: str, width: int, height: int) -> list[Camera]:
    """The un-jittered cameras of a preset or of a rig JSON file (raises ValueError naming 'rig')."""
    cams: list[Camera] = []
    if name in ("nuscenes", "pandaset"):
        for n, x, y, z, yaw, pitch, roll, fxn, fyn, cxn, cyn in (NUSCENES if name == "nuscenes" else PANDASET):
            cams.append(Camera(name=n, width=width, height=height, K=K_scaled(fxn, fyn, cxn, cyn, width, height),
                               cam_to_ego=pose((x, y, z), yaw, pitch, roll)))
    elif name == "carla-centric":
        for n, x, y, z, yaw, pitch, roll, *_ in NUSCENES:
            cams.append(Camera(name=n, width=width, height=height, K=K_from_fov(CARLA_FOV.get(n, 70.0), width, height),
                               cam_to_ego=pose((x, y, z), yaw, 0.0, 0.0)))
    elif name in ("waymo", "once", "argoverse"):
        table = {"waymo": WAYMO, "once": ONCE, "argoverse": ARGOVERSE}[name]
        for n, x, y, z, yaw, pitch, roll, hfov in table:
            cams.append(Camera(name=n, width=width, height=height, K=K_from_fov(hfov, width, height),
                               cam_to_ego=pose((x, y, z), yaw, pitch, roll)))
    else:
        path = Path(name)
        if not path.is_file():
            raise ValueError(f"rig: {name!r} is neither a preset ({', '.join(PRESETS)}) nor a rig JSON file")
        try:
            d = json.loads(path.read_text())
            for i, c in enumerate(d["cameras"]):
                K = np.asarray(c["K"], float)
                w0, h0 = int(c["width"]), int(c["height"])
                sx, sy = width / w0, height / h0
                Ks = np.array([[K[0, 0] * sx, 0.0, (K[0, 2] + 0.5) * sx - 0.5],
                               [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])
                T = np.asarray(c["cam_to_ego"], float)
                if T.shape != (4, 4) or K.shape != (3, 3):
                    raise ValueError(f"rig: camera #{i}: K must be 3x3 and cam_to_ego 4x4")
                cams.append(Camera(name=str(c.get("name", f"cam{i}")), width=width, height=height, K=Ks, cam_to_ego=T))
        except (KeyError, TypeError, json.JSONDecodeError, RigError) as exc:
            raise ValueError(f"rig: cannot read cameras from {name!r}: {exc}") from exc
    return cams


def jitter(cams: list[Camera], rng: np.random.Generator, pos_m: float = 0.02, ang_deg: float = 0.5):
    """Per-scene mount jitter: position +-pos_m (uniform per axis), rotation by yaw/pitch/roll +-ang_deg."""
    out = []
    for c in cams:
        T = c.cam_to_ego.copy()
        a = rng.uniform(-ang_deg, ang_deg, 3)
        T[:3, :3] = T[:3, :3] @ _cam_small_rotation(a)  # small rotation about the camera's own axes
        T[:3, 3] += rng.uniform(-pos_m, pos_m, 3)
        out.append(c.replace(cam_to_ego=T))
    return out


def _cam_small_rotation(a_deg: np.ndarray) -> np.ndarray:
    """Rotation in camera coordinates: pan about camera y, tilt about camera x, roll about camera z."""
    ay, ax, az = np.radians(a_deg)
    Ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    Rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return Ry @ Rx @ Rz


def ego_forward_targets(cams: list[Camera], lane_dir: np.ndarray, rng: np.random.Generator):
    """The input rig moved back by U(1,3) m and forward by U(1,3) m along the lane (paper's T0 and T2)."""
    back, fwd = rng.uniform(1.0, 3.0), rng.uniform(1.0, 3.0)
    out = []
    for tag, off in (("t0", -back), ("t2", fwd)):
        for c in cams:
            T = c.cam_to_ego.copy()
            T[:3, 3] += off * np.asarray(lane_dir, float)
            out.append(c.replace(name=f"{c.name}_{tag}", cam_to_ego=T, extra={"ego_offset_m": round(float(off), 6)}))
    return out


def inward_directions(n: int, rng: np.random.Generator, elev_min_deg=8.0, elev_max_deg=70.0) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the hemisphere band (Fibonacci spiral, random rotation)."""
    zmin, zmax = math.sin(math.radians(elev_min_deg)), math.sin(math.radians(elev_max_deg))
    phase = rng.uniform(0, 2 * math.pi)
    golden = math.pi * (3 - math.sqrt(5))
    out = np.zeros((n, 3))
    for i in range(n):
        z = zmin + (zmax - zmin) * (i + rng.uniform(0.2, 0.8)) / n
        a = phase + i * golden
        r = math.sqrt(1 - z * z)
        out[i] = (r * math.cos(a), r * math.sin(a), z)
    return out
