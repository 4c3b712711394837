"""Drives: a recorded clip of rigs (one per timestamp, each with the ego's pose) reconstructed into one scene.

A drive file (docs/inference.md "Drives"):

    {"frames": [{"rig": "frame_00/rig.json", "timestamp_s": 1557539956.5}, ...], "tracks": "tracks.json"}

paths relative to the drive file, frames in time order. Each rig holds its cameras in its own ego frame and the
ego's pose ``ego_to_world`` (Rig.ego_to_world); ``timestamp_s`` comes from the frame entry or, else, the rig's
top-level ``timestamp_s``. ``tracks`` (optional): annotated objects, each with an id, a label, a box size and
per-frame ``object_to_world`` poses (the format of the PandaSet drive's tracks.json; ``stationary`` when given).
A rig.json alone is a drive of one frame.

The scene's frame is the first frame's ego frame (scene.json records its ``ego_to_world``), so every pose API of a
one-rig scene applies to a drive's scene unchanged.

Reconstruction (reconstruct_drive):
1. keyframes (pick_keyframes): the first frame, then every frame at least ``spacing_m`` metres (the ego's
   position) or ``max_gap_s`` seconds after the last keyframe; the last frame when it adds ground;
2. each keyframe reconstructed as one rig up to its cameras' detail layers (Reconstructor.keyframe), in its own
   ego frame, then moved into the scene's frame (``relative`` = ego_to_world(first)^-1 ego_to_world(k));
   the Gaussians inside the boxes of tracked objects that move (``stationary`` false) leave the static scene: each
   object keeps them as its copy for that keyframe, in its box frame (runtime.actors: drawn at a render's time);
3. fusion: every camera's detail cells are carved as in one frame (runtime.detail.carve_details) against the
   cameras of its own keyframe (a finer copy of the same surface or a view through it) and against the cameras of
   the neighbouring keyframes (a view through it only: the road a later frame saw behind a car that has left);
   the surface seen by several keyframes is then kept once, from its finest observation (dedupe_frames: on voxels
   of about VOXEL_CELLS of the cells' footprints, the keyframe with the finest cell in a voxel keeps it; among
   equally fine ones the keyframe that saw it from nearest, keyframes of a still ego being one viewpoint); the
   model's Gaussians of every keyframe fill what no cell covers (runtime.detail.cull_covered), kept once per
   voxel the same way. Cells another keyframe drops are removed, not hidden: the scene has no own views; but a
   cell its own LiDAR placed that a neighbouring keyframe with LiDAR sees through moved away (_carve_pair): it is
   drawn only around its keyframe's time (actors_of, moved_spans), as an untracked object of that keyframe.
4. the ground under the tracked moving objects that no keyframe saw (they stood on it) is filled with the
   surrounding road's colour (runtime.groundfill), kept with the actors and drawn behind everything where a view
   hides or moves one (a view's actor edits: runtime.actors), so it leaves road, not the background panorama.

Before the keyframes, the ego's own body is found over the drive's frames (runtime.egobody: the pixels that stay
put while the world moves) and used as the cameras' ego masks; the scene keeps them (Scene.ego_body).

Each keyframe's cameras' exposure and white balance are harmonised as it arrives (runtime.exposure), against each
other and the previous keyframe's; the gains go into scene.json's drive block.

What is not done yet (docs/inference.md "Drives" lists it): moving objects found without tracks in a camera-only
drive, untracked objects drawn at their pose between keyframes, mirrors found as the ego's body. (The shared
Gaussians are kept in spatial tiles that views read and draw as they need them: runtime.tiles, by Scene.)
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numba
import numpy as np
from xyzcyl.common.wire import is_drive_file

from .actors import MOVED_LABEL
from .boxes import box_members, inside_boxes, snap_into_boxes
from .camera import check_pose
from .egobody import EgoBody
from .errors import FieldError, RigError
from .groundfill import fill_lattice, fill_lattice_under
from .heap import release_heap
from .numba_cache import njit, threadsafe
from .render import FIELDS, Gaussians
from .rig import Rig, load_rig
from .viewpoints import morton_code
from .voxelhash import capacity, cell_voxel, compact, empty_table, local_owners, rehash, take_over

MAX_SPEED_MPS = 100.0          # an ego faster than this between two frames is a pose error (360 km/h)
DEFAULT_SPACING_M = 1.5        # keyframe spacing: a drive posted at ~2 m spacing is used whole
DEFAULT_MAX_GAP_S = 2.0        # a keyframe at least this often, moving or not
# reconstruct_drive: keyframes made ahead in worker processes while this one fuses. 0 (all in one process) by
# default: on 2 cores a worker was slower (5 PandaSet keyframes: 33.5 s with one, 29.9 s without; both processes
# want both cores, and each keyframe's cells cross a pipe), and a script that starts workers needs the
# `if __name__ == "__main__":` guard of every multiprocessing program; machines with cores to spare ask for them
DEFAULT_WORKERS = 0            # 0: keyframes made in this process, one ahead in a thread (_keyframes_made)
CHUNKS_AHEAD = 2               # keyframes' chunks made at once at the end (_in_order): two cores
LAYER_READS = 2                # camera layer files read at once at the end (_Kept._from_layers): one's rows taken while
                               # the disk reads the other
CARVE_WINDOW = 2               # keyframes before and after whose cameras may carve a keyframe's cells
VOXEL_BASE_M = 0.02            # dedupe_frames: the finest voxel (2 cm); a cell's voxel is the power of two above
VOXEL_LEVELS = 12              # VOXEL_CELLS x its footprint, up to 2 cm x 2^11 = 41 m
VOXEL_CELLS = 4                # a voxel spans ~4 cells across: one keyframe owns each patch of a surface (at 1
#                                cell a voxel, two keyframes' cells of one surface fell in different voxels and
#                                both stayed, interleaved: the PandaSet drive kept 2.0x one frame's Gaussians)
VIEWPOINT_RADIUS_M = 0.5       # keyframes whose ego stood within this of a group's first see from one viewpoint
# _carve_pair (and, in a keyframe without a LiDAR sweep, its own cameras' carving): a camera sees through another's
# cell only where its image shows no colour like the cell's near that spot (runtime.detail.colour_seen: every
# channel within 12 + 0.15 x the larger value, sRGB 0..255; the relative part covers the exposure that harmonising
# leaves between cameras, ~1.1x). Glass, fences and edges, whose depth two LiDAR sweeps put apart, were carved (or
# drawn only around their keyframe's time) though both images show them. 6 + 0.08 and 20 + 0.25 score within 0.06 dB
# of it (docs/results.md "Drives: seeing through a cell needs another colour")
SEE_THROUGH_PHOTO = (12.0, 0.15)
TRACK_GROW = 1.1               # a moving object's box, grown by this factor, holds its Gaussians
# commit: the C heap handed back between keyframes only when it holds more than this free (runtime.heap). Each
# keyframe allocates and frees ~0.5 GB of the same sizes: handed back every time, they were fresh pages to fault
# in and zero at the next (20 PandaSet keyframes: ~1/3 of the drive's CPU time in the kernel). The same between the
# chunks at the end (handed back before each, 0.7-0.9 GB each time: 5 pairs, median 1.02x slower, the same peak)
HEAP_KEPT_BYTES = 1 << 30
SPILL_MIN_M = 0.25             # spill_boxes' least margin (a box's annotation is a few centimetres off the object)


class DriveError(FieldError):
    """A drive that cannot be used: ``field`` is the drive file's field ("frames[3].timestamp_s",
    "tracks[2].poses[0].frame"), ``where`` the drive file."""


@dataclass(frozen=True)
class DriveFrame:
    index: int                 # its place in the drive's frames
    rig_path: Path             # its rig.json
    rig: Rig                   # its cameras, in its ego frame
    timestamp_s: float         # seconds on the rigs' clock
    ego_to_world: np.ndarray   # [4, 4] ego -> world, metres


@dataclass(frozen=True)
class Track:
    id: str
    label: str
    size: tuple[float, float, float]      # length, width, height, metres (box along the object's x, y, z)
    stationary: bool
    poses: dict[int, np.ndarray]          # frame index -> [4, 4] object -> world (box centre, x along its length)


@dataclass(frozen=True)
class Drive:
    path: Path | None
    frames: tuple[DriveFrame, ...]
    tracks: tuple[Track, ...] = ()

    def __len__(self) -> int:
        return len(self.frames)

    def relative(self, k: int) -> np.ndarray:
        """[4, 4] frame k's ego -> the scene's frame (the first frame's ego frame)."""
        return np.linalg.inv(self.frames[0].ego_to_world) @ self.frames[k].ego_to_world

    def trajectory(self) -> np.ndarray:
        """[F, 4, 4] every frame's ego pose in the scene's frame."""
        return np.stack([self.relative(k) for k in range(len(self.frames))])


def _where(path: Path) -> str:
    return f"drive {str(path)!r}"


def _read_json(path: Path, field: str, where: str) -> Any:
    """The JSON document of ``path``; DriveError naming ``field`` when it cannot be read or is not JSON."""
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise DriveError(field, f"cannot read {str(path)!r}: {e.strerror or e}") from None
    except ValueError as e:
        raise DriveError(field, f"not JSON ({e})", where) from None


def load_drive(path: str | os.PathLike, check_images: bool = True) -> Drive:
    """The drive of a drive file, every frame's rig read and checked (module docstring); DriveError naming the
    frame and the field: a frame without ego_to_world or timestamp_s (when there are several frames), frames out of
    time order or at one time, a jump faster than MAX_SPEED_MPS, a frame whose cameras are not the first frame's,
    tracks that name a frame the drive lacks. Frames with and without LiDAR may mix (each keyframe uses its own
    sweep when it has one)."""
    p = Path(path)
    where = _where(p)
    doc = _read_json(p, "drive", where)
    if not isinstance(doc, dict):
        raise DriveError("drive", "must be a JSON object with \"frames\"", where)
    items = doc.get("frames")
    if not isinstance(items, list) or not items:
        raise DriveError("frames", "must be a non-empty list of {\"rig\": \"frame/rig.json\"}", where)
    frames: list[DriveFrame] = []
    for i, item in enumerate(items):
        f = f"frames[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("rig"), str):
            raise DriveError(f"{f}.rig", "must name the frame's rig.json (a path relative to the drive file)", where)
        rig_path = p.parent / item["rig"]
        try:
            rig = load_rig(rig_path, check_images=check_images)
        except RigError as e:
            raise DriveError(f"{f}.rig", str(e), where) from None
        except OSError as e:
            raise DriveError(f"{f}.rig", f"cannot read {str(rig_path)!r}: {e.strerror or e}", where) from None
        ts = item.get("timestamp_s", rig.extra.get("timestamp_s"))
        if ts is not None and (isinstance(ts, bool) or not isinstance(ts, (int, float)) or not math.isfinite(ts)):
            raise DriveError(f"{f}.timestamp_s", f"must be a finite number of seconds (got {ts!r:.60})", where)
        if len(items) > 1:
            if rig.ego_to_world is None:
                raise DriveError(f"{f}.rig", f"{item['rig']} has no ego_to_world: a drive needs each frame's ego "
                                             "pose", where)
            if ts is None:
                raise DriveError(f"{f}.timestamp_s", "is missing (in the frame entry or its rig.json)", where)
        pose = np.eye(4) if rig.ego_to_world is None else rig.ego_to_world
        frames.append(DriveFrame(i, rig_path, rig, 0.0 if ts is None else float(ts), pose))
        if i:
            prev, cur = frames[i - 1], frames[i]
            if not cur.timestamp_s > prev.timestamp_s:
                raise DriveError(f"{f}.timestamp_s", f"{cur.timestamp_s!r} is not after frames[{i - 1}]'s "
                                                     f"{prev.timestamp_s!r} (frames in time order, each at its "
                                                     "own time)", where)
            step = float(np.linalg.norm(cur.ego_to_world[:3, 3] - prev.ego_to_world[:3, 3]))
            speed = step / (cur.timestamp_s - prev.timestamp_s)
            if speed > MAX_SPEED_MPS:
                raise DriveError(f"{f}.rig", f"the ego moved {step:.1f} m in {cur.timestamp_s - prev.timestamp_s:.3g} "
                                             f"s since frames[{i - 1}] ({speed:.0f} m/s, more than "
                                             f"{MAX_SPEED_MPS:g}): a pose in another world frame?", where)
            if rig.names != frames[0].rig.names:
                raise DriveError(f"{f}.rig", f"cameras {rig.names} are not frames[0]'s {frames[0].rig.names} (a "
                                             "drive keeps one rig)", where)
    tracks: tuple[Track, ...] = ()
    if doc.get("tracks") is not None:
        if not isinstance(doc["tracks"], str):
            raise DriveError("tracks", "must name a tracks file (a path relative to the drive file)", where)
        tracks = load_tracks(p.parent / doc["tracks"], len(frames))
    return Drive(p, tuple(frames), tracks)


def drive_of_rig(rig: Rig, rig_path: Path | None = None) -> Drive:
    """A one-frame drive of ``rig``."""
    pose = np.eye(4) if rig.ego_to_world is None else rig.ego_to_world
    ts = rig.extra.get("timestamp_s")
    return Drive(None, (DriveFrame(0, rig_path or Path("rig.json"), rig, float(ts) if ts is not None else 0.0,
                                   pose),))


def load_tracks(path: Path, n_frames: int) -> tuple[Track, ...]:
    """The tracks of a tracks file ({"tracks": [...]} or a list); DriveError naming the track's field."""
    where = f"tracks {str(path)!r}"
    doc = _read_json(path, "tracks", where)
    items = doc.get("tracks") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise DriveError("tracks", "must be a list of objects (or {\"tracks\": [...]})", where)
    out = []
    for i, t in enumerate(items):
        f = f"tracks[{i}]"
        if not isinstance(t, dict):
            raise DriveError(f, "must be an object", where)
        size = t.get("size")
        if not (isinstance(size, list) and len(size) == 3 and all(isinstance(x, (int, float)) and not
                                                                   isinstance(x, bool) and x > 0 for x in size)):
            raise DriveError(f"{f}.size", f"must be [length, width, height] metres > 0 (got {size!r:.60})", where)
        poses: dict[int, np.ndarray] = {}
        for j, pose in enumerate(t.get("poses") or []):
            fr = pose.get("frame") if isinstance(pose, dict) else None
            if isinstance(fr, bool) or not isinstance(fr, int) or not 0 <= fr < n_frames:
                raise DriveError(f"{f}.poses[{j}].frame", f"must be a frame of the drive, 0..{n_frames - 1} "
                                                          f"(got {fr!r:.60})", where)
            try:
                poses[fr] = check_pose(pose.get("object_to_world"), where, f"{f}.poses[{j}].object_to_world")
            except RigError as e:
                raise DriveError(e.field, e.message, where) from None
        out.append(Track(id=str(t.get("id", i)), label=str(t.get("label", "")), size=tuple(float(x) for x in size),
                         stationary=bool(t.get("stationary", False)), poses=poses))
    return tuple(out)


# ------------------------------------------------------------------------------------------- keyframes


def pick_keyframes(drive: Drive, spacing_m: float | None = None, max_gap_s: float | None = None,
                   every: int | None = None) -> list[int]:
    """The frames to reconstruct: the first, then each frame at least ``spacing_m`` metres (the ego's position;
    None: DEFAULT_SPACING_M) or ``max_gap_s`` seconds (None: DEFAULT_MAX_GAP_S) after the last keyframe, and the
    last frame when it is at least half a spacing away from the last keyframe. ``every``: every Nth frame instead
    (evaluation). `xyzcyl reconstruct DRIVE.json` and the service (POST /v1/scenes' keyframe_spacing /
    keyframe_gap) pick them so."""
    spacing_m = DEFAULT_SPACING_M if spacing_m is None else spacing_m
    max_gap_s = DEFAULT_MAX_GAP_S if max_gap_s is None else max_gap_s
    n = len(drive.frames)
    if every is not None:
        if every < 1:
            raise DriveError("every", f"must be >= 1 (got {every})")
        return list(range(0, n, every))
    if not spacing_m > 0 or not max_gap_s > 0:
        raise DriveError("spacing_m" if not spacing_m > 0 else "max_gap_s", "must be > 0")
    keys = [0]
    for k in range(1, n):
        last = drive.frames[keys[-1]]
        cur = drive.frames[k]
        far = np.linalg.norm(cur.ego_to_world[:3, 3] - last.ego_to_world[:3, 3])
        if far >= spacing_m or cur.timestamp_s - last.timestamp_s >= max_gap_s:
            keys.append(k)
    if keys[-1] != n - 1:
        far = np.linalg.norm(drive.frames[-1].ego_to_world[:3, 3] - drive.frames[keys[-1]].ego_to_world[:3, 3])
        if far >= 0.5 * spacing_m:
            keys.append(n - 1)
    return keys


# ------------------------------------------------------------------------------------------- moving things


def transform_gaussians(g: Gaussians, T: np.ndarray) -> Gaussians:
    """``g`` moved by the rigid [4, 4] ``T`` (Gaussians.transformed); DriveError for SH above degree 0."""
    from .render import GaussianError

    try:
        return g.transformed(T)
    except GaussianError as e:
        raise DriveError("sh", f"a drive's keyframes: {e.message}") from None


def transform_detail(d, T: np.ndarray):
    """A runtime.detail.CameraDetail moved by the rigid [4, 4] ``T`` (its grid camera's pose and its cells'
    centres; depths and footprints are the camera's own and stay)."""
    R = np.asarray(T[:3, :3], np.float64)
    return replace(d, grid=d.grid.replace(cam_to_ego=T @ d.grid.cam_to_ego), means=d.means @ R.T + T[:3, 3],
                   split=None if d.split is None else d.split.moved(T))


def moving_tracks(drive: Drive) -> list[int]:
    """The indices of the tracks that move (``stationary`` false) and have an annotated pose."""
    return [i for i, t in enumerate(drive.tracks) if not t.stationary and t.poses]


def moving_boxes(drive: Drive, k: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(track index, scene frame -> box [4, 4], half-sizes grown by TRACK_GROW) of the tracked objects that move,
    at frame k (the tracks annotated at that frame)."""
    E0 = drive.frames[0].ego_to_world
    out = []
    for i in moving_tracks(drive):
        t = drive.tracks[i]
        if k not in t.poses:
            continue
        box_to_scene = np.linalg.inv(E0) @ t.poses[k]
        out.append((i, np.linalg.inv(box_to_scene), 0.5 * TRACK_GROW * np.asarray(t.size)))
    return out


def track_speed(drive: Drive, track: Track, k: int) -> float:
    """Metres per second: how fast ``track`` moves at frame k, from its annotated poses at the frames nearest before
    and after k (k's own when it has no pose on one side); 0 with fewer than two."""
    frames = sorted(track.poses)
    before = [f for f in frames if f < k]
    after = [f for f in frames if f > k]
    a = before[-1] if before else (k if k in track.poses else None)
    b = after[0] if after else (k if k in track.poses else None)
    if a is None or b is None or a == b:
        return 0.0
    dt = drive.frames[b].timestamp_s - drive.frames[a].timestamp_s
    return float(np.linalg.norm(track.poses[b][:3, 3] - track.poses[a][:3, 3]) / dt) if dt > 0 else 0.0


def spill_boxes(drive: Drive, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(scene frame -> box [4, 4], half-sizes [3]) of the objects that move at frame k (moving_boxes), each grown on
    every side by how far it moves in one frame interval (track_speed x the drive's frame_interval), at least
    SPILL_MIN_M: where a keyframe's sweep and cameras put cells of the object outside its box. A sweep takes a frame
    interval to turn (a PandaSet Pandar64: 0.1 s), and a camera fires at one moment of it: a car at 10 m/s has moved
    a metre between the returns that met it and the pixels that saw it, so cells placed by the returns land beside
    it, on its colour. Cells that moved away (_carve_pair) within these are that spill, not something that stood
    there: runtime.drive leaves them out of the keyframe's moved cells (an object is drawn from its copy, in its box)."""
    from .actors import frame_interval

    dt = frame_interval([f.timestamp_s for f in drive.frames])
    return [(inv, half + max(SPILL_MIN_M, track_speed(drive, drive.tracks[i], k) * dt))
            for i, inv, half in moving_boxes(drive, k)]


def without_spill(g: Gaussians, boxes: Sequence[tuple[np.ndarray, np.ndarray]]) -> Gaussians:
    """The Gaussians of ``g`` (scene frame) in none of ``boxes`` (spill_boxes)."""
    return g if not boxes or not len(g) else g.subset(box_members(g.means, boxes) < 0)


def moved_spans(times: Sequence[float], first_s: float, last_s: float, slack_s: float) -> list[tuple[float, float]]:
    """Per keyframe (``times`` [K] seconds, ascending): the (first, last) times its cells that moved away are drawn
    at (runtime.actors draws an object from ``first - slack_s`` to ``last + slack_s``): from halfway to the keyframe
    before (the drive's first frame ``first_s`` for the first keyframe) to halfway to the one after (``last_s``),
    narrowed by the slack on either side, so that at any time one keyframe's are drawn (two exactly at a
    midpoint); never narrower than the keyframe's own time."""
    t = [float(x) for x in times]
    out = []
    for i, tk in enumerate(t):
        lo = first_s if i == 0 else 0.5 * (t[i - 1] + tk) + slack_s
        hi = last_s if i == len(t) - 1 else 0.5 * (tk + t[i + 1]) - slack_s
        out.append((min(lo, tk), max(hi, tk)))
    return out


def actors_of(drive: Drive, copies: list[tuple[int, float, Gaussians]],
              moved: Sequence[tuple[int, Gaussians]] = (), keys: Sequence[int] = ()):
    """runtime.actors.Actors of the drive's moving tracks (every annotated pose, box -> scene frame, at its frame's
    time) and ``copies`` (track index, keyframe time, Gaussians in the box frame); then, one object a keyframe, the
    cells that moved away (``moved``: (index into ``keys``, Gaussians in the scene's frame), runtime.drive's
    carving across keyframes): label MOVED_LABEL, id "moved@<frame>", its box the cells' bounds, at the scene's
    frame (identity poses) over moved_spans. None when there is neither."""
    from .actors import Actors, frame_interval

    moving = moving_tracks(drive)
    moved = [(n, g) for n, g in moved if len(g)]
    if not moving and not moved:
        return None
    index = {t: a for a, t in enumerate(moving)}
    E0inv = np.linalg.inv(drive.frames[0].ego_to_world)
    pt, ptime, pose = [], [], []
    for t in moving:
        for fr, m in sorted(drive.tracks[t].poses.items()):
            pt.append(index[t])
            ptime.append(drive.frames[fr].timestamp_s)
            pose.append(E0inv @ m)
    kept = [(index[t], ts, g) for t, ts, g in copies if len(g)]
    ids = [drive.tracks[t].id for t in moving]
    labels = [drive.tracks[t].label for t in moving]
    sizes = [drive.tracks[t].size for t in moving]
    if moved:
        times = [drive.frames[k].timestamp_s for k in keys]
        slack = 0.5 * frame_interval([f.timestamp_s for f in drive.frames])     # Scene.moving_at's slack
        spans = moved_spans(times, drive.frames[0].timestamp_s, drive.frames[-1].timestamp_s, slack)
        for n, g in moved:
            a = len(ids)
            ids.append(f"moved@{keys[n]}")
            labels.append(MOVED_LABEL)
            lo, hi = g.means.min(axis=0).astype(np.float64), g.means.max(axis=0).astype(np.float64)
            sizes.append(tuple(float(x) for x in hi - lo))
            for ts in spans[n]:
                pt.append(a)
                ptime.append(ts)
                pose.append(np.eye(4))
            kept.append((a, times[n], g))
    starts = np.cumsum([0] + [len(g) for _, _, g in kept])
    g = _concat([g for _, _, g in kept]) if kept else Gaussians.empty(0)
    return Actors(track_id=tuple(ids), track_label=tuple(labels), track_size=np.array(sizes, np.float64),
                  pose_track=np.array(pt, np.int32), pose_time=np.array(ptime, np.float64),
                  pose=np.array(pose, np.float64).reshape(-1, 4, 4),
                  copy_track=np.array([a for a, _, _ in kept], np.int32),
                  copy_time=np.array([ts for _, ts, _ in kept], np.float64),
                  copy_start=starts.astype(np.int64), gaussians=g)


# ------------------------------------------------------------------------------------------- fusion


def voxel_levels(footprint: np.ndarray) -> np.ndarray:
    """[N] int8: each footprint's voxel level, the smallest L with VOXEL_BASE_M 2^L >= VOXEL_CELLS x the footprint
    (metres), clipped to 0..VOXEL_LEVELS - 1."""
    f = np.maximum(VOXEL_CELLS * np.asarray(footprint, np.float64), 1e-9)
    return np.clip(np.ceil(np.log2(f / VOXEL_BASE_M)), 0, VOXEL_LEVELS - 1).astype(np.int8)


def dedupe_frames(points: np.ndarray, level: np.ndarray, frame: np.ndarray,
                  origins: np.ndarray | None = None) -> np.ndarray:
    """[N] bool, what to keep of cells from several keyframes (points [N, 3] metres in one frame, level [N] their
    voxel_levels, frame [N] their keyframe; origins [K, 3] metres, where each keyframe saw from: the ego position of
    its viewpoint group, viewpoint_origins): a cell at level L looks at its voxel of size VOXEL_BASE_M 2^L and the
    cells in it at level L or finer; the best of them owns the voxel, and the cell is kept only when that is its own
    keyframe. Best: the finest (the lowest level); among equally fine ones, the keyframe that saw the voxel from
    nearest (the distance from the voxel's centre to its origin; without origins, all equally near); then the
    earliest keyframe. So a keyframe's surface is replaced where another keyframe resolved it more finely or, as
    finely, from closer by, and cells of one keyframe never drop each other (that is its own fusion's work).
    Voxels nest (each level's grid halves the next) and the owner of a voxel is never dropped, so the result does
    not depend on the order cells arrive in: adding keyframes one at a time and deduping each time keeps what
    deduping them all at once keeps. dedupe_frames_reference is its definition."""
    n = len(points)
    keep = np.ones(n, bool)
    if n == 0:
        return keep
    level = np.asarray(level, np.int64)
    frame = np.asarray(frame, np.int64)
    owners = _NO_OWNERS
    for L in range(int(level.max()) + 1):      # level by level, fine to coarse (_owners_up)
        here = np.flatnonzero(level == L)
        owners, _, _, at, _ = _owners_up(owners, points[here], level[here], frame[here], L, origins)
        if len(here):
            keep[here] = owners[3][at] == frame[here]
    return keep


_NO_OWNERS = (np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64), np.zeros(0, np.int64))


def _owners_up(owners: tuple, points: np.ndarray, level: np.ndarray, frame: np.ndarray, L: int,
               origins: np.ndarray | None) -> tuple[tuple, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One level of dedupe_frames, fine to coarse: a voxel's owner at level L is the best of its cells at this level
    and the owners of its eight children (the voxels of the level below: their coordinates halved), so each step
    sorts the owners so far and this level's cells, not every finer cell again; an owner keeps its (level,
    distance, keyframe). owners: (voxel coordinates [M, 3] at level L - 1 (ignored at L 0), level, distance,
    keyframe) of the level below; points [n, 3] metres, level, frame [n]: this level's cells. Returns (the owners of
    level L's voxels, their packed keys (ascending, one per voxel), the packed keys of this level's cells [n], each
    cell's voxel (its index in the owners) [n] int64, the cells in the order of their keys [n] int64 (a stable
    order: np.argsort(their keys, kind="stable"), from the sort of all the keys))."""
    oc, olev, odist, oframe = owners
    if L:
        oc = np.floor_divide(oc, 2)
    size = VOXEL_BASE_M * 2.0 ** L
    n_o, n = len(oc), len(points)
    coords = np.empty((n_o + n, 3), np.int64)
    coords[:n_o] = oc
    dists = np.empty(n_o + n, np.float64)
    dists[:n_o] = odist
    keys = np.empty(n_o + n, np.int64)
    keys[:n_o] = _pack(oc)
    # this level's cells: voxel, packed key and distance in one pass (_cell_voxels; the numpy of _pack and
    # _voxel_distance_reference, the same bits)
    _cell_voxels(np.ascontiguousarray(points), size, np.ascontiguousarray(frame, np.int64),
                 _NO_ORIGINS if origins is None else np.ascontiguousarray(origins, np.float64), origins is not None,
                 coords[n_o:], keys[n_o:], dists[n_o:])
    levs = np.concatenate([olev, level])
    frames = np.concatenate([oframe, frame])
    order = np.argsort(keys, kind="stable")
    k_sorted = keys[order]
    run_of = np.empty(len(keys), np.int64)
    win = _best_of_runs(order, k_sorted, levs, dists, frames, run_of)
    cells = order[order >= n_o] - n_o
    return (coords[win], levs[win], dists[win], frames[win]), keys[win], keys[n_o:], run_of[n_o:], cells


_NO_ORIGINS = np.zeros((0, 3), np.float64)
_NO_ORIGIN = np.zeros(3, np.float64)


@njit(cache=True, parallel=True, nogil=True)
def _cell_voxels(points, size, frame, origins, with_origins, coords, keys, dists):
    """For each point [N, 3] (metres): its voxel coords = floor(point / size) (float64), its _pack key and its
    distance to its keyframe's origin (frame [N], origins [K, 3]; _voxel_distance_reference; 0 without origins),
    written to coords [N, 3], keys [N], dists [N] (the numpy's operations
    and order: the same bits)."""
    for i in numba.prange(points.shape[0]):
        if with_origins:
            c0, c1, c2, key, d = cell_voxel(points, i, size, origins[frame[i]], True)
        else:
            c0, c1, c2, key, d = cell_voxel(points, i, size, _NO_ORIGIN, False)
        coords[i, 0], coords[i, 1], coords[i, 2] = c0, c1, c2
        keys[i], dists[i] = key, d


@njit(cache=True, nogil=True)
def _best_of_runs(order, k_sorted, levs, dists, frames, run_of):
    """[V] int64: for each run of equal keys in ``k_sorted`` (= keys[order], ``order`` a stable argsort), the entry
    of the best rank (level, distance, keyframe), the earliest among equals: what the first of each run of
    np.lexsort((frames, dists, levs, keys)) is, in one pass over the sorted keys. run_of [N] int64 (written): each
    entry's run, its index in the result (what np.searchsorted(keys[result], keys) gives, without the search)."""
    n = len(order)
    out = np.empty(n, np.int64)
    v = 0
    i = 0
    while i < n:
        best = order[i]
        run_of[best] = v
        j = i + 1
        while j < n and k_sorted[j] == k_sorted[i]:
            c = order[j]
            run_of[c] = v
            if levs[c] < levs[best] or (levs[c] == levs[best] and (dists[c] < dists[best] or (
                    dists[c] == dists[best] and frames[c] < frames[best]))):
                best = c
            j += 1
        out[v] = best
        v += 1
        i = j
    return out[:v]


SCRATCH_CELLS = 8          # VoxelOwners: a keyframe's cells per voxel it first sizes its own table for (~10 seen)


class VoxelOwners:
    """dedupe_frames kept up to date as keyframes arrive, at a cost that follows each keyframe's cells rather than
    all the cells so far: per voxel level, the owner of every voxel that holds a kept cell (its rank: level, distance,
    keyframe; the best of the kept cells in it at that level or finer) and the kept cells at exactly that level by
    voxel, in hash tables (runtime.voxelhash). A keyframe's cells take a voxel over where their best beats its owner;
    the kept cells at that level in it are then lost. Owners are never lost (a lost cell ranks below its voxel's new
    owner, and so below every coarser voxel's), so this keeps what dedupe_frames keeps over all the cells added,
    whatever the order (the tests)."""

    def __init__(self, origins: np.ndarray | None = None):
        self.origins = None if origins is None else np.asarray(origins, np.float64)
        slots = capacity(0)
        # per level: the voxels with an owner (keys), their owner's rank (level, distance, keyframe) and the first of
        # their kept cells at that level (an entry, -1: none; a free slot's is not read)
        self.keys = [empty_table(slots) for _ in range(VOXEL_LEVELS)]
        self.lev = [np.zeros(slots, np.int8) for _ in range(VOXEL_LEVELS)]
        self.dist = [np.zeros(slots, np.float64) for _ in range(VOXEL_LEVELS)]
        self.frame = [np.zeros(slots, np.int64) for _ in range(VOXEL_LEVELS)]
        self.head = [np.zeros(slots, np.int64) for _ in range(VOXEL_LEVELS)]
        self.voxels = [0] * VOXEL_LEVELS
        self.ent_id = np.zeros(1024, np.int64)      # the entries: a kept cell's id, the next entry of its voxel
        self.nxt = np.zeros(1024, np.int64)
        self.n_ent = 0
        self.live = 0                               # entries a chain reaches (kept cells); the rest were lost
        self.scratch = empty_table(capacity(0))     # a keyframe's own owners at one level (voxelhash.local_owners)
        self.scratch_v = np.zeros(len(self.scratch), np.int64)

    def _room(self, L: int, more: int) -> None:
        """Level L's table with room for ``more`` keys (a load of at most one half)."""
        need = capacity(self.voxels[L] + more)
        if need <= len(self.keys[L]):
            return
        new = (empty_table(need), np.zeros(need, np.int8), np.zeros(need, np.float64), np.zeros(need, np.int64),
               np.zeros(need, np.int64))
        rehash(self.keys[L], self.lev[L], self.dist[L], self.frame[L], self.head[L], *new)
        self.keys[L], self.lev[L], self.dist[L], self.frame[L], self.head[L] = new

    def _entries(self, more: int) -> None:
        """Room for ``more`` entries; the lost ones dropped first when they are most of them."""
        if self.n_ent + more <= len(self.ent_id):
            return
        size = max(2 * len(self.ent_id), 2 * (self.live + more))
        new_id, new_nxt = np.empty(size, np.int64), np.empty(size, np.int64)
        if self.n_ent > 2 * self.live:
            n = 0
            for keys, head in zip(self.keys, self.head):
                n = compact(keys, head, self.ent_id, self.nxt, new_id, new_nxt, n)
            self.n_ent = n
        else:
            new_id[:self.n_ent], new_nxt[:self.n_ent] = self.ent_id[:self.n_ent], self.nxt[:self.n_ent]
        self.ent_id, self.nxt = new_id, new_nxt

    def add(self, points: np.ndarray, level: np.ndarray, frame: int, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One keyframe's cells (points [M, 3] metres, level [M] voxel_levels, all of keyframe ``frame``, ``ids`` [M]
        int64 the caller's names for them) -> (keep [M] bool: the cells that own their voxel, the ids of cells added
        before that are lost to them)."""
        level = np.clip(np.asarray(level, np.int64), 0, VOXEL_LEVELS - 1)
        ids = np.ascontiguousarray(ids, np.int64)
        points = np.ascontiguousarray(points)
        keep = np.zeros(len(level), bool)
        if not len(level):
            return keep, np.zeros(0, np.int64)
        origin = self.origins[int(frame)] if self.origins is not None else np.zeros(3)
        lost = np.empty(self.live, np.int64)        # at most every kept cell
        n_lost = 0
        self._entries(len(level))
        # the cells level by level, each level's in index order (a stable sort of the levels, 0..11: a radix sort)
        by_level = np.argsort(level.astype(np.uint8), kind="stable")
        starts = np.searchsorted(level[by_level], np.arange(VOXEL_LEVELS + 1))
        prev = (np.zeros((0, 3), np.int64), np.zeros(0, np.int8), np.zeros(0, np.float64))
        for L in range(VOXEL_LEVELS):
            here = by_level[starts[L]:starts[L + 1]]
            n_in = len(prev[1]) + len(here)
            if not n_in:
                continue
            oc, ol, od, ok = (np.empty((n_in, 3), np.int64), np.empty(n_in, np.int8), np.empty(n_in, np.float64),
                              np.empty(n_in, np.int64))
            owner = np.empty(len(here), np.int64)
            # a table for a voxel per SCRATCH_CELLS cells first (it stays in cache), for one per cell if that is short
            v = -1
            for slots in (capacity(n_in // SCRATCH_CELLS), capacity(n_in)):
                if slots > len(self.scratch):
                    self.scratch, self.scratch_v = empty_table(slots), np.zeros(slots, np.int64)
                v = local_owners(*prev, points, here, VOXEL_BASE_M * 2.0 ** L, L, origin, self.origins is not None,
                                 self.scratch[:slots], self.scratch_v[:slots], oc, ol, od, ok, owner)
                if v >= 0:
                    break
            self._room(L, v)
            kept = np.empty(len(here), bool)
            added, self.n_ent, n_lost = take_over(
                self.keys[L], self.lev[L], self.dist[L], self.frame[L], self.head[L], ok, ol, od, v, int(frame),
                owner, ids[here], self.ent_id, self.nxt, self.n_ent, lost, n_lost, np.empty(v, bool),
                np.empty(v, np.int64), kept)
            self.voxels[L] += added
            keep[here] = kept
            prev = (oc[:v], ol[:v], od[:v])
        n_kept = int(keep.sum())
        self.live += n_kept - n_lost
        return keep, lost[:n_lost].copy()


def _voxel_distance_reference(coords: np.ndarray, size: float, frame: np.ndarray,
                              origins: np.ndarray | None) -> np.ndarray:
    """[N] metres from the centres of voxels ``coords`` [N, 3] (integer, of edge ``size`` metres) to the origins of
    keyframes ``frame`` [N] (0 without origins): what _cell_voxels computes (its test). Cells of one viewpoint group
    in one voxel get the same value exactly (the same centre, the same origin): their tie goes to the earliest
    keyframe."""
    if origins is None:
        return np.zeros(len(coords), np.float64)
    centre = (coords.astype(np.float64) + 0.5) * size
    return np.linalg.norm(centre - np.asarray(origins, np.float64)[frame], axis=1)


def viewpoint_groups(positions: np.ndarray, radius_m: float | None = None) -> np.ndarray:
    """[K] int: each keyframe's viewpoint group, the index of the group's first keyframe, from the ego positions
    [K, 3] (scene frame, in keyframe order): a keyframe within ``radius_m`` (default VIEWPOINT_RADIUS_M) of the first
    keyframe of the current group joins it, else it starts a group of its own. An ego that stands still (the
    PandaSet drive's first 2 s) is one viewpoint."""
    radius = VIEWPOINT_RADIUS_M if radius_m is None else radius_m
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    head = np.zeros(len(positions), np.int64)
    for k, p in enumerate(positions):
        head[k] = k if k == 0 or np.linalg.norm(p - positions[head[k - 1]]) > radius else head[k - 1]
    return head


def viewpoint_origins(positions: np.ndarray, radius_m: float | None = None) -> np.ndarray:
    """[K, 3] metres: each keyframe's viewpoint for dedupe_frames, the position of its viewpoint group's first
    keyframe (viewpoint_groups): the keyframes of an ego that stands still tie, and the earliest keeps the surface
    whole, rather than a patchwork decided by centimetres of pose noise."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    return positions[viewpoint_groups(positions, radius_m)].copy()


def _pack(coords: np.ndarray) -> np.ndarray:
    """[N] int64 keys of integer voxel coordinates [N, 3] (21 bits an axis, offset: +-1e6 voxels)."""
    v = np.clip(coords + (1 << 20), 0, (1 << 21) - 1)
    return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]


def dedupe_frames_reference(points: np.ndarray, level: np.ndarray, frame: np.ndarray,
                            origins: np.ndarray | None = None) -> np.ndarray:
    """dedupe_frames cell by cell (slow, obviously correct; for the tests): each cell's rank is (its level, the
    distance from its own voxel's centre to its keyframe's origin, its keyframe); a cell is kept when no cell of
    another keyframe at its level or finer, in its voxel, ranks lower."""
    n = len(points)
    keep = np.ones(n, bool)
    pts = np.asarray(points, np.float64)

    def rank(j: int) -> tuple[int, float, int]:
        size = VOXEL_BASE_M * 2.0 ** int(level[j])
        centre = (np.floor(pts[j] / size) + 0.5) * size
        d = 0.0 if origins is None else float(np.linalg.norm(centre - np.asarray(origins[int(frame[j])], np.float64)))
        return int(level[j]), d, int(frame[j])

    for i in range(n):
        size = VOXEL_BASE_M * 2.0 ** int(level[i])
        vi = np.floor(pts[i] / size)
        owner = rank(i)
        for j in range(n):
            if level[j] <= level[i] and np.array_equal(np.floor(pts[j] / size), vi):
                owner = min(owner, rank(j))
        keep[i] = owner[2] == frame[i]
    return keep


def _footprint(g: Gaussians | np.ndarray) -> np.ndarray:
    """[N] metres: a Gaussian's footprint for dedupe_frames, twice its largest standard deviation: a model Gaussian's;
    a detail cell's from its disc (the disc's standard deviation is DetailOptions.footprint = 0.5 cell footprints
    across: twice its larger in-plane deviation). The largest log-scale taken column by column (numpy's max over a
    3-wide axis is six times slower), then exp: the same value as the largest of the exps. ``g``: the Gaussians, or
    their log-scales [N, 3]."""
    ls = g.log_scales if isinstance(g, Gaussians) else g
    return 2.0 * np.exp(np.maximum(np.maximum(ls[:, 0], ls[:, 1]), ls[:, 2]).astype(np.float64))


@dataclass
class _Kept:
    """The cells (or model Gaussians) of the keyframes so far, in the scene's frame, each part with its ``shared``
    mask: what the fusion keeps in the scene's shared Gaussians (dedupe_frames over the shared cells so far: a cell
    another keyframe took over never comes back, so deduping the shared ones as each keyframe arrives keeps what
    deduping them all at once keeps; with ``owners``, a VoxelOwners, only the new keyframe's cells are looked at).
    The rest is each keyframe's own chunk (own_of): runtime.viewpoints. With
    ``spill`` (a folder), each part's Gaussians wait there (a folder of .npy files: no archive, whose CRC of every
    byte cost 1.3 s of 10 keyframes) and only their centres stay in memory (12 of a cell's 68 bytes): a drive's memory
    does not grow with every keyframe's every cell."""

    origins: np.ndarray             # [K, 3] metres: each keyframe's viewpoint (viewpoint_origins)
    spill: Path | None = None
    owners: VoxelOwners | None = None
    means: list[np.ndarray] = field(default_factory=list)          # [N_i, 3] per part
    store: list[Gaussians | Path] = field(default_factory=list)    # the part, or its folder in ``spill``
    rows: list[np.ndarray | None] = field(default_factory=list)    # a spilled part: its file's rows kept (None: all)
    split: list[np.ndarray | None] = field(default_factory=list)   # [N_i] int32: each cell's row of its part's split
    #                                                                cells (runtime.detail.split_rows), or None
    quarters: list[tuple | None] = field(default_factory=list)     # (means, colours) [S, 4, 3] of a part's split
    #                                                                cells in memory (None: none, or in its folder)
    level: list[np.ndarray] = field(default_factory=list)
    frame: list[np.ndarray] = field(default_factory=list)
    shared: list[np.ndarray] = field(default_factory=list)
    start: list[int] = field(default_factory=list)      # the id of each part's first cell as added (VoxelOwners)
    now: list[np.ndarray | None] = field(default_factory=list)      # a part's row as added -> its row now (-1: gone)
    layer: list[np.ndarray | None] = field(default_factory=list)    # [N_i] int32: each cell's row in its keyframe's
    #                                                                 camera layer file (a split cell's first
    #                                                                 quarter's), or None (drive._layer_rows)
    source: Callable[[int], Path] | None = None     # keyframe n -> its camera layer file: a part with layer rows is
    #                                                 not kept (nor spilled) but read there when drawn
    deduped: int = 0                                    # parts before this one have been through dedupe
    next_id: int = 0

    def _put(self, g: Gaussians, quarters: tuple | None) -> tuple[Gaussians | Path, tuple | None]:
        if self.spill is None:
            return g, quarters
        path = self.spill / f"part_{len(self.store):05d}"
        path.mkdir()
        more = {} if quarters is None else {"split_means": quarters[0], "split_colours": quarters[1]}
        for name, a in {**{k: getattr(g, k) for k in FIELDS}, **more}.items():
            np.save(path / f"{name}.npy", a, allow_pickle=False)
        return path, None

    def part(self, i: int, m: np.ndarray | None = None) -> Gaussians:
        """Part i's Gaussians (where ``m``, [N_i] bool over the rows it keeps, holds): a spilled part's rows taken
        from its files in one pass (mapped, not read whole and then taken again)."""
        s = self.store[i]
        some = m is not None and not m.all()
        if isinstance(s, Gaussians):
            return s.subset(m) if some else s
        rows = None if self.rows[i] is None else np.flatnonzero(self.rows[i])
        if some:
            rows = np.flatnonzero(m) if rows is None else rows[m]
        # the rows of checked Gaussians as written: not checked again
        if rows is None:
            return Gaussians.joined(**{k: np.load(s / f"{k}.npy", allow_pickle=False) for k in FIELDS})
        return Gaussians.joined(**{k: np.load(s / f"{k}.npy", mmap_mode="r", allow_pickle=False)[rows]
                                   for k in FIELDS})

    def add(self, g: Gaussians, level: np.ndarray, n: int, split: tuple | None = None,
            layer: np.ndarray | None = None) -> None:
        """Keyframe n's part ``g`` (cells or model Gaussians) with its voxel levels; ``split``: (each cell's row of
        the part's split cells or -1 [N], their quarters' means and colours [S, 4, 3]) or None. Split cells are
        deduped as cells and drawn as their quarters (runtime.detail.expand_rows: shared_parts, own_of). ``layer``:
        each cell's row in its keyframe's camera layer file ([N] int32, _layer_rows), or None."""
        if layer is not None and self.source is not None:
            # its rows of the keyframe's camera layer file hold it (_from_layers)
            self.add_cells(np.array(g.means, np.float32), level, n, split, layer)
            return
        self._add(np.array(g.means, np.float32), level, n, split, layer, *self._put(g, None if split is None
                                                                                   else split[1:]))

    def add_cells(self, means: np.ndarray, level: np.ndarray, n: int, split: tuple | None, layer: np.ndarray) -> None:
        """add of a part whose Gaussians are rows of keyframe n's camera layer file (``layer``: each one's row there,
        with ``source`` set): only their centres ``means`` [N, 3] float32 (scene frame, metres; kept as given) and
        voxel levels are kept."""
        self._add(np.asarray(means, np.float32), level, n, split, layer, None, None)

    def _add(self, means: np.ndarray, level: np.ndarray, n: int, split: tuple | None, layer: np.ndarray | None,
             stored: Gaussians | Path | None, quarters: tuple | None) -> None:
        self.start.append(self.next_id)
        self.next_id += len(means)
        self.now.append(None)
        self.store.append(stored)
        self.quarters.append(quarters)
        self.split.append(None if split is None else np.asarray(split[0], np.int32))
        self.rows.append(None)
        self.layer.append(None if layer is None else np.asarray(layer, np.int32))     # (a file's rows < 2^31)
        self.means.append(means)
        self.level.append(level)
        self.frame.append(_same(n, len(means)))
        self.shared.append(np.ones(len(means), bool))

    def keep(self, i: int, m: np.ndarray) -> None:
        """Part i keeps only the cells ``m`` selects (shared or not)."""
        if not m.all():
            if isinstance(self.store[i], Gaussians):
                self.store[i] = self.store[i].subset(m)
            else:       # a spilled part is not written again: the rows of its file it keeps
                r = self.rows[i]
                if r is None:
                    self.rows[i] = m.copy()
                else:
                    r[np.flatnonzero(r)[~m]] = False
            self.means[i], self.level[i] = self.means[i][m], self.level[i][m]
            f = self.frame[i]
            self.frame[i], self.shared[i] = _same(f[0] if len(f) else 0, int(m.sum())), self.shared[i][m]
            if self.split[i] is not None:
                self.split[i] = self.split[i][m]
            if self.layer[i] is not None:
                self.layer[i] = self.layer[i][m]
            row = np.where(m, np.cumsum(m) - 1, -1)
            old = self.now[i]
            self.now[i] = row if old is None else np.where(old >= 0, row[np.maximum(old, 0)], -1)

    def dedupe(self) -> None:
        if not self.store:
            return
        if self.owners is None:
            sel = [np.flatnonzero(s) for s in self.shared]
            pts = np.concatenate([p[j] for p, j in zip(self.means, sel)])
            keep = dedupe_frames(pts, np.concatenate([v[j] for v, j in zip(self.level, sel)]),
                                 np.concatenate([f[j] for f, j in zip(self.frame, sel)]), self.origins)
            start = 0
            for i, j in enumerate(sel):
                self.shared[i][j] = keep[start:start + len(j)]
                start += len(j)
            return
        # the parts added since: each keyframe's together (its cells never drop each other)
        new = list(range(self.deduped, len(self.store)))
        self.deduped = len(self.store)
        for n in sorted({int(self.frame[i][0]) for i in new if len(self.frame[i])}):
            mine = [i for i in new if len(self.frame[i]) and int(self.frame[i][0]) == n]
            ids = np.concatenate([self.start[i] + np.arange(len(self.means[i])) for i in mine])
            keep, lost = self.owners.add(np.concatenate([self.means[i] for i in mine]),
                                         np.concatenate([self.level[i] for i in mine]), n, ids)
            at = 0
            for i in mine:
                self.shared[i] = keep[at:at + len(self.means[i])].copy()
                at += len(self.means[i])
            self._lose(lost)

    def _lose(self, ids: np.ndarray) -> None:
        """The cells ``ids`` (VoxelOwners' names: start + row as added) are no longer shared."""
        if not len(ids):
            return
        starts = np.asarray(self.start, np.int64)
        part = np.searchsorted(starts, ids, "right") - 1
        for i in np.unique(part):
            rows = ids[part == i] - starts[i]
            if self.now[i] is not None:
                rows = self.now[i][rows]
                rows = rows[rows >= 0]
            self.shared[i][rows] = False

    def count(self) -> int:
        return sum(int(s.sum()) for s in self.shared)

    def deduped_all(self) -> None:
        """The last keyframe is deduped: the voxel owners and the parts' voxel levels go (what is shared and what
        is each keyframe's own stays)."""
        self.owners = None
        self.level = [np.zeros(0, np.int8)] * len(self.level)

    def release(self) -> None:
        """Forget every part (its spilled file removed) and the voxel owners: the parts have been drawn."""
        for s in self.store:
            if isinstance(s, Path):
                shutil.rmtree(s, ignore_errors=True)
        for name in ("means", "store", "rows", "split", "quarters", "level", "frame", "shared", "start", "now",
                     "layer"):
            getattr(self, name).clear()
        self.owners = None

    def drawn(self, i: int, m: np.ndarray) -> Gaussians:
        """Part i's Gaussians where ``m`` ([N_i] bool) holds, its split cells as their quarters (expand_rows)."""
        if self.store[i] is None:
            return self._from_layers([(i, m)])[0]
        g = self.part(i, m)
        if self.split[i] is None:
            return g
        from .detail import expand_rows

        quarters = self.quarters[i]
        if quarters is None:                            # in the part's folder
            quarters = tuple(np.load(self.store[i] / f"split_{k}.npy", allow_pickle=False)
                             for k in ("means", "colours"))
        return expand_rows(g, self.split[i][m], *quarters)

    def _from_layers(self, items: list[tuple[int, np.ndarray]],
                     found: Callable[[int, np.ndarray], None] | None = None) -> list[Gaussians]:
        """drawn(i, m) of each (i, m) of ``items``, parts whose Gaussians are rows of their keyframe's camera layer
        file (``source``): each keyframe's file read once for all its parts (Gaussians.read_ply_take), in keyframe
        order; ``found``: called with each keyframe and the box of the means of its own rows there (own_layer_rows'
        rows, [2, 3] float64: min; max; its chunk's box, runtime.viewpoints.LayerRows) as soon as the same reads
        find it."""
        out: list[Gaussians | None] = [None] * len(items)
        by_key: dict[int, list[int]] = {}
        for j, (i, _) in enumerate(items):
            by_key.setdefault(int(self.frame[i][0]) if len(self.frame[i]) else -1, []).append(j)
        if found is not None:
            for f, layer in zip(self.frame, self.layer):
                if len(f) and layer is not None:
                    by_key.setdefault(int(f[0]), [])

        def read(n: int, js: list[int]) -> tuple[list[np.ndarray], Gaussians]:
            rows = [self._layer_take(*items[j], centres=False)[0] for j in js]
            own, box = None, None
            if found is not None and n >= 0:
                own = [self._layer_take(i, ~self.shared[i], centres=False)[0] for i in self._own(n)
                       if self.layer[i] is not None]
                own = np.concatenate(own) if own else None
                box = np.array([[np.inf] * 3, [-np.inf] * 3])
            if n < 0 or not (sum(map(len, rows)) or own is not None and len(own)):
                g = Gaussians.empty()
            else:
                g = Gaussians.read_ply_take(self.source(n), np.concatenate(rows) if rows else np.zeros(0, np.int32),
                                            box_of=own, box=box)
            if box is not None:
                found(n, box)
            return rows, g

        # LAYER_READS files at a time: one's rows found and taken while the disk reads another's
        keyed = sorted(by_key.items())
        for (n, js), (rows, g) in zip(keyed, _in_order(lambda k: read(*keyed[k]), len(keyed), LAYER_READS)):
            at = 0
            for j, r in zip(js, rows):
                out[j] = g.slice(at, at + len(r)) if len(r) else Gaussians.empty()
                at += len(r)
        return out

    def shared_parts(self, found: Callable[[int, np.ndarray], None] | None = None
                     ) -> tuple[list[Gaussians], list[np.ndarray]]:
        """(each part's shared Gaussians, their keyframes); ``found``: told the box of each keyframe's own rows of
        its camera layer file as they are read (_from_layers)."""
        read = [i for i, s in enumerate(self.store) if s is None]
        got = dict(zip(read, self._from_layers([(i, self.shared[i]) for i in read], found)))
        out = [got[i] if i in got else self.drawn(i, s) for i, s in enumerate(self.shared)]
        return out, [np.full(len(g), f[0] if len(f) else 0, f.dtype) for g, f in zip(out, self.frame)]

    def _own(self, n: int) -> list[int]:
        """Keyframe ``n``'s parts that hold cells the shared Gaussians keep from another keyframe."""
        return [i for i, (f, s) in enumerate(zip(self.frame, self.shared)) if len(f) and int(f[0]) == n
                and not s.all()]

    def own_of(self, n: int) -> list[Gaussians]:
        """Keyframe ``n``'s cells that the shared Gaussians keep from another keyframe (its parts' unshared)."""
        return [self.drawn(i, ~self.shared[i]) for i in self._own(n)]

    def own_layer_rows(self, n: int) -> np.ndarray | None:
        """own_of(n)'s Gaussians as rows of keyframe ``n``'s camera layer file ([M] int32) in spatial order
        (runtime.viewpoints.spatial_order of their cells' centres, a split cell's four quarters at its centre: a
        view's projection skips runs of neighbours whole), without a copy of the centres: the box of the parts' kept
        cells, then each row's Morton code beside it, sorted (own_layer_rows_reference, tested equal); None when
        one of its parts has no rows there."""
        from .render import kernels as K
        from .viewpoints import SPATIAL_BITS, box_steps, grow_box

        own = self._own(n)
        if any(self.layer[i] is None for i in own):
            return None
        masks = [~self.shared[i] for i in own]
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        total = 0
        for i, m in zip(own, masks):
            grow_box(self.means[i], m, lo, hi)
            total += int(m.sum()) + (0 if self.split[i] is None else 3 * int((self.split[i][m] >= 0).sum()))
        rows, codes = np.empty(total, np.int32), np.empty(total, np.uint32)
        step, at = box_steps(lo, hi, SPATIAL_BITS), 0
        for i, m in zip(own, masks):
            split = self.split[i]
            at = _rows_and_codes(self.layer[i], self.means[i], m, _NO_SPLIT if split is None else split,
                                 split is not None, lo, step, SPATIAL_BITS, rows, codes, at)
        return K.depth_order(rows, codes) if total else rows

    def own_layer_rows_reference(self, n: int) -> np.ndarray | None:
        """own_layer_rows with the centres made (_layer_take) and put in spatial_order (its test)."""
        from .viewpoints import spatial_order

        rows, centres = [], []
        for i in self._own(n):
            if self.layer[i] is None:
                return None
            r, c = self._layer_take(i, ~self.shared[i])
            rows.append(r)
            centres.append(c)
        if not rows:
            return np.zeros(0, np.int32)
        rows, centres = np.concatenate(rows), np.concatenate(centres)
        return rows[spatial_order(centres)]

    def _layer_take(self, i: int, m: np.ndarray, centres: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Part i's cells where ``m`` ([N_i] bool) holds as rows of its keyframe's camera layer file, in drawn's
        order (the cells that do not split, then the quarters, cell by cell), and (``centres``) their cells'
        centres."""
        r = self.layer[i][m]
        c = self.means[i][m] if centres else None
        if self.split[i] is not None:
            q = self.split[i][m] >= 0
            if q.any():
                r = np.concatenate([r[~q], (r[q][:, None] + np.arange(4, dtype=r.dtype)).ravel()])
                if centres:
                    c = np.concatenate([c[~q], np.repeat(c[q], 4, axis=0)])
        return r, c


def _same(n: int, count: int) -> np.ndarray:
    """[count] int32 all ``n`` (a part's keyframe, each of its cells'): one value seen ``count`` times (read-only, no
    memory: 53 M cells of a 20-keyframe drive held 213 MB of copies)."""
    return np.broadcast_to(np.int32(n), (count,))


_NO_SPLIT = np.zeros(0, np.int32)


@njit(cache=True, nogil=True)
def _rows_and_codes(layer, means, mask, split, has_split, lo, step, bits, rows, codes, at):
    """_Kept._layer_take's rows of one part where ``mask`` holds (the cells that do not split, then each split
    cell's four quarters: rows layer[i] + 0..3) written to rows[at:], and beside each its cell's Morton code
    (runtime.viewpoints.morton_code in the box from ``lo``, box_steps ``step``) to codes[at:]; returns the next at."""
    for i in range(mask.shape[0]):
        if mask[i] and not (has_split and split[i] >= 0):
            rows[at] = layer[i]
            codes[at] = morton_code(means, i, lo, step, bits)
            at += 1
    if has_split:
        for i in range(mask.shape[0]):
            if mask[i] and split[i] >= 0:
                c = morton_code(means, i, lo, step, bits)
                for k in range(4):
                    rows[at] = layer[i] + k
                    codes[at] = c
                    at += 1
    return at


_DEFAULT = object()


def reconstruct_drive(rec, drive: Drive, keyframes: Sequence[int] | None = None, lidar: bool = True,
                      detail: Any = _DEFAULT, progress: Callable[[str], None] | None = None, stereo: bool = True,
                      ego_body: bool = True, exposure: bool = True, workers: int | None = None,
                      stationary_actors: bool = False, make_keyframes: Callable[..., Any] | None = None):
    """One runtime.scene.Scene of ``drive`` (module docstring) with runtime.inference.Reconstructor ``rec``:
    ``keyframes`` (default pick_keyframes), each keyframe's LiDAR sweep when ``lidar`` and it has one, else when
    ``stereo`` (the default) the points triangulated between it and the frames about a metre before and after it
    (runtime.stereo; docs/inference.md), the detail layer's settings ``detail`` (default runtime.inference.DEFAULT_DETAIL; None: the model's Gaussians only), the
    ego's own body found over the drive's frames when ``ego_body`` (runtime.egobody: no cells there; a camera's
    ego_mask file wins), each camera's exposure and white balance harmonised across cameras and keyframes when
    ``exposure`` (runtime.exposure). ``workers``: keyframes reconstructed ahead in that many worker processes while
    this one fuses (each loads the model once; at most ``workers`` keyframes wait, so memory stays bounded; 0: all
    here; default DEFAULT_WORKERS). ``stationary_actors``: the tracks marked ``stationary`` (parked cars) become
    actors too (a view can then hide or move them), instead of staying in the static scene. A one-frame drive is
    exactly Reconstructor.reconstruct of its rig (one_rig). ``make_keyframes(drive, keys, opts)``: where the
    keyframes are made instead of ``workers`` (`xyzcyl batch`: on Ray actors): an iterator of make_keyframe(rec,
    drive, k, **opts) for each of ``keys`` in order; ``rec`` is then only asked for ``scene_model()``, and a
    one-frame drive is refused (make it with Reconstructor.reconstruct)."""
    from .cameralayers import CameraLayers
    from .detail import carve_details, carve_details_both, cull_covered, detail_pyramids, split_rows
    from .exposure import Harmoniser
    from .inference import DEFAULT_DETAIL
    from .scene import Scene
    from .tiles import in_tile_order
    from .viewpoints import LayerRows, Viewpoints

    say = progress or (lambda msg: None)
    detail = DEFAULT_DETAIL if detail is _DEFAULT else detail
    if stationary_actors:           # every track is then an object that leaves the static scene
        drive = replace(drive, tracks=tuple(replace(t, stationary=False) for t in drive.tracks))
    tol = detail.cull_tolerance if detail is not None else 0.0
    keys = pick_keyframes(drive) if keyframes is None else list(keyframes)
    if not keys or any(not 0 <= k < len(drive) for k in keys) or keys != sorted(set(keys)):
        raise DriveError("keyframes", f"must be increasing frame indices in 0..{len(drive) - 1} (got {keys})")
    n_workers = DEFAULT_WORKERS if workers is None else int(workers)
    if n_workers < 0:
        raise DriveError("workers", f"must be >= 0, got {workers}")
    t0 = time.perf_counter()

    if one_rig(drive, keys):
        if make_keyframes is not None:
            raise DriveError("keyframes", "a one-frame drive is one rig's scene (Reconstructor.reconstruct)")
        fr = drive.frames[keys[0]]
        scene = rec.reconstruct(fr.rig, progress=say, lidar=_sweep(drive, keys[0], lidar), detail=detail,
                                exposure=exposure)
        scene.drive = drive_meta(drive, keys)
        return scene
    counts: dict[str, Any] = {"keyframes": len(keys), "frames": len(drive)}
    timings: dict[str, float] = {}
    harmoniser = Harmoniser(len(drive.frames[0].rig.cameras)) if exposure else None
    found = EgoBody()
    finding: Future | None = None       # the ego's body, found in a thread beside the first keyframe's making

    def find() -> EgoBody:
        t_e = time.perf_counter()
        out = find_drive_ego_body(drive, lidar)
        timings["ego_body"] = time.perf_counter() - t_e
        return out

    def ego_found(body: EgoBody) -> EgoBody:
        say("ego body: " + (", ".join(f"{k} {v:.0%}" for k, v in body.fractions.items() if v > 0) or
                            f"none found ({body.travelled_m:.1f} m travelled)"))
        counts["ego_body_cameras"] = len(body.masks)
        return body

    positions = np.array([drive.relative(k)[:3, 3] for k in keys])
    heads = viewpoint_groups(positions)
    origins = positions[heads]
    spill = tempfile.TemporaryDirectory(prefix="xyzcyl-drive-")      # removed when the scene lets go of it
    detail_kept = _Kept(origins, Path(spill.name), VoxelOwners(origins))
    coarse_kept = _Kept(origins)
    layers = CameraLayers.spill(drive.frames[0].rig.names, spill) if detail is not None else None
    if layers is not None:      # a keyframe's kept cells are rows of its layers' file: read there, not spilled again
        detail_kept.source = lambda n: Path(spill.name) / layers.keyframes[n].file
    # (keyframe, details, parts, keep, whether its depth was measured: a LiDAR sweep, its measured cells that a
    # neighbouring keyframe saw through: they moved away (_carve_pair), each part's cells' rows in its camera layer
    # file or None (_layer_rows))
    window: list[tuple[int, list, list[Gaussians], list[np.ndarray], bool, list[np.ndarray], list | None]] = []
    moved: list[tuple[int, Gaussians]] = []
    stacks: dict = {}           # the window's keyframes' cameras stacked for carving (_carve_pair)
    made_pyramids: dict = {}    # the window's keyframes' detail_pyramids (commit)
    background = None
    moved_out = 0
    copies: list[tuple[int, float, Gaussians]] = []

    def commit(entry) -> None:
        """A keyframe leaves the carving window: its kept cells join the scene (deduped across keyframes), and the
        model's Gaussians so far that would veil one of its cameras' surfaces go (as in one frame)."""
        n, details, parts, keep, _, gone, lrows = entry
        if any(m.any() for m in gone):       # drawn only around this keyframe's time (actors_of)
            # not the spill of a tracked object's cells beside its box: it is drawn from its copy
            moved.append((n, without_spill(_concat([g.subset(m) for g, m in zip(parts, gone) if m.any()]),
                                           spill_boxes(drive, keys[n]))))
        pyramids = made_pyramids.pop(n, None)      # made when its own model Gaussians were culled, else here
        if pyramids is None and details and len(coarse_kept.store):
            pyramids = detail_pyramids(details)     # once for all
        for i in range(len(coarse_kept.store)):
            g = coarse_kept.part(i)
            if details and len(g):
                coarse_kept.keep(i, cull_covered(g, details, tol, pyramids))
        # the kept cells' rows in the keyframe's camera layer file (a chunk is rows of it): each kept cell is one
        # its cameras kept (carve_details with the dedupe keeps fewer than without; the boxes and the neighbours
        # only take more away)
        at = None if lrows is None else [r[k] for r, k in zip(lrows, keep)]
        if at is not None and any((r < 0).any() for r in at):
            at = None                   # (never met: then the keyframe's chunk is written whole)
        for i, (g, d, k) in enumerate(zip(parts, details, keep)):
            split = None if d.split is None else (split_rows(len(k), d.split)[k], d.split.means, d.split.colours)
            if at is not None and detail_kept.source is not None:
                # its rows of the camera layer file hold the cells: only their centres and footprints are taken
                rows = np.flatnonzero(k)
                detail_kept.add_cells(g.means[rows], voxel_levels(_footprint(g.log_scales[rows])), n, split, at[i])
                continue
            g = g.subset(k)             # deduped as cells; a split cell drawn as its quarters (_Kept.drawn)
            detail_kept.add(g, voxel_levels(_footprint(g)), n, split, None if at is None else at[i])
        detail_kept.dedupe()
        release_heap(HEAP_KEPT_BYTES)

    ego_pool = ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-ego-body")
    if ego_body and make_keyframes is None and n_workers == 0 and threadsafe():
        # the first keyframe's decoding, network and LiDAR depth need no masks: only its detail layer waits for
        # them (_Later); the search for the body alone kept a core idle (20 PandaSet keyframes: it took 1.2-1.9 s)
        finding = ego_pool.submit(find)
    elif ego_body:
        found = ego_found(find())
    masks = found.masks if finding is None else _Later(finding, lambda body: body.masks)
    opts = dict(lidar=lidar, stereo=stereo, detail=detail, masks=masks)
    try:
        made = _keyframes_made(rec, drive, keys, n_workers, opts, say) if make_keyframes is None else \
            make_keyframes(drive, keys, opts)
    except BaseException:
        ego_pool.shutdown(wait=True)
        raise
    try:
        for n, k in enumerate(keys):
            fr = drive.frames[k]
            say(f"keyframe {n + 1}/{len(keys)}: frame {k} ({fr.timestamp_s - drive.frames[0].timestamp_s:.2f} s)")
            points, kf, coarse, parts, details, note = next(made)
            if finding is not None:
                found, finding = ego_found(finding.result()), None
            if note:
                say(note)
            for key, v in kf.timings.items():
                timings[key] = timings.get(key, 0.0) + v
            if background is None:
                background = kf.background
            if harmoniser is not None and parts:
                t_x = time.perf_counter()
                parts = harmoniser.add(details, parts, kf.owners)
                details = harmoniser.details(details, kf.owners)
                coarse = harmoniser.coarse(coarse)
                timings["exposure"] = timings.get("exposure", 0.0) + time.perf_counter() - t_x
            # this keyframe as one rig: its model Gaussians under its cells culled, its cells carved against its own
            # cameras; later against its neighbours' (see-through, by a keyframe with a LiDAR sweep: _carve_pair)
            if details and len(coarse):
                # its cameras' depth pyramids, kept for its commit (the same details: made once; ~85 MB a PandaSet
                # keyframe, CARVE_WINDOW + 1 of them)
                made_pyramids[n] = detail_pyramids(details)
                coarse = coarse.subset(cull_covered(coarse, details, tol, made_pyramids[n]))
            # without a sweep the cameras' depths are the model's (scaled per camera to a few stereo points), up to
            # 2x apart: one camera sees through another's cell only where it also sees another colour there
            photo = SEE_THROUGH_PHOTO if points is None else None
            # and each camera's camera layer: its cells that no other camera of the keyframe saw through (no dedupe),
            # from the same pass over the cells
            if details and layers is not None:
                own, seen = carve_details_both(details, tol, detail.dedupe, photo)
            else:
                own, seen = carve_details(details, tol, detail.dedupe, photo) if details else [], []
            boxes = moving_boxes(drive, k)
            if boxes:                       # what moves is not the static scene's: each object's copy, in its box
                geo = [(inv, half) for _, inv, half in boxes]
                if points is None:          # no sweep: the model's depth of what a box holds is put into the box
                    parts = [_snapped(g, d.grid.cam_to_ego[:3, 3], geo) for g, d in zip(parts, details)]
                c_mem = box_members(coarse.means, geo)
                p_mem = [box_members(g.means, geo) for g in parts]
                # each part's members by box: one sort of the few members, not a mask over all cells per box
                by_box = [_by_box(coarse, c_mem >= 0, c_mem, len(boxes))] + \
                    [_by_box(g, keep & (m >= 0), m, len(boxes)) for g, keep, m in zip(parts, own, p_mem)]
                for b, (t, inv, _) in enumerate(boxes):
                    pieces = [pieces_of[b] for pieces_of in by_box]
                    copies.append((t, fr.timestamp_s, transform_gaussians(_concat(pieces), inv)))
                moved_out += int((c_mem >= 0).sum())
                coarse = coarse.subset(c_mem < 0)
                for i, m in enumerate(p_mem):
                    moved_out += int((own[i] & (m >= 0)).sum())
                    own[i] &= m < 0
                    if seen:
                        seen[i] &= m < 0
            lrows = None
            if layers is not None:      # every keyframe has its layers (none: no cells), so chunks can point there
                t_l = time.perf_counter()
                layers.add(_layer_parts(parts, details, seen, kf.owners, len(layers.cameras)))
                runs = layers.keyframes[-1].runs
                lrows = [_layer_rows(m, d, runs[c][0]) for m, d, c in zip(seen, details, kf.owners)]
                timings["camera_layers"] = timings.get("camera_layers", 0.0) + time.perf_counter() - t_l
            coarse_kept.add(coarse, voxel_levels(_footprint(coarse)), n)
            entry = (n, details, parts, own, points is not None, [np.zeros(len(k), bool) for k in own], lrows)
            for prev in window:
                _carve_pair(entry, prev, tol, stacks)
                _carve_pair(prev, entry, tol, stacks)
            window.append(entry)
            while len(window) > CARVE_WINDOW:
                stacks.pop(window[0][0], None)
                commit(window.pop(0))
            say(f"fused: {detail_kept.count()} detail cells so far")
    finally:
        made.close()              # a failed keyframe: the workers stop
        ego_pool.shutdown(wait=True)
    t1 = time.perf_counter()
    release_heap(HEAP_KEPT_BYTES)   # the fusion below allocates other sizes: what the keyframes freed, above that
    if layers is not None:
        t_l = time.perf_counter()
        layers.finish()                         # the last keyframe's written: the scene's cells are read there
        timings["camera_layers"] = timings.get("camera_layers", 0.0) + time.perf_counter() - t_l
    stacks.clear()
    while window:
        commit(window.pop(0))
    coarse_kept.dedupe()
    coarse_parts, coarse_frames = coarse_kept.shared_parts()
    # each chunk's box (of its rows of its keyframe's camera layer file), found as the shared cells are read there
    own_boxes: list[Future] = [Future() for _ in keys]
    shared_read: Future = Future()          # the shared cells read: the parts may go (write_chunks)

    # each keyframe's chunk (with its viewpoint group) written beside the spilled parts, one at a time, and read
    # back when a view needs it: its model Gaussians, and its cells as rows of its camera layer file, in an order
    # that keeps neighbours together (spatial_order: a view's projection skips runs of them whole)
    def chunk(n: int) -> Gaussians | tuple[Gaussians, LayerRows]:
        release_heap(HEAP_KEPT_BYTES)           # the chunk before was written and let go of
        rows = detail_kept.own_layer_rows(n) if layers is not None else None
        if rows is None:
            return _concat(coarse_kept.own_of(n) + detail_kept.own_of(n))
        return _concat(coarse_kept.own_of(n)), LayerRows(layers.keyframes[n].file, rows, own_boxes[n].result())

    def write_chunks() -> Viewpoints | None:
        out = Viewpoints.spilled([[n] for n in range(len(keys))], _in_order(chunk, len(keys), CHUNKS_AHEAD), spill,
                                 [int(h) for h in heads]) if len(keys) > 1 else None
        shared_read.result()
        for kept in (detail_kept, coarse_kept):     # every cell is in the scene or a chunk now: their files and
            kept.release()                          # maps go
        release_heap(HEAP_KEPT_BYTES)
        return out

    # the chunks are written in a thread, and the moving objects and the lattice under them made in another, while
    # this one reads the shared cells from the camera layer files (the disk's time: runtime.directio), puts them in
    # tiles and fills the ground under the objects: the keyframes are all made, the two cores are this work's (each
    # side is mostly numpy and numba, which release the GIL); one after the other where numba's threading layer
    # cannot run two threads' kernels at once (numba_cache.threadsafe)
    def objects():
        """The moving objects (actors_of) and the lattice under their footprints (fill_lattice; its seconds): they
        need none of the shared cells, so they are made while those are read."""
        actors = actors_of(drive, copies, moved, keys)
        if actors is None:
            return None, None, 0.0
        t_f = time.perf_counter()
        tracked = actors.pose_track < len(moving_tracks(drive))
        lattice = fill_lattice([(int(a), T, actors.track_size[a]) for a, T in
                                zip(actors.pose_track[tracked], actors.pose[tracked])], len(actors))
        return actors, lattice, time.perf_counter() - t_f

    with ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-chunks") as pool, \
            ThreadPoolExecutor(1, thread_name_prefix="xyzcyl-actors") as beside:
        written = pool.submit(write_chunks) if threadsafe() else None
        made_objects = beside.submit(objects) if threadsafe() else None
        try:
            detail_parts, detail_frames = detail_kept.shared_parts(lambda n, box: own_boxes[n].set_result(box))
        finally:                    # a chunk whose box was not found (none, or the reads failed) reads it itself
            for f in own_boxes:
                if not f.done():
                    f.set_result(None)
            shared_read.set_result(None)
        for kept in (detail_kept, coarse_kept):
            kept.deduped_all()
        n_coarse, n_detail = sum(map(len, coarse_parts)), sum(map(len, detail_parts))
        # one run per keyframe (its model Gaussians, then its cells); in_tile_order puts them in tiles, each tile's
        # keyframes one run each, which a view draws without a copy
        pieces = sorted(zip(coarse_parts + detail_parts, coarse_frames + detail_frames),
                        key=lambda p: int(p[1][0]) if len(p[1]) else -1)
        del coarse_parts, detail_parts
        keyframe_of = np.concatenate([f for _, f in pieces]).astype(np.int16)
        viewpoints = write_chunks() if written is None else None
        tiles = None
        if len(keys) > 1 and len(keyframe_of):
            # put in tiles as they are joined (one copy; Scene would take them again): runtime.tiles.in_tile_order
            gauss, keyframe_of, tiles = in_tile_order([p for p, _ in pieces if len(p)], keyframe_of, len(keys))
        else:
            gauss = _concat([p for p, _ in pieces])
        del pieces
        actors, lattice, lattice_s = objects() if made_objects is None else made_objects.result()
        fill_s, fill_counts = None, {}
        if actors is not None:
            # the ground under the tracked objects that no keyframe saw: filled, drawn where a view hides or moves one
            t_f = time.perf_counter()
            fill, fill_track, filled = fill_lattice_under(gauss, lattice)
            if len(fill):
                actors = replace(actors, fill=fill, fill_track=fill_track)
            fill_counts = {"ground_filled": len(fill), "ground_filled_m2": round(float(filled.sum()), 2)}
            fill_s = time.perf_counter() - t_f
        scene = Scene(gaussians=gauss, background=background, rig=drive.frames[0].rig, model=rec.scene_model(),
                      actors=actors, keyframe_of=keyframe_of if len(keyframe_of) == len(gauss) else None,
                      camera_layers=layers, ego_body=found if ego_body else None, tiles=tiles,
                      drive=drive_meta(drive, keys))
        if written is not None:
            viewpoints = written.result()
    scene.viewpoints = viewpoints
    timings["fusion"] = time.perf_counter() - t1 - (fill_s or 0.0)
    if fill_s is not None:              # its lattice was laid beside the fusion (objects)
        timings["ground_fill"] = fill_s + lattice_s
    timings["total"] = time.perf_counter() - t0
    counts.update({"coarse": n_coarse, "detail": n_detail, "moving_removed": moved_out,
                   "moved_away": int(sum(len(g) for _, g in moved)), "total": len(gauss)})
    if viewpoints is not None:
        counts.update({"viewpoints": len(viewpoints), "viewpoint_gaussians": viewpoints.count})
    if layers is not None:
        counts["camera_layer_gaussians"] = layers.count
    if actors is not None:
        counts.update({"actors": len(actors), "actor_copies": len(actors.copy_track),
                       "actor_gaussians": len(actors.gaussians), **fill_counts})
    scene.counts, scene.timings = counts, {key: round(v, 6) for key, v in timings.items()}
    if harmoniser is not None:
        scene.drive["exposure"] = harmoniser.to_json(drive.frames[0].rig.names)
    return scene


def _layer_parts(parts: list[Gaussians], details: list, keep: list[np.ndarray], owners: list[int],
                 n_cameras: int) -> list[list[Gaussians]]:
    """A keyframe's camera layers (runtime.cameralayers) in the rig's camera order: each camera's detail Gaussians
    ``parts`` where ``keep`` holds, its split cells as their quarters (expand_split_parts); ``owners``: each part's
    camera (an index into the rig); a camera without a detail layer has none."""
    from .detail import expand_split_parts

    out: list[list[Gaussians]] = [[] for _ in range(n_cameras)]
    for g, d, m, c in zip(parts, details, keep, owners):
        out[c] = expand_split_parts(g, d, m)
    return out


def _layer_rows(seen: np.ndarray, d, start: int) -> np.ndarray:
    """[N] int64: each of a camera's N cells' row in its keyframe's camera layer file (the rows _layer_parts wrote,
    the camera's run from ``start``), -1 where ``seen`` ([N] bool) left it out; a split cell's first quarter's
    (its four follow): the cells that do not split first, in order, then the quarters, cell by cell
    (expand_split_parts)."""
    from .detail import split_rows

    seen = np.asarray(seen, bool)
    split = split_rows(len(seen), d.split) >= 0 if d.split is not None and len(d.split.index) else \
        np.zeros(len(seen), bool)
    whole, quartered = seen & ~split, seen & split
    out = np.full(len(seen), -1, np.int64)
    n_whole = int(whole.sum())
    out[whole] = start + np.arange(n_whole)
    out[quartered] = start + n_whole + 4 * np.arange(int(quartered.sum()))
    return out


def one_rig(drive: Drive, keys: Sequence[int]) -> bool:
    """Whether the keyframes ``keys`` of ``drive`` make one rig's scene (Reconstructor.reconstruct of frame 0):
    the scene's frame is frame 0's, and without tracks nothing moves."""
    return list(keys) == [0] and not drive.tracks


def _sweep(drive: Drive, k: int, lidar: bool) -> np.ndarray | None:
    """Frame k's LiDAR sweep [P, 3] metres (its ego frame) when ``lidar`` and it has one, else None."""
    from .lidar import has_lidar, load_lidar

    rig = drive.frames[k].rig
    return load_lidar(rig).points if lidar and has_lidar(rig) else None


def _stereo_sweep(drive: Drive, k: int, masks: dict[str, np.ndarray]):
    """(points triangulated between keyframe k and its partner frames (runtime.stereo) or None, keyframe k's images
    when they were read for it, else None: Reconstructor.keyframe reads them; a note for the progress)."""
    from .detail import read_ego_mask
    from .inference import rgb_images
    from .stereo import partner_frames, stereo_points

    positions_all = np.array([drive.relative(j)[:3, 3] for j in range(len(drive))])
    parts = partner_frames(positions_all, k)
    tracked = bool(drive.tracks)    # the tracks name what moves: a feature seen with one partner is enough
    if len(parts) < (1 if tracked else 2):      # else stereo_points needs a partner on each side
        return None, None, ""

    def loaded(j):
        r = drive.frames[j].rig
        return r.cameras, rgb_images(r), drive.relative(j)

    rig = drive.frames[k].rig
    cams, imgs, T = loaded(k)
    ego = [read_ego_mask(rig.path(c.extra["ego_mask"]), c) if c.extra.get("ego_mask") else masks.get(c.name)
           for c in cams]
    boxes = [(inv, half) for _, inv, half in moving_boxes(drive, k)]
    pts = stereo_points(cams, imgs, T, [loaded(j) for j in parts], ego, boxes, tracked=tracked)
    return (pts if len(pts) else None), imgs, f"stereo: {len(pts)} points from frames {parts}"


class _Later(Mapping):
    """A mapping that a thread is still making: ``of(future.result())``, waited for when first read (the first
    keyframe's ego masks while the ego's body is still being found: reconstruct_drive)."""

    def __init__(self, future: Future, of: Callable[[Any], Mapping]):
        self._future, self._of = future, of

    def _now(self) -> Mapping:
        return self._of(self._future.result())

    def __getitem__(self, key):
        return self._now()[key]

    def __iter__(self):
        return iter(self._now())

    def __len__(self) -> int:
        return len(self._now())


def make_keyframe(rec, drive: Drive, k: int, lidar: bool, stereo: bool, detail, masks: dict[str, np.ndarray],
                   progress: Callable[[str], None] | None = None, detail_threads: int = 1):
    """Keyframe k up to its fusion (a worker's job): (its LiDAR sweep or None, the runtime.inference.Keyframe,
    its model Gaussians, detail Gaussians and cell maps moved into the scene's frame, a note for the progress).
    detail_threads: cameras whose detail is made at once (Reconstructor.keyframe)."""
    points, images, note = _sweep(drive, k, lidar), None, ""
    guide, t_s = points, time.perf_counter()
    if points is None and stereo:
        guide, images, note = _stereo_sweep(drive, k, masks)
    t_s = time.perf_counter() - t_s
    kf = rec.keyframe(drive.frames[k].rig, images, progress=progress, lidar=guide, detail=detail, ego_masks=masks,
                      lidar_is_sweep=points is not None, detail_threads=detail_threads)
    if stereo and points is None:
        kf.timings["stereo"] = t_s
    kf.app_plane = None                 # baked into kf.background already; not sent back from a worker
    T = drive.relative(k)
    return (points, kf, transform_gaussians(kf.coarse, T), [transform_gaussians(g, T) for g in kf.parts],
            [transform_detail(d, T) for d in kf.details], note)


_WORKER: dict[str, Any] = {}


def _worker_start(model_dir: str, threads: int | None, drive: Drive, opts: dict) -> None:
    """A keyframe worker process's start: its own model sessions, the drive and the keyframes' settings."""
    from .inference import Reconstructor

    _WORKER.update(rec=Reconstructor.load(model_dir, threads=threads), drive=drive, opts=opts)


def _worker_keyframe(k: int):
    return make_keyframe(_WORKER["rec"], _WORKER["drive"], k, **_WORKER["opts"])


def _keyframes_made(rec, drive: Drive, keys: Sequence[int], workers: int, opts: dict,
                    say: Callable[[str], None] | None = None):
    """make_keyframe of each of ``keys`` in order: here (``workers`` 0: in a thread of this process, one keyframe
    ahead of the one the caller fuses), else in that many worker processes (spawned: no onnxruntime or numba threads
    are forked) with at most ``workers`` keyframes ahead. An error making a keyframe is raised here, the others
    cancelled. ``say``: the stages' progress lines, each led by its frame (here only)."""
    def make(k: int, led: bool = True, threads: int = 1):
        """Keyframe k made here, its progress lines led by its frame (``led``), ``threads`` cameras at once."""
        return make_keyframe(rec, drive, k, **opts,
                             progress=(lambda m: say(f"frame {k}: {m}")) if say and led else say,
                             detail_threads=threads)

    alone = len(keys) < 2
    if alone or (workers == 0 and not threadsafe()):
        # numba's workqueue layer (no libgomp, no TBB): two threads' kernels at once would abort the process, so
        # each keyframe is made when the caller asks for it (numba_cache.threadsafe)
        if say and not alone:
            say("keyframes made one at a time: numba has no thread-safe threading layer here (install libgomp1 "
                "or `pip install tbb`)")
        for k in keys:
            yield make(k, led=not alone)
        return
    if workers == 0:
        # the next keyframe is made while the caller fuses this one: onnxruntime, the numba kernels and numpy's big
        # operations release the GIL, and a keyframe's making and its fusion each leave a core idle part of the
        # time (one keyframe's cells more in memory; the service renders from threads the same way)
        from .inference import DETAIL_THREADS

        ahead = ThreadPoolExecutor(1, thread_name_prefix="keyframe")
        try:
            # each keyframe's cameras two at a time, as one rig's, also beside a fusion: with the voxel owners in
            # hash tables the fusion waited for the next keyframe 0.2-0.5 s of each (20 PandaSet keyframes: 46-49
            # s with two, 49-54 s with one; docs/results.md "Speed, session of 2026-12-03 (afternoon)")
            nxt = ahead.submit(make, keys[0], True, DETAIL_THREADS)
            for i in range(len(keys)):
                got = nxt.result()
                if i + 1 < len(keys):
                    nxt = ahead.submit(make, keys[i + 1], True, DETAIL_THREADS)
                yield got
        finally:
            ahead.shutdown(wait=True, cancel_futures=True)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    cores = os.cpu_count() or 1
    threads = max(1, (rec.threads or cores) // (workers + 1))       # the cores shared with this process's fusion
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_start,
                               initargs=(str(rec.info.path), threads, drive, opts))
    try:
        ahead = [pool.submit(_worker_keyframe, k) for k in keys[:workers]]
        for i in range(len(keys)):
            got = ahead.pop(0).result()
            if i + workers < len(keys):
                ahead.append(pool.submit(_worker_keyframe, keys[i + workers]))
            yield got
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def find_drive_ego_body(drive: Drive, lidar: bool = True) -> EgoBody:
    """The ego's own body over ``drive``'s frames (runtime.egobody.find_ego_body) for the cameras whose rig gives
    no ego_mask; the ground from the LiDAR sweep of the first frame that has one (when ``lidar``), else the ego
    frame's z = 0."""
    from .detail import fit_ground
    from .egobody import find_ego_body
    from .inference import rgb_images
    from .lidar import has_lidar, load_lidar

    rig0 = drive.frames[0].rig
    poses = [drive.relative(k) for k in range(len(drive))]
    ground_z = 0.0
    with_lidar = [k for k in range(len(drive)) if lidar and has_lidar(drive.frames[k].rig)]
    if with_lidar:
        plane = fit_ground(load_lidar(drive.frames[with_lidar[0]].rig).points)
        if plane is not None and abs(plane[2]) > 1e-6:
            ground_z = float(-plane[3] / plane[2])          # n . x + d = 0 at x = y = 0
    lidar_of = None
    if with_lidar and len(with_lidar) == len(drive):
        lidar_of = lambda k: load_lidar(drive.frames[k].rig).points    # noqa: E731
    return find_ego_body(rig0.cameras, lambda k: rgb_images(drive.frames[k].rig),
                         np.array([T[:3, 3] for T in poses]), poses, ground_z,
                         skip=[c.name for c in rig0.cameras if c.extra.get("ego_mask")], lidar_of=lidar_of)


def save_drive_scene(rec, drive: Drive, keys: Sequence[int], out: str | os.PathLike, *, detail,
                     lidar: bool = True, say: Callable[[str], None] | None = None, stereo: bool = True,
                     ego_body: bool = True, exposure: bool = True, workers: int | None = None,
                     stationary_actors: bool = False):
    """A drive's scene folder, the one path of `xyzcyl reconstruct DRIVE_JSON` and of the service's worker for a
    posted drive: reconstruct_drive of the keyframes ``keys`` with the Reconstructor ``rec`` and the detail layer's
    settings ``detail`` (None: none), written to ``out`` (replaced). Returns the scene and the seconds the save
    took."""
    say = say or (lambda msg: None)
    scene = reconstruct_drive(rec, drive, keys, lidar=lidar, detail=detail, progress=say, stereo=stereo,
                              ego_body=ego_body, exposure=exposure, workers=workers,
                              stationary_actors=stationary_actors)
    say(f"write {out}")
    t1 = time.perf_counter()
    scene.save(out, overwrite=True)
    return scene, time.perf_counter() - t1



def _carve_pair(a, b, tolerance: float, stacks: dict | None = None) -> None:
    """Clear a's keep masks for the cells that b's cameras see through (runtime.detail.carve_details' free-space
    rule, dedupe 0: another keyframe never takes over a surface here; dedupe_frames does, on voxels), when b's
    depth was measured (its keyframe had a LiDAR sweep). The model's depth from images alone is too far off to
    say that a camera of another keyframe sees through a cell: on the synthetic drive at 5 m/s without LiDAR,
    carving by it cut trees and signs into pieces and cost 1.8 dB (docs/results.md "Drives at city speed").
    And b's camera must show, near where the cell lands, no colour like the cell's (SEE_THROUGH_PHOTO): a like
    colour is the same surface that the two sweeps put at other depths (glass, a fence, an edge).
    A cell of a that a's own LiDAR placed (CONF_MEASURED) and b sees through was there at a's time and gone at
    b's: it moved away (a car, a pedestrian, tracked or not). It is marked in a's moved masks (the entry's sixth
    field) and drawn only around a's time (actors_of), not dropped. ``stacks``: keyframe -> its cameras stacked
    (CarveCameras), kept there for the next pair (a keyframe carves and is carved by each in its window)."""
    from .detail import CONF_MEASURED, CarveCameras, carve_against

    _, details_a, _, keep_a, measured_a, moved_a = a[:6]
    _, details_b, _, _, measured, _ = b[:6]
    if not measured:
        return
    cameras_b = None if stacks is None else stacks.get(b[0])
    if cameras_b is None:
        cameras_b = CarveCameras.of(details_b)      # stacked once for a's cameras
        if stacks is not None:
            stacks[b[0]] = cameras_b
    for d, keep, gone in zip(details_a, keep_a, moved_a):
        before = keep.copy() if measured_a else None
        carve_against(d, cameras_b, keep, tolerance, SEE_THROUGH_PHOTO)
        if before is not None:
            gone |= before & ~keep & (d.cell_conf() == CONF_MEASURED)


def _snapped(g: Gaussians, origin: np.ndarray, boxes) -> Gaussians:
    """A camera's detail Gaussians with the cells whose ray passes through a moving object's box near their
    depth moved into it (runtime.boxes.snap_into_boxes), their sizes scaled with their distance."""
    means, factor = snap_into_boxes(g.means, origin, boxes)
    moved = factor != 1.0
    if not moved.any():
        return g
    scales = np.array(g.log_scales, copy=True)
    scales[moved] += np.log(factor[moved])[:, None].astype(scales.dtype)
    return replace(g, means=means.astype(g.means.dtype), log_scales=scales)


def _by_box(g: Gaussians, inside: np.ndarray, member: np.ndarray, n_boxes: int) -> list[Gaussians]:
    """[n_boxes] the Gaussians of ``g`` where ``inside`` ([N] bool) holds, by their box ``member`` ([N] int, its
    index), each box's in index order."""
    idx = np.flatnonzero(inside)
    idx = idx[np.argsort(member[idx], kind="stable")]
    bounds = np.searchsorted(member[idx], np.arange(n_boxes + 1))
    return [g.subset(idx[bounds[b]:bounds[b + 1]]) for b in range(n_boxes)]


def _in_order(make: Callable[[int], Any], count: int, ahead: int):
    """make(0), make(1), ..., make(count - 1), yielded in order, up to ``ahead`` of them made at once in threads
    (those not yet yielded: memory stays bounded); where numba's threading layer cannot run two threads' kernels
    at once (numba_cache.threadsafe), one after the other here."""
    if ahead < 2 or not threadsafe():
        yield from (make(i) for i in range(count))
        return
    with ThreadPoolExecutor(ahead, thread_name_prefix="xyzcyl-chunk") as pool:
        waiting = deque(pool.submit(make, i) for i in range(min(ahead, count)))
        try:
            for i in range(count):
                got = waiting.popleft().result()
                if i + ahead < count:
                    waiting.append(pool.submit(make, i + ahead))
                yield got
        finally:
            for f in waiting:
                f.cancel()


def _concat(parts: list[Gaussians]) -> Gaussians:
    from .detail import concat_gaussians

    parts = [g for g in parts if len(g)] or parts[:1]
    return concat_gaussians(parts) if parts else Gaussians.empty()      # no parts: detail off


def drive_meta(drive: Drive, keys: Sequence[int]) -> dict[str, Any]:
    """What scene.json records of the drive: its frames' times (seconds after the first) and ego poses in the
    scene's frame, the keyframes, the first frame's ego_to_world, the tracks' count."""
    t0 = drive.frames[0].timestamp_s
    return {"frames": len(drive), "keyframes": list(map(int, keys)),
            "timestamp_s": drive.frames[0].timestamp_s,
            "times_s": [round(f.timestamp_s - t0, 6) for f in drive.frames],
            "ego_to_world": drive.frames[0].ego_to_world.tolist(),
            "trajectory": [np.round(T, 9).tolist() for T in drive.trajectory()],
            "tracks": len(drive.tracks)}


__all__ = ["DEFAULT_MAX_GAP_S", "DEFAULT_SPACING_M", "Drive", "DriveError", "DriveFrame", "Track",
           "VoxelOwners", "dedupe_frames", "dedupe_frames_reference", "drive_meta", "drive_of_rig",
           "find_drive_ego_body", "inside_boxes", "is_drive_file", "load_drive", "load_tracks",
           "make_keyframe", "moving_boxes", "one_rig", "pick_keyframes", "reconstruct_drive",
           "save_drive_scene", "spill_boxes", "track_speed", "transform_detail", "transform_gaussians",
           "viewpoint_groups", "viewpoint_origins", "voxel_levels", "without_spill"]
