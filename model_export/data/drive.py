"""Synthetic drives: one generated street, the ego driving along it, exact ground truth (`xyzcyl data synth-drive`).

The product reconstructs whole recorded drives (runtime/drive.py, docs/inference.md "Drives"); the real PandaSet
drive barely moves. A synthetic drive moves at any speed and has exact truth at every frame, between keyframes
too. Format and rules: docs/data.md "Synthetic drives".

- The street: scene `scene_index` of `seed` (scene.sample_scene) with the road along x (SceneConfig.max_psi_deg
  = 0: the same draws, the heading offset 0), so the world frame is the road frame and the first frame's ego frame.
- The ego (rear axle) drives along its lane at `speed` m/s with a gentle lane-keeping sway: lateral offset
  SWAY_M (1 - cos(2 pi s / SWAY_PERIOD_M)) at s metres along the road, heading along the path's tangent. Its body
  moves with it and is skipped by every rig view and the LiDAR.
- Movers: `movers` cars (scene._car, a side stream) that drive along lanes at their own speeds, alternately in
  the oncoming lanes (passing the ego mid-drive) and in the ego's direction (another forward lane, or the ego lane
  ahead and faster than the ego). Standing cars in a mover's or the ego's way are taken out of the scene; every
  other car stands (parked cars, the sampler's traffic) and is a stationary track.
- Each frame: the rig's views traced at the ego's pose (RGB, depth, sky, semantics), a spinning-LiDAR sweep
  (lidar.py) in the ego frame, rig.json with ego_to_world and timestamp_s. tracks.json: every car's box per frame.
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from xyzcyl.common.media import write_exr
from xyzcyl.runtime.camera import Camera

from . import classes as C
from .lidar import BEAMS, ELEV_MAX_DEG, ELEV_MIN_DEG, MAX_RANGE_M, MOUNT, lidar_sweep
from .rigs import PRESETS, base_rig
from .scene import (
    G_LANEW,
    G_NFWD,
    G_NLANES,
    G_VD0,
    G_VL,
    G_VR,
    GENERATOR_VERSION,
    HALF_LENGTH,
    T_CARBODY,
    Scene,
    SceneConfig,
    _Builder,
    _car,
    sample_scene,
)
from .synth import FRAME, _write_png, open_output, produce
from .trace import View, build_grid, render_view

DRIVE_VERSION = "1"             # changes whenever the files of a given config change
CLOCK_START_S = 1_700_000_000.0  # timestamp_s of frame 0 (seconds; a fixed clock, frames at k / hz after it)
SWAY_M = 0.15                   # the ego's lateral offset peaks at 2 SWAY_M (left of its lane centre)
SWAY_PERIOD_M = 40.0            # ... once every this many metres along the road (heading within +-1.4 deg)
MAX_TRAVEL_M = HALF_LENGTH - 10.0  # metres: the ego's way along the street (it starts at its middle)
CLEAR_AHEAD_M = 8.0             # standing cars in the ego lane up to this far past the ego's last front are removed
MOVER_GAP_M = 2.0               # movers of one lane keep at least this much bumper-to-bumper
MOVER_KINDS = (("sedan", "hatch", "suv", "van"), (0.35, 0.3, 0.25, 0.1))
ONCOMING_SPEED = (4.0, 12.0)    # m/s
SAME_WAY_SPEED = (2.0, 10.0)    # m/s, in another forward lane
AHEAD_EXTRA_SPEED = (2.0, 4.0)  # m/s faster than the ego, in the ego lane ahead of it
# image size of the presets' real cameras: --width keeps this aspect
RIG_SIZE = {"nuscenes": (1600, 900), "carla-centric": (1600, 900), "pandaset": (1920, 1080),
            "waymo": (1920, 1280), "once": (1920, 1020), "argoverse": (1920, 1200)}
LIDAR_FILE = "lidar.npy"


@dataclass(frozen=True)
class DriveConfig:
    """Everything that determines a synthetic drive (stored in index.json and drive.json)."""

    seed: int = 7
    frames: int = 40
    hz: float = 10.0              # frames per second
    speed: float = 5.0            # the ego's speed, m/s
    rig: str = "pandaset"         # preset (rigs.PRESETS) or path to a rig JSON
    width: int = 1920             # pixels; height from the rig's aspect (height_for)
    movers: int = 3
    supersample: int = 2
    shadows: bool = True
    scene_index: int | None = None  # which scene of `seed` is the street (None: street_index, parked cars)

    @property
    def height(self) -> int:
        return height_for(self.rig, self.width)

    @property
    def duration_s(self) -> float:
        return (self.frames - 1) / self.hz

    def validate(self) -> None:
        """Raise ValueError naming the field."""
        for name in ("seed", "frames", "width", "movers", "supersample", "scene_index"):
            v = getattr(self, name)
            if name == "scene_index" and v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f"{name}: must be an integer, got {v!r}")
        if not 1 <= self.frames <= 10000:
            raise ValueError(f"frames: must be in 1..10000, got {self.frames}")
        if not (math.isfinite(self.hz) and 0.1 <= self.hz <= 1000):
            raise ValueError(f"hz: must be in 0.1..1000, got {self.hz}")
        if not (math.isfinite(self.speed) and 0 <= self.speed <= 60):
            raise ValueError(f"speed: must be in 0..60 m/s, got {self.speed}")
        if self.speed * self.duration_s > MAX_TRAVEL_M:
            raise ValueError(f"speed: {self.speed:g} m/s for {self.frames} frames at {self.hz:g} Hz drives "
                             f"{self.speed * self.duration_s:.0f} m, more than the street's {MAX_TRAVEL_M:g} m")
        if not 8 <= self.width <= 4096:
            raise ValueError(f"width: must be in 8..4096, got {self.width}")
        if not 0 <= self.movers <= 20:
            raise ValueError(f"movers: must be in 0..20, got {self.movers}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample: must be in 1..8, got {self.supersample}")
        if self.scene_index is not None and self.scene_index < 0:
            raise ValueError(f"scene_index: must be >= 0, got {self.scene_index}")
        base_rig(self.rig, self.width, self.height)  # raises naming 'rig'

    def to_json(self) -> dict:
        return asdict(self)


def has_parking(scene: Scene) -> tuple[bool, bool]:
    """Whether the street has a parking strip on its right and on its left side."""
    G = scene.ground
    lanes_end = G[G_VD0] + G[G_NLANES] * G[G_LANEW]
    return bool(G[G_VR] < G[G_VD0] - 1.0), bool(G[G_VL] > lanes_end + 1.0)


@functools.lru_cache(maxsize=16)
def street_index(seed: int) -> int:
    """The first scene of `seed` with parking strips on both sides (parked cars seen from both sides of the
    drive), else the first with one, else 0 (the first 50 scenes are looked at)."""
    one = None
    for i in range(50):
        r, left = has_parking(sample_scene(seed, i, SceneConfig(max_psi_deg=0.0, with_ego=True)))
        if r and left:
            return i
        if one is None and (r or left):
            one = i
    return 0 if one is None else one


def scene_index_of(cfg: "DriveConfig") -> int:
    return street_index(cfg.seed) if cfg.scene_index is None else cfg.scene_index


def height_for(rig: str, width: int) -> int:
    """The image height at `width` with the aspect of the rig's real cameras (RIG_SIZE; a rig JSON: its first
    camera's), at least 8."""
    if rig in RIG_SIZE:
        w0, h0 = RIG_SIZE[rig]
    else:
        try:
            cam = json.loads(Path(rig).read_text())["cameras"][0]
            w0, h0 = int(cam["width"]), int(cam["height"])
        except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
            raise ValueError(f"rig: {rig!r} is neither a preset ({', '.join(PRESETS)}) nor a readable rig JSON "
                             f"file ({exc})") from None
    return max(8, int(round(width * h0 / w0)))


# --------------------------------------------------------------------------------------------------------------
# the ego's path


def ego_pose(cfg: DriveConfig, t: float) -> np.ndarray:
    """[4, 4] ego -> world at `t` seconds after frame 0 (world = frame 0's ego frame = the road frame)."""
    s = cfg.speed * t
    w = 2.0 * math.pi / SWAY_PERIOD_M
    y = SWAY_M * (1.0 - math.cos(w * s))
    yaw = math.atan(SWAY_M * w * math.sin(w * s))
    T = np.eye(4)
    c, sn = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -sn], [sn, c]]
    T[0, 3], T[1, 3] = s, y
    return T


# --------------------------------------------------------------------------------------------------------------
# cars


@dataclass(frozen=True)
class CarBox:
    """A car's box: centre (m, world), size (length, width, height m), yaw (rad); the box holds the car whole
    (body footprint, ground to roof)."""

    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float

    def pose(self, dx: float = 0.0) -> np.ndarray:
        """[4, 4] box -> world, moved `dx` metres along world x."""
        T = np.eye(4)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = (self.centre[0] + dx, self.centre[1], self.centre[2])
        return T


@dataclass(frozen=True)
class Mover:
    id: str
    rows: np.ndarray        # [n] int: its primitives in DriveScene.scene
    box: CarBox             # at frame 0
    velocity: float         # m/s along world x (negative: oncoming)
    lane: int

    def x(self, t: float) -> float:
        return self.box.centre[0] + self.velocity * t


@dataclass(frozen=True)
class Standing:
    id: str
    label: str
    box: CarBox


def car_groups(scene: Scene) -> list[np.ndarray]:
    """The primitives of each car (not the ego) in scene order: scene._car writes a body (T_CARBODY) first, then
    its glass and wheels, all class VEHICLE and consecutive."""
    veh = (scene.cls == C.VEHICLE) & ~scene.ego
    groups: list[list[int]] = []
    for i in range(scene.n):
        if veh[i] and scene.tex[i] == T_CARBODY:
            groups.append([i])
        elif veh[i] and groups and groups[-1][-1] == i - 1:
            groups[-1].append(i)
    return [np.array(g, np.int64) for g in groups]


def group_box(geo: np.ndarray, rows: np.ndarray) -> CarBox:
    b = geo[rows[0]]
    top = float(np.max(geo[rows, 2] + geo[rows, 5]))
    return CarBox((float(b[0]), float(b[1]), top / 2.0), (2.0 * float(b[3]), 2.0 * float(b[4]), top),
                  math.atan2(float(b[7]), float(b[6])))


def _rows_to_arrays(b: _Builder) -> dict[str, np.ndarray]:
    """A builder's rows as Scene arrays (road frame = world: no heading offset)."""
    geo = np.array([(*r[1], *r[2], math.cos(r[3]), math.sin(r[3])) for r in b.rows], np.float64).reshape(-1, 8)
    return {"kind": np.array([r[0] for r in b.rows], np.int32), "geo": geo,
            "cls": np.array([r[4] for r in b.rows], np.int32), "tex": np.array([r[5] for r in b.rows], np.int32),
            "col": np.array([r[6] for r in b.rows], np.float64).reshape(-1, 3),
            "col2": np.array([r[7] for r in b.rows], np.float64).reshape(-1, 3),
            "par": np.array([r[8] for r in b.rows], np.float64).reshape(-1, 6),
            "ego": np.array([r[9] for r in b.rows], bool)}


@dataclass(frozen=True, eq=False)
class DriveScene:
    """The street at frame 0 (world frame) with its movers, standing cars and the rig."""

    scene: Scene
    cameras: tuple[Camera, ...]        # the rig, ego frame
    movers: tuple[Mover, ...]
    standing: tuple[Standing, ...]
    removed: int                       # standing cars taken out of the ego's and the movers' ways

    def at(self, cfg: DriveConfig, t: float) -> Scene:
        """The scene at `t` seconds: the movers moved along their lanes, the ego's body at its pose."""
        geo = self.scene.geo.copy()
        for m in self.movers:
            geo[m.rows, 0] += m.velocity * t
        E = ego_pose(cfg, t)
        e = self.scene.ego
        if e.any():
            R = E[:2, :2]
            geo[e, :2] = geo[e, :2] @ R.T + E[:2, 3]
            yaw = np.arctan2(geo[e, 7], geo[e, 6]) + math.atan2(E[1, 0], E[0, 0])
            geo[e, 6], geo[e, 7] = np.cos(yaw), np.sin(yaw)
        return replace(self.scene, geo=geo)


def _lanes(scene: Scene) -> tuple[np.ndarray, int, int, float]:
    """(lane centres [n] metres across, ego lane, forward lanes, lane width)."""
    G = scene.ground
    lane_w, n_lanes, n_fwd = float(G[G_LANEW]), int(G[G_NLANES]), int(G[G_NFWD])
    centres = float(G[G_VD0]) + (np.arange(n_lanes) + 0.5) * lane_w
    return centres, int(np.argmin(np.abs(centres))), n_fwd, lane_w


@functools.lru_cache(maxsize=4)
def drive_scene(cfg: DriveConfig) -> DriveScene:
    """The street, movers and standing cars of `cfg` (deterministic in the config)."""
    scene = sample_scene(cfg.seed, scene_index_of(cfg), SceneConfig(max_psi_deg=0.0, with_ego=True))
    centres, ego_lane, n_fwd, lane_w = _lanes(scene)
    T = cfg.duration_s
    times = np.arange(cfg.frames) / cfg.hz
    ego_x = np.array([ego_pose(cfg, t)[0, 3] for t in times])
    rng = np.random.default_rng([int(cfg.seed), scene_index_of(cfg), 0xD21FE])
    ego_front = float(scene.geo[scene.ego, 0].max() + scene.geo[scene.ego, 3].max()) if scene.ego.any() else 3.6

    # -- movers: drawn first, each a car at the origin moved to its lane --
    placed: list[tuple[int, float, float, float, _Builder]] = []  # lane, x at t=0, velocity, length, rows
    back = [j for j in range(n_fwd, len(centres))]
    fwd = [j for j in range(n_fwd) if j != ego_lane]
    for i in range(cfg.movers):
        for _attempt in range(50):
            b = _Builder()
            oncoming = i % 2 == 0
            kind = str(rng.choice(MOVER_KINDS[0], p=MOVER_KINDS[1]))
            length = _car(b, rng, 0.0, 0.0, math.pi if oncoming else 0.0, kind=kind)
            mid = float(cfg.speed * T / 2)
            if oncoming:
                lane, vel = int(rng.choice(back)), -rng.uniform(*ONCOMING_SPEED)
                x_mid = mid + rng.uniform(-10.0, 10.0)
            elif fwd:
                lane, vel = int(rng.choice(fwd)), rng.uniform(*SAME_WAY_SPEED)
                x_mid = mid + rng.uniform(-12.0, 12.0)
            else:  # the ego lane, ahead of the ego and faster: it pulls away
                lane, vel = ego_lane, cfg.speed + rng.uniform(*AHEAD_EXTRA_SPEED)
                x_mid = ego_front + rng.uniform(8.0, 15.0) + length / 2 + vel * T / 2
            x0 = x_mid - vel * T / 2
            ok = all(lane != ln or np.all(np.abs((x0 + vel * times) - (x1 + v1 * times)) > (length + l1) / 2
                                          + MOVER_GAP_M) for ln, x1, v1, l1, _ in placed)
            if ok:
                placed.append((lane, x0, vel, length, b))
                break
        else:
            raise ValueError(f"movers: cannot place {cfg.movers} movers on this road without collisions; use fewer")

    # -- standing cars out of the ways of the ego and the movers --
    groups = car_groups(scene)
    keep = np.ones(scene.n, bool)
    standing: list[Standing] = []
    removed = 0
    for rows in groups:
        box = group_box(scene.geo, rows)
        x, y = box.centre[0], box.centre[1]
        half = box.size[0] / 2
        ways = [(centres[ego_lane], -1.0, float(ego_x[-1]) + ego_front + CLEAR_AHEAD_M)]
        ways += [(centres[ln], min(x1, x1 + v1 * T) - ln1 / 2 - 1.0, max(x1, x1 + v1 * T) + ln1 / 2 + 1.0)
                 for ln, x1, v1, ln1, _ in placed]
        if any(abs(y - yc) < lane_w / 2 and x + half > lo and x - half < hi for yc, lo, hi in ways):
            keep[rows] = False
            removed += 1
            continue
        standing.append(Standing(f"car_{len(standing):03d}", "Bus" if box.size[0] > 8 else "Car", box))
    arrays = {k: getattr(scene, k)[keep] for k in ("kind", "geo", "cls", "tex", "col", "col2", "par", "ego")}
    # renumber the standing boxes' rows is not needed (boxes only); the movers' rows follow the kept ones
    movers = []
    for i, (lane, x0, vel, _length, b) in enumerate(placed):
        a = _rows_to_arrays(b)
        a["geo"][:, 0] += x0
        a["geo"][:, 1] += centres[lane]
        start = arrays["kind"].shape[0]
        for k in arrays:
            arrays[k] = np.concatenate([arrays[k], a[k]])
        rows = np.arange(start, arrays["kind"].shape[0])
        movers.append(Mover(f"mover_{i}", rows, group_box(arrays["geo"], rows), float(vel), lane))
    arrays = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    scene = replace(scene, **arrays)
    cams = tuple(base_rig(cfg.rig, cfg.width, cfg.height))
    return DriveScene(scene, cams, tuple(movers), tuple(standing), removed)


# --------------------------------------------------------------------------------------------------------------
# frames


@dataclass(eq=False)
class FrameData:
    index: int
    timestamp_s: float
    ego_to_world: np.ndarray
    cameras: tuple[Camera, ...]
    views: list[View]
    lidar: np.ndarray           # [N, 4] float32: x, y, z (ego frame), class id


def frame_name(cfg: DriveConfig, k: int) -> str:
    return f"frame_{k:0{max(2, len(str(cfg.frames - 1)))}d}"


def timestamp(cfg: DriveConfig, k: int) -> float:
    return CLOCK_START_S + k / cfg.hz


def render_frame(cfg: DriveConfig, k: int) -> FrameData:
    """Frame k of the drive: the rig's views at the ego's pose (its body skipped) and a LiDAR sweep."""
    ds = drive_scene(cfg)
    t = k / cfg.hz
    E = ego_pose(cfg, t)
    scene = ds.at(cfg, t)
    grid = build_grid(scene)
    views = [render_view(scene, grid, c.replace(cam_to_ego=E @ c.cam_to_ego), cfg.supersample, True, cfg.shadows)
             for c in ds.cameras]
    return FrameData(k, timestamp(cfg, k), E, ds.cameras, views, lidar_sweep(scene, grid, E))


def _source(cfg: DriveConfig) -> str:
    return (f"xyzcyl synthetic drive v{DRIVE_VERSION} (scene generator v{GENERATOR_VERSION}) seed {cfg.seed} "
            f"scene {scene_index_of(cfg)}")


def write_frame(data: FrameData, folder: Path, cfg: DriveConfig) -> None:
    """Write one frame into `folder` (created; must not exist)."""
    folder.mkdir(parents=True)
    cams = []
    for c, v in zip(data.cameras, data.views):
        files = {"image": f"{c.name}.png", "truth_depth": f"{c.name}_depth.exr", "sky": f"{c.name}_sky.png",
                 "semantic": f"{c.name}_sem.png"}
        _write_png(folder / files["image"], v.rgb)
        write_exr(folder / files["truth_depth"], v.depth[..., None], ("Z",), compression="zip")
        _write_png(folder / files["sky"], (v.sky * 255).astype(np.uint8))
        _write_png(folder / files["semantic"], v.semantic)
        d = c.replace(image=files["image"]).to_dict()
        d["timestamp_s"] = data.timestamp_s
        d["cam_to_world"] = (data.ego_to_world @ c.cam_to_ego).tolist()
        d["truth_depth"], d["sky"], d["semantic"] = files["truth_depth"], files["sky"], files["semantic"]
        cams.append(d)
    np.save(folder / LIDAR_FILE, data.lidar)
    rig = {"source": f"{_source(cfg)} frame {data.index}", "license": "generated (CC0)", "frame": FRAME,
           "generator_version": GENERATOR_VERSION, "seed": cfg.seed, "timestamp_s": data.timestamp_s,
           "ego_to_world": data.ego_to_world.tolist(), "depth_sky_value": 0.0,
           "lidar": {"file": LIDAR_FILE,
                     "format": f"numpy float32 N x 4 (x, y, z in the ego frame, semantic class id); a {BEAMS}-beam "
                               f"spinning LiDAR at {list(MOUNT)} m (ego), elevations {ELEV_MIN_DEG:g}..{ELEV_MAX_DEG:g}"
                               f" deg, range <= {MAX_RANGE_M:g} m, the whole turn at the frame's time",
                     "lidar_to_ego": np.eye(4).tolist(), "timestamp_s": data.timestamp_s},
           "cameras": cams}
    (folder / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")


def tracks_doc(cfg: DriveConfig) -> dict:
    """tracks.json: every car's box at every frame (the PandaSet drive's format; world = frame 0's ego frame)."""
    ds = drive_scene(cfg)
    out = []
    for m in ds.movers:
        out.append({"id": m.id, "label": "Car", "size": list(m.box.size), "stationary": False,
                    "speed_mps": abs(m.velocity),
                    "poses": [{"frame": k, "timestamp_s": timestamp(cfg, k),
                               "object_to_world": m.box.pose(m.velocity * k / cfg.hz).tolist()}
                              for k in range(cfg.frames)]})
    for s in ds.standing:
        pose = s.box.pose().tolist()
        out.append({"id": s.id, "label": s.label, "size": list(s.box.size), "stationary": True,
                    "poses": [{"frame": k, "timestamp_s": timestamp(cfg, k), "object_to_world": pose}
                              for k in range(cfg.frames)]})
    return {"frame": "world (the frame of each rig's ego_to_world: frame 0's ego frame)",
            "object_frame": "x forward along the length, y left, z up; origin at the box centre (ground to roof)",
            "source": _source(cfg), "tracks": out}


def drive_doc(cfg: DriveConfig) -> dict:
    ds = drive_scene(cfg)
    return {"source": _source(cfg), "license": "generated (CC0)", "generator": "xyzcyl.model_export.data.drive",
            "drive_version": DRIVE_VERSION, "generator_version": GENERATOR_VERSION, "config": cfg.to_json(),
            "scene_index": scene_index_of(cfg), "height": cfg.height, "movers": len(ds.movers), "standing_cars": len(ds.standing),
            "removed_cars": ds.removed,
            "frames": [{"rig": f"{frame_name(cfg, k)}/rig.json", "timestamp_s": timestamp(cfg, k), "lidar": True}
                       for k in range(cfg.frames)],
            "tracks": "tracks.json"}


def _write_json_atomic(path: Path, doc: dict) -> None:
    part = path.with_name(path.name + ".part")
    part.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(part, path)


def _write_atomic(data: FrameData, out: Path, cfg: DriveConfig) -> None:
    """Write the frame into out/.tmp/<name> (replacing a leftover partial folder), then rename it to out/<name>."""
    name = frame_name(cfg, data.index)
    part = out / ".tmp" / name
    if part.exists():
        shutil.rmtree(part)
    write_frame(data, part, cfg)
    os.replace(part, out / name)


def _render_and_write(cfg: DriveConfig, k: int, out: Path) -> int:
    _write_atomic(render_frame(cfg, k), out, cfg)
    return k


def synth_drive(out: Path, cfg: DriveConfig, progress: bool = True, workers: int = 1) -> int:
    """Write the drive of `cfg` into `out`, skipping finished frames; returns the number of frames rendered now.

    index.json (the config) is written first: a later run into the same folder must have the same config
    (ValueError naming the field). Each frame is written into out/.tmp and renamed into place, so a frame folder is
    always complete. drive.json, tracks.json and scene.npz are written when every frame is there. `workers` as in
    synth.synth (N spawned processes, each rendering whole frames with cores // N numba threads)."""
    from xyzcyl.common.progress import is_terminal, progress_bar

    out = open_output(out, workers, cfg)
    idx_path = out / "index.json"
    if idx_path.exists():
        old = json.loads(idx_path.read_text()).get("config", {})
        for k, v in cfg.to_json().items():
            if old.get(k) != v:
                raise ValueError(f"{k}: {out} was made with {k}={old.get(k)!r}, not {v!r}")
    _write_json_atomic(idx_path, {"generator": "xyzcyl.model_export.data.drive", "drive_version": DRIVE_VERSION,
                                  "generator_version": GENERATOR_VERSION, "config": cfg.to_json()})
    drive_scene(cfg)  # raises before any frame for an impossible config (movers)
    tmp = out / ".tmp"
    tmp.mkdir(exist_ok=True)
    todo = [k for k in range(cfg.frames) if not (out / frame_name(cfg, k)).is_dir()]
    workers = min(workers, len(todo))
    t0 = time.perf_counter()
    log = progress and not is_terminal(sys.stderr)   # no bar there (a log file): a line per frame instead
    with progress_bar(total=len(todo), desc="synth-drive", unit="frame", enabled=progress) as tq:
        count = [0]

        def done() -> None:
            tq.update()
            count[0] += 1
            if log:
                print(f"synth-drive: {count[0]}/{len(todo)} frames, {time.perf_counter() - t0:.0f} s", file=sys.stderr,
                      flush=True)

        produce(todo, workers, lambda k: render_frame(cfg, k), lambda data: _write_atomic(data, out, cfg),
                functools.partial(_render_and_write, cfg, out=out), done)
    ds = drive_scene(cfg)
    mover = np.full(ds.scene.n, -1, np.int32)
    for i, m in enumerate(ds.movers):
        mover[m.rows] = i
    part = out / "scene.part.npz"
    np.savez_compressed(part, mover=mover, **ds.scene.arrays())
    os.replace(part, out / "scene.npz")
    _write_json_atomic(out / "tracks.json", tracks_doc(cfg))
    _write_json_atomic(out / "drive.json", drive_doc(cfg))
    shutil.rmtree(tmp, ignore_errors=True)
    return len(todo)


__all__ = ["DriveConfig", "DriveScene", "ego_pose", "drive_scene", "render_frame", "synth_drive", "height_for"]
