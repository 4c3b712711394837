"""Small drives for tests (runtime.drive; docs/inference.md "Drives"): ``write_drive`` writes a drive folder of the
example rig (its images, by absolute path) at given ego poses and times, optionally with tracks; ``moving_car`` is a
tracks file's content with one moving box; ``pose`` makes an ego pose on the ground."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import xyzcyl.testing as _testing  # its EXAMPLE_RIG is found on first use (the source checkout's)


def pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> list[list[float]]:
    """An ego (or object) pose, 4x4 rows: at (x, y) metres on the ground, turned ``yaw_deg`` to the left."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return [[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0.0], [0, 0, 0, 1]]


def _rows(m: Any) -> list[list[float]]:
    return np.asarray(m, np.float64).reshape(4, 4).tolist()


def write_drive(tmp: Path, poses: list, times: list, edit: Callable[[int, dict], Any] | None = None,
                tracks: Any = None) -> Path:
    """A drive of the example rig (its images, by absolute path) at ``poses`` (ego_to_world: 4x4 lists or arrays;
    None: none) and ``times`` (the frame entries' timestamp_s; None: none), written into ``tmp``; ``edit(i,
    rig_dict)`` may change a frame's rig; ``tracks``: a tracks file's content. Returns the drive file."""
    tmp = Path(tmp)
    base = json.loads(Path(_testing.EXAMPLE_RIG).read_text())
    frames = []
    for i, (p, ts) in enumerate(zip(poses, times)):
        rig = json.loads(json.dumps(base))
        for c in rig["cameras"]:
            c["image"] = str(Path(_testing.EXAMPLE_RIG).parent / c["image"])
        if p is not None:
            rig["ego_to_world"] = _rows(p)
        if edit is not None:
            edit(i, rig)
        (tmp / f"frame_{i:02d}").mkdir(parents=True, exist_ok=True)
        (tmp / f"frame_{i:02d}" / "rig.json").write_text(json.dumps(rig))
        entry = {"rig": f"frame_{i:02d}/rig.json"}
        if ts is not None:
            entry["timestamp_s"] = ts
        frames.append(entry)
    doc = {"frames": frames}
    if tracks is not None:
        (tmp / "tracks.json").write_text(json.dumps(tracks))
        doc["tracks"] = "tracks.json"
    (tmp / "drive.json").write_text(json.dumps(doc))
    return tmp / "drive.json"


def moving_car(ego_to_world: Any, ahead_m: float = 12.0, moved_m: float = 3.0,
               size: tuple[float, float, float] = (5.0, 6.0, 4.0)) -> dict:
    """A tracks file's content: one car ("car-1", not stationary) ``ahead_m`` metres ahead of the ego at
    ``ego_to_world`` in frame 0 and ``moved_m`` further along the ego's x in frame 1 (a box large enough to hold
    what the example rig's front camera sees there)."""
    E = np.asarray(ego_to_world, np.float64).reshape(4, 4)
    at = lambda dx: _rows(E @ np.asarray(pose(ahead_m + dx, 0.0)))      # noqa: E731
    return {"tracks": [{"id": "car-1", "label": "Car", "size": list(size), "stationary": False,
                        "poses": [{"frame": 0, "object_to_world": at(0.0)},
                                  {"frame": 1, "object_to_world": at(moved_m)}]}]}


def cut_drive(src: Path, frames: list[int], out: Path) -> Path:
    """A drive of ``frames`` (indices into the drive file ``src``'s frames, increasing) written to ``out``/drive.json:
    its frame entries (rigs by absolute path) and its tracks, each pose renumbered into the new frames and the
    poses of other frames left out (a track left with none is dropped). Returns the drive file."""
    src, out = Path(src), Path(out)
    doc = json.loads(src.read_text())
    new = {old: i for i, old in enumerate(frames)}
    entries = []
    for old in frames:
        e = dict(doc["frames"][old])
        e["rig"] = str((src.parent / e["rig"]).resolve())
        entries.append(e)
    cut: dict = {"frames": entries}
    if isinstance(doc.get("tracks"), str):
        tracks = json.loads((src.parent / doc["tracks"]).read_text())
        kept = []
        for t in tracks["tracks"]:
            poses = [{**p, "frame": new[p["frame"]]} for p in t["poses"] if p["frame"] in new]
            if poses:
                kept.append({**t, "poses": poses})
        out.mkdir(parents=True, exist_ok=True)
        (out / "tracks.json").write_text(json.dumps({**tracks, "tracks": kept}))
        cut["tracks"] = "tracks.json"
    out.mkdir(parents=True, exist_ok=True)
    (out / "drive.json").write_text(json.dumps(cut))
    return out / "drive.json"


__all__ = ["cut_drive", "moving_car", "pose", "write_drive"]
