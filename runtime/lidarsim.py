"""A simulated LiDAR sweep of a scene: the Gaussians' expected depth along the beams of a LiDAR model (what the gRPC
``render_lidar``, ``xyzcyl render --lidar`` and ``GET /v1/scenes/{id}/lidar`` answer; docs/simulators.md "LiDAR").

Frames and units. The LiDAR frame is the sensor's own: x forward, y left, z up (our ego frame's axes), metres. A
beam's elevation is its angle above the LiDAR's x-y plane (degrees, + up); a column's azimuth is atan2(y, x)
(degrees, 0 = forward, counter-clockwise positive seen from above). A ray of beam b and column j has the unit
direction d = (cos e_b cos a_j, cos e_b sin a_j, sin e_b) in the LiDAR frame.

The spin. A model's columns are fired one after the other over the spin, turning clockwise seen from above (as Hesai
and Velodyne sensors turn): column j (of n) at the fraction (j + 1/2) / n of the spin, at azimuth
``azimuth_start_deg - j * azimuth_step_deg``. A 360-degree spinner starts and ends behind the sensor (180 degrees),
the AT128 sweeps its 120 degrees from the left (+60) to the right (-60). The sensor's pose moves during the spin
from ``start`` (lidar -> scene, at the spin's start) to ``end`` (at its end): translation linearly, rotation along the
shorter arc (slerp); column j is fired at its interpolated pose, and every point is expressed in the end-of-spin
LiDAR frame (AlpaSim's "the xyz of the lidar points in the end-of-spin lidar space").

How it is rendered. The renderer draws pinhole cameras, not rays; so the spin is cut into S sectors of consecutive
columns (at most MAX_SECTOR_DEG of azimuth each, and more when the sensor moves or turns much during the spin:
SECTOR_MOTION_M, SECTOR_TURN_DEG), each drawn once as a pinhole camera at the sector's middle pose, looking along the
sector's middle azimuth and sized to hold exactly its rays (PX_PER_RAY pixels per ray pitch, at least
MIN_PX_PER_DEG); each ray of the sector reads the
sector's image along its own direction (its column's interpolated rotation) bilinearly, the nearest pixel at a depth
edge (as runtime.raydepth does). The range is the alpha-normalised expected distance (render's depth: sum(w z) /
alpha, converted from camera z to distance along the ray). So a column's ray leaves from its sector's middle
position, not its own: the origin is off by at most half a sector's travel (``origin_error_m`` in the stats:
translation / (2 S); 3 cm at 10 m/s over a 0.1 s spin). The point lies on the rendered surface either way.

Returns. A ray returns a point where the rendered alpha is at least ``alpha_min`` (ALPHA_MIN; the Gaussians there
are mostly opaque) and the range is within [min_range_m, max_range_m]; else no point (counted in the stats). The
sky (the scene's background panorama) returns nothing. Moving objects are drawn at one time for the whole spin (the
caller's: the middle of the spin), as the RGB path draws them at mid-exposure.

Intensity. The scene has no reflectance. ``intensity`` is a documented proxy: the rendered colour's Rec. 709
luminance (colour / alpha, clipped to [0, 1]) at the return -- a camera appearance, not a LiDAR reflectivity
(a white wall and a retro-reflective sign are not told apart; a dark car is dark).

Models (LIDAR_MODELS): nominal beam layouts built from the vendors' datasheets (channel count, vertical FOV, the
finer spacing of the centre band, azimuth step at 10 Hz, range), not the devices' per-unit calibration tables (which
also carry per-channel azimuth offsets, ignored here). ``beams_from_sweep`` estimates a model's elevations from a
recorded sweep instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from xyzcyl.common.wire import ViewError

from .camera import Camera, check_pose, look_rotation, pinhole_K
from .rotations import quat_to_rotmat, rotmat_to_quat

ALPHA_MIN = 0.5             # a ray returns a point where the rendered alpha reaches this (module docstring)
MAX_RAYS = 1 << 19          # beams x columns of one sweep at most (524288: a Pandar128 sweep is 230400)
MAX_BEAMS = 512
ELEVATION_LIMIT_DEG = 60.0  # |elevation| at most this (a sector camera is a pinhole: it cannot hold the poles)
AZIMUTH_STEP_RANGE = (0.02, 5.0)    # degrees
MAX_RANGE_LIMIT_M = 1000.0
MAX_SECTOR_DEG = 45.0       # azimuth of one sector camera at most (pinhole: +-22.5 degrees off its axis)
SECTOR_MOTION_M = 0.05      # more sectors while a ray's origin would be off by more than half this... (docstring)
SECTOR_TURN_DEG = 5.0       # ... or the sensor turns more than this within one sector
MAX_SECTORS = 64
# pixels of a sector camera: PX_PER_RAY per ray pitch (the finer of the azimuth step and the median beam spacing),
# and at least MIN_PX_PER_DEG. A pixel blends the Gaussians within about half a pixel of its centre (the
# renderer's 0.3 px low-pass) front to back, so on a surface seen obliquely the nearer side of that footprint wins:
# range reads short by about range x tan(incidence) x the footprint's angle. Measured on a cylinder 10 m away at
# 22 degrees off a sector's axis: -0.15 m at 0.5 px per degree, -0.02 m at 5 px per degree.
PX_PER_RAY = 2.0
MIN_PX_PER_DEG = 10.0
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)    # Rec. 709


@dataclass(frozen=True)
class LidarModel:
    """A LiDAR's beams and columns (module docstring: frames, the spin). Build one with ``lidar_model`` (checked)."""

    name: str
    elevations_deg: tuple[float, ...]      # [B] degrees above the LiDAR's x-y plane, ascending
    azimuth_step_deg: float = 0.2          # degrees between consecutive columns
    azimuth_fov_deg: float = 360.0         # degrees swept by one spin (360: a spinner)
    azimuth_start_deg: float = 180.0       # azimuth of the first column (the spin turns clockwise from it)
    max_range_m: float = 200.0
    min_range_m: float = 0.3

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def columns(self) -> int:
        return max(1, int(round(self.azimuth_fov_deg / self.azimuth_step_deg)))

    @property
    def rays(self) -> int:
        return self.beams * self.columns

    def azimuths_deg(self) -> np.ndarray:
        """[C] float64 degrees: each column's azimuth, in firing order."""
        return self.azimuth_start_deg - self.azimuth_step_deg * np.arange(self.columns, dtype=np.float64)

    def directions(self) -> np.ndarray:
        """[B, C, 3] float64 unit ray directions in the LiDAR frame."""
        e = np.radians(np.asarray(self.elevations_deg, np.float64))[:, None]
        a = np.radians(self.azimuths_deg())[None, :]
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e) + 0.0 * a], axis=-1)

    def describe(self) -> dict[str, Any]:
        e = self.elevations_deg
        return {"name": self.name, "beams": self.beams, "columns": self.columns, "rays": self.rays,
                "elevation_deg": [min(e), max(e)], "azimuth_step_deg": self.azimuth_step_deg,
                "azimuth_fov_deg": self.azimuth_fov_deg, "max_range_m": self.max_range_m}


def _pandar128() -> tuple[float, ...]:
    """Hesai Pandar128E3X, nominal: 128 channels over -25..+15 degrees; 64 of them 0.125-degree-spaced in the
    -6..+2 band, the other 64 0.5 degrees apart above and below it."""
    centre = np.linspace(-6.0, 2.0, 64)
    below = -25.0 + 0.5 * np.arange(38)          # -25 .. -6.5
    above = 2.5 + 0.5 * np.arange(26)            # 2.5 .. 15
    return tuple(float(v) for v in np.sort(np.concatenate([below, centre, above])))


def _pandar64() -> tuple[float, ...]:
    """Hesai Pandar64, nominal: 64 channels over -25..+15 degrees; 1/6-degree-spaced from -6 to +2, sparser
    beyond (+3, +5, +8, +11, +15 above; -7..-14 every degree, -19, -25 below)."""
    centre = np.linspace(-6.0, 2.0, 49)
    rest = [15.0, 11.0, 8.0, 5.0, 3.0, -7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0, -19.0, -25.0]
    return tuple(float(v) for v in np.sort(np.concatenate([centre, rest])))


LIDAR_MODELS: dict[str, LidarModel] = {
    # 360-degree spinner, 0.2-degree steps at 10 Hz, 200 m
    "pandar128": LidarModel("pandar128", _pandar128(), 0.2, 360.0, 180.0, 200.0),
    # a 120 x 25.4 degree forward solid-state (rotating mirror) LiDAR: 128 channels 0.2 degrees apart, 0.1-degree
    # columns swept left to right at 10 Hz, 200 m
    "at128": LidarModel("at128", tuple(float(v) for v in np.linspace(-12.5, 12.9, 128)), 0.1, 120.0, 60.0, 200.0),
    # the spinner of PandaSet's recordings (docs/simulators.md "LiDAR")
    "pandar64": LidarModel("pandar64", _pandar64(), 0.2, 360.0, 180.0, 200.0),
}
PROTO_MODELS = ("pandar128", "at128")      # LidarDeviceType PANDAR128 = 0, AT128 = 1 (sensorsim.proto)


def _finite(v: Any, field: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ViewError(field, f"must be a number (got {v!r})") from None
    if not math.isfinite(f):
        raise ViewError(field, f"must be finite (got {f})")
    return f


def lidar_model(name: str | None = "pandar128", *, elevations_deg: Sequence[float] | None = None,
                azimuth_step_deg: float | None = None, max_range_m: float | None = None,
                fields: dict[str, str] | None = None) -> LidarModel:
    """The checked LidarModel ``name`` (LIDAR_MODELS) with the given overrides (``elevations_deg``: beams of one's
    own, e.g. beams_from_sweep's). ViewError naming the field (``fields`` maps "model", "elevations_deg",
    "azimuth_step_deg", "max_range_m" to the caller's names) when a value is out of range or the sweep would have
    more than MAX_RAYS rays."""
    f = {"model": "model", "elevations_deg": "elevations_deg", "azimuth_step_deg": "azimuth_step_deg",
         "max_range_m": "max_range_m", **(fields or {})}
    key = (name or "pandar128").strip().lower()
    if key not in LIDAR_MODELS:
        raise ViewError(f["model"], f"unknown LiDAR model {name!r}: one of {', '.join(LIDAR_MODELS)}")
    m = LIDAR_MODELS[key]
    if elevations_deg is not None:
        e = [_finite(v, f"{f['elevations_deg']}[{i}]") for i, v in enumerate(elevations_deg)]
        if not 1 <= len(e) <= MAX_BEAMS:
            raise ViewError(f["elevations_deg"], f"1 to {MAX_BEAMS} beams (got {len(e)})")
        for i, v in enumerate(e):
            if abs(v) > ELEVATION_LIMIT_DEG:
                raise ViewError(f"{f['elevations_deg']}[{i}]",
                                f"must be within +-{ELEVATION_LIMIT_DEG:g} degrees (got {v:g})")
        m = replace(m, name=f"{m.name}+beams", elevations_deg=tuple(sorted(e)))
    if azimuth_step_deg is not None:
        s = _finite(azimuth_step_deg, f["azimuth_step_deg"])
        lo, hi = AZIMUTH_STEP_RANGE
        if not lo <= s <= hi:
            raise ViewError(f["azimuth_step_deg"], f"must be in [{lo:g}, {hi:g}] degrees (got {s:g})")
        m = replace(m, azimuth_step_deg=s)
    if max_range_m is not None:
        r = _finite(max_range_m, f["max_range_m"])
        if not m.min_range_m < r <= MAX_RANGE_LIMIT_M:
            raise ViewError(f["max_range_m"], f"must be in ({m.min_range_m:g}, {MAX_RANGE_LIMIT_M:g}] metres "
                                              f"(got {r:g})")
        m = replace(m, max_range_m=r)
    if m.rays > MAX_RAYS:
        which = f["azimuth_step_deg"] if azimuth_step_deg is not None else f["elevations_deg"]
        raise ViewError(which, f"{m.beams} beams x {m.columns} columns = {m.rays} rays, more than the {MAX_RAYS} "
                               "of one sweep")
    return m


# ------------------------------------------------------------------------------------------- poses over the spin

def interpolate_pose(start: np.ndarray, end: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[T, 4, 4] poses at fractions ``t`` [T] of the way from ``start`` to ``end`` ([4, 4] rigid): translation
    linear, rotation slerp along the shorter arc."""
    t = np.asarray(t, np.float64).reshape(-1)
    q0, q1 = rotmat_to_quat(start[:3, :3]), rotmat_to_quat(end[:3, :3])
    if float(q0 @ q1) < 0:
        q1 = -q1
    dot = min(1.0, float(q0 @ q1))
    theta = math.acos(dot)
    if theta < 1e-9:
        q = np.repeat(q0[None], len(t), axis=0)
    else:
        s = math.sin(theta)
        q = (np.sin((1 - t) * theta)[:, None] * q0 + np.sin(t * theta)[:, None] * q1) / s
    out = np.repeat(np.eye(4)[None], len(t), axis=0)
    out[:, :3, :3] = quat_to_rotmat(q)
    out[:, :3, 3] = (1 - t)[:, None] * start[:3, 3] + t[:, None] * end[:3, 3]
    return out


def _turn_deg(start: np.ndarray, end: np.ndarray) -> float:
    c = (np.trace(start[:3, :3].T @ end[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def sector_count(model: LidarModel, start: np.ndarray, end: np.ndarray) -> int:
    """S (module docstring): enough sectors for MAX_SECTOR_DEG of azimuth each, an origin off by at most
    SECTOR_MOTION_M / 2 and SECTOR_TURN_DEG of turn each; at most MAX_SECTORS and the column count."""
    travel = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
    s = max(math.ceil(model.azimuth_fov_deg / MAX_SECTOR_DEG - 1e-9), math.ceil(travel / SECTOR_MOTION_M),
            math.ceil(_turn_deg(start, end) / SECTOR_TURN_DEG))
    return int(max(1, min(s, MAX_SECTORS, model.columns)))


# ------------------------------------------------------------------------------------------- the sweep

@dataclass(frozen=True)
class LidarSweep:
    """A rendered sweep: N returns of ``model``'s rays (module docstring)."""

    model: LidarModel
    points: np.ndarray        # [N, 3] float32 metres, end-of-spin LiDAR frame
    intensity: np.ndarray     # [N] float32 in [0, 1]: rendered luminance (module docstring "Intensity")
    range_m: np.ndarray       # [N] float32 metres from the ray's origin
    beam: np.ndarray          # [N] int16 beam index (into model.elevations_deg, ascending elevation)
    column: np.ndarray        # [N] int32 column index (firing order)
    stats: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def range_image(self) -> np.ndarray:
        """[B, C] float32 metres, 0 where the ray returned nothing (row 0 the lowest beam)."""
        img = np.zeros((self.model.beams, self.model.columns), np.float32)
        img[self.beam, self.column] = self.range_m
        return img


Draw = Callable[[Camera], tuple[np.ndarray, np.ndarray, np.ndarray]]    # camera -> (rgb, depth, alpha) [H, W]


def scene_drawer(scene: Any, time_s: float | None = None, actors: Sequence[Any] = ()) -> Draw:
    """A Draw of a runtime.scene.Scene at ``time_s`` with the actor edits ``actors``: its Gaussians only (the sky
    panorama returns nothing), as Scene.render draws them for a camera."""
    def draw(cam: Camera):
        return scene.render(cam, time_s, background=None, actors=actors)
    return draw


def gaussians_drawer(gaussians: Any) -> Draw:
    """A Draw of bare Gaussians (runtime.render.render, no background)."""
    from .render import render

    def draw(cam: Camera):
        r = render(gaussians, cam)
        return r.rgb, r.depth, r.alpha
    return draw


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray, edge: bool) -> np.ndarray:
    """Bilinear samples of ``img`` [H, W] at pixel coordinates (u, v) [M] (inside by construction); with ``edge``,
    the nearest pixel where the bilinear value differs from it by more than 10 % (a depth edge: runtime.raydepth's
    rule)."""
    H, W = img.shape
    u = np.clip(u, 0.0, W - 1.0)
    v = np.clip(v, 0.0, H - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), W - 2) if W > 1 else np.zeros(u.shape, np.int64)
    v0 = np.minimum(np.floor(v).astype(np.int64), H - 2) if H > 1 else np.zeros(v.shape, np.int64)
    fu, fv = u - u0, v - v0
    u1, v1 = np.minimum(u0 + 1, W - 1), np.minimum(v0 + 1, H - 1)
    lin = ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u1] + (1 - fu) * fv * img[v1, u0]
           + fu * fv * img[v1, u1])
    if not edge:
        return lin
    near = img[np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)]
    return np.where(np.abs(lin - near) > 0.1 * near, near, lin)


def _sector_camera(dirs_lidar: np.ndarray, pose: np.ndarray, R_rel: np.ndarray, azimuth_mid_deg: float,
                   elev_mid_deg: float, px_per_rad: float) -> tuple[Camera, np.ndarray, np.ndarray, np.ndarray]:
    """The pinhole camera (in the scene frame) at sector pose ``pose`` that holds the sector's rays, and each ray's
    (u, v, z-to-distance factor). dirs_lidar: [M, 3] unit directions in the LiDAR frame; R_rel: [M, 3, 3] each ray's
    column rotation relative to the sector pose (R_sector^T R_column)."""
    R_cl = look_rotation(math.radians(azimuth_mid_deg), math.radians(elev_mid_deg))   # camera -> LiDAR
    d_sector = np.einsum("mij,mj->mi", R_rel, dirs_lidar)                              # [M, 3] sector frame
    d_cam = d_sector @ R_cl                                                             # [M, 3] camera frame
    z = d_cam[:, 2]
    x, y = d_cam[:, 0] / z, d_cam[:, 1] / z
    margin = 2.0
    f = px_per_rad
    x0, x1, y0, y1 = float(x.min()), float(x.max()), float(y.min()), float(y.max())
    cx, cy = margin - f * x0, margin - f * y0
    W = int(math.ceil(f * (x1 - x0) + 2 * margin)) + 1
    H = int(math.ceil(f * (y1 - y0) + 2 * margin)) + 1
    T = pose.copy()
    T[:3, :3] = pose[:3, :3] @ R_cl
    cam = Camera(K=pinhole_K(f, f, cx, cy), cam_to_ego=T, width=W, height=H)
    return cam, f * x + cx, f * y + cy, 1.0 / z


def render_lidar(draw: Draw, model: LidarModel, start: Any, end: Any | None = None,
                 alpha_min: float = ALPHA_MIN) -> LidarSweep:
    """The sweep of ``model`` drawn by ``draw`` (scene_drawer / gaussians_drawer) with the LiDAR at ``start``
    (lidar -> scene frame, [4, 4], at the spin's start) and ``end`` (at its end; None: still). Points in the
    end-of-spin LiDAR frame (module docstring). Poses are checked (runtime.camera.check_pose: ViewError-like
    CameraError naming ``lidar_to_ego``)."""
    start = check_pose(start, key="lidar_to_ego")
    end = start if end is None else check_pose(end, key="lidar_to_ego")
    B, C = model.beams, model.columns
    dirs = model.directions()                                    # [B, C, 3]
    az = model.azimuths_deg()
    frac = (np.arange(C) + 0.5) / C                              # each column's time in the spin
    col_pose = interpolate_pose(start, end, frac)                # [C, 4, 4]
    S = sector_count(model, start, end)
    bounds = np.linspace(0, C, S + 1).round().astype(int)
    e = np.asarray(model.elevations_deg)
    spacing = np.diff(e)
    pitch_deg = min(model.azimuth_step_deg, float(np.median(spacing)) if len(spacing) else model.azimuth_step_deg)
    px_per_rad = max(PX_PER_RAY / math.radians(max(pitch_deg, 0.02)), MIN_PX_PER_DEG * 180.0 / math.pi)
    elev_mid = 0.5 * (e[0] + e[-1])
    end_inv = np.linalg.inv(end)
    out = {k: [] for k in ("p", "i", "r", "b", "c")}
    no_return = out_of_range = nonfinite = 0
    sizes = []
    for s in range(S):
        j0, j1 = int(bounds[s]), int(bounds[s + 1])
        if j1 <= j0:
            continue
        pose = interpolate_pose(start, end, np.array([0.5 * (frac[j0] + frac[j1 - 1])]))[0]
        R_rel = np.einsum("ji,cjk->cik", pose[:3, :3], col_pose[j0:j1, :3, :3])    # [Cs, 3, 3]
        Cs = j1 - j0
        d = dirs[:, j0:j1].reshape(-1, 3)                                            # [B*Cs, 3] (b major)
        R_rays = np.broadcast_to(R_rel[None], (B, Cs, 3, 3)).reshape(-1, 3, 3)
        cam, u, v, to_dist = _sector_camera(d, pose, R_rays, 0.5 * (az[j0] + az[j1 - 1]), elev_mid, px_per_rad)
        sizes.append((cam.width, cam.height))
        rgb, depth, alpha = draw(cam)
        a = _sample(alpha, u, v, edge=False)
        z = _sample(depth, u, v, edge=True)
        rng = z * to_dist
        bad = ~np.isfinite(rng) | ~np.isfinite(a)
        nonfinite += int(bad.sum())
        hit = ~bad & (a >= alpha_min)
        no_return += int((~bad & ~hit).sum())
        inside = hit & (rng >= model.min_range_m) & (rng <= model.max_range_m)
        out_of_range += int((hit & ~inside).sum())
        k = np.flatnonzero(inside)
        if not len(k):
            continue
        lum = np.stack([_sample(rgb[..., c], u[k], v[k], edge=False) for c in range(3)], axis=-1) @ LUMA
        inten = np.clip(lum / np.maximum(a[k], 1e-6), 0.0, 1.0)
        b_idx, c_idx = k // Cs, j0 + k % Cs
        world_dir = np.einsum("ij,kj->ki", pose[:3, :3], np.einsum("kij,kj->ki", R_rays[k], d[k]))
        p_scene = pose[:3, 3] + rng[k, None] * world_dir           # from the sector's origin (module docstring)
        p_end = p_scene @ end_inv[:3, :3].T + end_inv[:3, 3]
        out["p"].append(p_end.astype(np.float32))
        out["i"].append(inten.astype(np.float32))
        out["r"].append(rng[k].astype(np.float32))
        out["b"].append(b_idx.astype(np.int16))
        out["c"].append(c_idx.astype(np.int32))
    cat = {k: (np.concatenate(v) if v else np.zeros((0, 3) if k == "p" else 0,
                                                     {"b": np.int16, "c": np.int32}.get(k, np.float32)))
           for k, v in out.items()}
    travel = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
    stats = {"rays": B * C, "returns": int(len(cat["p"])), "no_return": no_return, "out_of_range": out_of_range,
             "nonfinite": nonfinite, "sectors": S, "origin_error_m": travel / (2 * S),
             "sector_pixels": int(sum(w * h for w, h in sizes))}
    return LidarSweep(model, cat["p"], cat["i"], cat["r"], cat["b"], cat["c"], stats)


@dataclass(frozen=True)
class LidarRequest:
    """One sweep asked by a front end (gRPC render_lidar, GET .../lidar, `xyzcyl render --lidar`): the model, the
    LiDAR's poses at the spin's start and end (lidar -> the scene's frame, [4, 4] float64, checked rigid), the time
    the moving objects are drawn at (seconds on the rigs' clock; None: the scene's start), actor edits
    (common.wire.ActorEdit) and the file format of the answer ("ply", "npy"; gRPC answers its own message)."""

    model: LidarModel
    start: np.ndarray = field(repr=False)
    end: np.ndarray = field(repr=False)
    time_s: float | None = None
    actors: tuple = ()
    format: str = "ply"


def render_request(scene: Any, req: LidarRequest) -> LidarSweep:
    """The sweep of ``req`` in runtime.scene.Scene ``scene`` (scene_drawer at its time and edits)."""
    return render_lidar(scene_drawer(scene, req.time_s, req.actors), req.model, req.start, req.end)


def ray_ranges(draw: Draw, directions: np.ndarray, pose: Any, alpha_min: float = ALPHA_MIN,
               max_range_m: float = MAX_RANGE_LIMIT_M) -> np.ndarray:
    """[M] float64 rendered range (metres) along arbitrary rays ``directions`` [M, 3] (LiDAR frame; normalised
    here) from a still LiDAR at ``pose`` (lidar -> scene), NaN where the ray returns nothing (alpha < alpha_min,
    beyond max_range_m, or |elevation| > ELEVATION_LIMIT_DEG): the comparison with a recorded sweep along its own
    rays (benchmarks/lidar_bench.py --compare). Rays are drawn in MAX_SECTOR_DEG azimuth sectors as render_lidar's."""
    pose = check_pose(pose, key="lidar_to_ego")
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    out = np.full(len(d), np.nan)
    el = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    ok = np.abs(el) <= ELEVATION_LIMIT_DEG
    n = int(math.ceil(360.0 / MAX_SECTOR_DEG))
    sector = np.minimum(((az + 180.0) / (360.0 / n)).astype(int), n - 1)
    px = MIN_PX_PER_DEG * 2 * 180.0 / math.pi
    elev_mid = 0.5 * (float(el[ok].min()) + float(el[ok].max())) if ok.any() else 0.0
    for s in range(n):
        k = np.flatnonzero(ok & (sector == s))
        if not len(k):
            continue
        mid = -180.0 + (s + 0.5) * 360.0 / n
        R = np.broadcast_to(np.eye(3), (len(k), 3, 3))
        cam, u, v, to_dist = _sector_camera(d[k], pose, R, mid, elev_mid, px)
        _, depth, alpha = draw(cam)
        a = _sample(alpha, u, v, edge=False)
        r = _sample(depth, u, v, edge=True) * to_dist
        good = (a >= alpha_min) & np.isfinite(r) & (r <= max_range_m)
        out[k[good]] = r[good]
    return out


# ------------------------------------------------------------------------------------------- encodings

LIDAR_FORMATS = {"ply": "application/octet-stream", "npy": "application/octet-stream"}


def sweep_bytes(sweep: LidarSweep, fmt: str = "ply") -> bytes:
    """The sweep as a file: "ply" -- binary little-endian PLY, one vertex per point with float x, y, z (metres,
    end-of-spin LiDAR frame), float intensity ([0, 1]) and ushort ring (the beam, 0 = lowest), readable by
    CloudCompare, Open3D and plyfile; "npy" -- float32 [N, 4] x, y, z, intensity (the layout of the recorded sweeps in
    data/real, and of KITTI's .bin)."""
    import io

    if fmt == "npy":
        buf = io.BytesIO()
        np.save(buf, np.concatenate([sweep.points, sweep.intensity[:, None]], axis=1).astype(np.float32))
        return buf.getvalue()
    if fmt != "ply":
        raise ViewError("format", f"unknown LiDAR file format {fmt!r}: ply or npy")
    from plyfile import PlyData, PlyElement

    v = np.empty(len(sweep), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                                    ("ring", "<u2")])
    v["x"], v["y"], v["z"] = sweep.points[:, 0], sweep.points[:, 1], sweep.points[:, 2]
    v["intensity"], v["ring"] = sweep.intensity, sweep.beam
    buf = io.BytesIO()
    PlyData([PlyElement.describe(v, "vertex")], text=False, byte_order="<",
            comments=[f"xyzcyl LiDAR sweep: model {sweep.model.name}, end-of-spin LiDAR frame (x forward, y left, "
                      "z up, metres); intensity = rendered luminance (not reflectance)"]).write(buf)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------- beams of a recording

def elevations_of(points: np.ndarray, origin: Sequence[float] = (0.0, 0.0, 0.0), min_range_m: float = 3.0
                  ) -> np.ndarray:
    """[M] float64 degrees: the elevation of each point ([N, 3] metres, any frame with z up) seen from ``origin``,
    for the points at least ``min_range_m`` away horizontally (near points magnify an origin's error). Non-finite
    rows are left out (the caller's reader counts them: runtime.lidar.read_points)."""
    p = np.asarray(points, np.float64)[:, :3] - np.asarray(origin, np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    h = np.hypot(p[:, 0], p[:, 1])
    keep = h >= min_range_m
    return np.degrees(np.arctan2(p[keep, 2], h[keep]))


def peakiness(elev_deg: np.ndarray, bin_deg: float = 0.05) -> float:
    """How much the elevations gather in rings: sum of squared histogram shares over ``bin_deg`` bins (1 / bins
    when spread evenly, larger as they concentrate; a sweep seen from its sensor's origin is sharpest)."""
    if not len(elev_deg):
        return 0.0
    h, _ = np.histogram(elev_deg, bins=np.arange(-40.0, 40.0 + bin_deg, bin_deg))
    s = h / max(1, h.sum())
    return float((s * s).sum())


SENSOR_GROUND_BAND_M = 0.1   # returns this close to the sweep's ground plane are ground (sensor_height_from_sweep)
INNER_RING_QUANTILE = 0.5    # percent: the innermost ground ring's radius is this quantile of the ground returns'


def sensor_height_from_sweep(points: np.ndarray, lowest_elevation_deg: float) -> tuple[float, float]:
    """(the ground's height under the frame's origin, the sensor's height above that ground), metres, from a
    recorded sweep ``points`` [N, 3] (a frame with z up, e.g. an ego frame whose origin is not the sensor) and its
    LiDAR's lowest beam (degrees, negative; a Pandar64's is -25): its nearest ground returns lie on the ring where
    that beam meets the ground, ``height = radius * tan(-lowest)``. The ground is runtime.detail.fit_ground's plane;
    the ring's radius the INNER_RING_QUANTILE percentile of the ground returns' horizontal distance from the origin
    (the sensor is taken to stand above the origin: an offset of d metres sideways shifts the estimate by about
    d x tan(-lowest) on average around the ring). ViewError when the sweep shows no ground."""
    from .detail import fit_ground

    p = np.asarray(points, np.float64)[:, :3]
    p = p[np.all(np.isfinite(p), axis=1)]
    if not lowest_elevation_deg < 0:
        raise ViewError("lowest_elevation_deg", f"must be below the horizon (got {lowest_elevation_deg})")
    plane = fit_ground(p)
    if plane is None:
        raise ViewError("points", "no ground plane in the sweep: cannot estimate the sensor's height")
    ground = p[np.abs(p @ plane[:3] + plane[3]) <= SENSOR_GROUND_BAND_M]
    radius = float(np.percentile(np.hypot(ground[:, 0], ground[:, 1]), INNER_RING_QUANTILE))
    ground_z = float(-plane[3] / plane[2])
    return ground_z, radius * math.tan(math.radians(-lowest_elevation_deg))


def beams_from_sweep(points: np.ndarray, origin: Sequence[float] = (0.0, 0.0, 0.0), max_beams: int = 128,
                     bin_deg: float = 0.02, min_gap_deg: float = 0.08, min_share: float = 0.002) -> tuple[float, ...]:
    """The beam elevations (degrees, ascending) of a recorded sweep ``points`` [N, 3] seen from ``origin``: the
    peaks of the elevation histogram (``bin_deg`` bins, smoothed over 3 bins), at least ``min_gap_deg`` apart,
    each holding at least ``min_share`` of the points; the ``max_beams`` strongest, each refined to the mean elevation
within ``min_gap_deg`` / 2 of its peak."""
    e = elevations_of(points, origin)
    if len(e) == 0:
        raise ViewError("points", "no point at least 3 m away: cannot estimate beams")
    edges = np.arange(-40.0, 40.0 + bin_deg, bin_deg)
    h, _ = np.histogram(e, bins=edges)
    hs = np.convolve(h, np.ones(3) / 3.0, mode="same")
    centres = 0.5 * (edges[:-1] + edges[1:])
    peak = (hs > np.roll(hs, 1)) & (hs >= np.roll(hs, -1)) & (hs >= min_share * len(e) / 3.0)
    idx = np.flatnonzero(peak)
    idx = idx[np.argsort(-hs[idx])]
    chosen: list[int] = []
    for i in idx:
        if all(abs(centres[i] - centres[j]) >= min_gap_deg for j in chosen):
            chosen.append(int(i))
        if len(chosen) >= max_beams:
            break
    if not chosen:
        raise ViewError("points", "the elevations show no beam rings")
    es = np.sort(e)
    out = []
    for i in sorted(chosen):           # each peak refined: the mean elevation within half a gap of it
        c = centres[i]
        lo, hi = np.searchsorted(es, [c - 0.5 * min_gap_deg, c + 0.5 * min_gap_deg])
        out.append(float(es[lo:hi].mean()) if hi > lo else float(c))
    return tuple(out)


__all__ = ["ALPHA_MIN", "LIDAR_MODELS", "MAX_RAYS", "PROTO_MODELS", "LidarModel", "LidarRequest", "LidarSweep", "beams_from_sweep",
           "elevations_of", "gaussians_drawer", "interpolate_pose", "lidar_model", "peakiness", "ray_ranges", "render_lidar",
           "render_request", "scene_drawer", "sector_count", "sensor_height_from_sweep", "sweep_bytes"]
