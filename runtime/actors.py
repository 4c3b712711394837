"""The moving objects of a drive's scene, drawn at a time: ``Actors``.

runtime.drive leaves the Gaussians inside the box of a tracked object that moves out of the static scene. Here
they become that object's copies: at each keyframe that saw it, its Gaussians in its box frame (x along its
length, y left, z up, origin at the box centre), with the keyframe's time. A render at time T (seconds on the
rigs' clock) draws every object whose annotated poses span T (half a frame interval of slack at either end): its
copy from the keyframe nearest T, placed at its box pose at T (the annotated poses interpolated: the position
linearly, the rotation by slerp). An object is not drawn outside its time span, so a passing car leaves no ghost
trail; the static scene holds no copy of it.

actors.npz (numpy arrays, no pickle): the copies' Gaussians concatenated (means, quats, log_scales,
opacity_logits, sh), ``copy_track`` / ``copy_time`` / ``copy_start`` (each copy's object, keyframe time, first
Gaussian; copy_start has one more entry), ``track_id`` / ``track_label`` / ``track_size``, ``pose_track`` /
``pose_time`` / ``pose`` (every annotated pose: object, time, box -> scene [4, 4]); optionally ``fill_means`` ...
``fill_sh`` and ``fill_track`` (the ground under the objects that no frame saw, runtime.groundfill, in the scene's
frame, and each disc's object)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from xyzcyl.common.poses import pose_matrix
from xyzcyl.common.wire import ActorEdit, ViewError

from .camera import check_pose
from .errors import CameraError, FieldError
from .render import FIELDS, Gaussians
from .rotations import quat_to_rotmat, rotmats_to_quats

ACTORS_NAME = "actors.npz"
CLEARED_TOL = (0.05, 1.0)  # (metres, degrees): an actor placed within this of where it is has not been taken away
MOVED_LABEL = "moved"          # the label of a keyframe's cells that moved away without a track (runtime.drive)


class ActorsError(FieldError):
    """An actors.npz that cannot be used (``field`` the array at fault)."""


def frame_interval(times_s) -> float:
    """A drive's median time between frames (seconds; ``times_s`` [F] ascending; 0.1 with fewer than two). An
    object is drawn half of it beyond its first and last pose (Actors.at's slack)."""
    d = np.diff(np.asarray(times_s, np.float64))
    return float(np.median(d)) if len(d) else 0.1


def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Unit quaternion (wxyz) a fraction ``t`` of the way from q0 to q1 along the shorter arc."""
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    a = math.acos(min(1.0, d))
    return (math.sin((1 - t) * a) * q0 + math.sin(t * a) * q1) / math.sin(a)


@dataclass(frozen=True, eq=False)
class Actors:
    track_id: tuple[str, ...]
    track_label: tuple[str, ...]
    track_size: np.ndarray        # [A, 3] metres: length, width, height
    pose_track: np.ndarray        # [Q] int: the object of each annotated pose
    pose_time: np.ndarray         # [Q] float64 seconds (rigs' clock)
    pose: np.ndarray              # [Q, 4, 4] box -> scene frame
    copy_track: np.ndarray        # [C] int
    copy_time: np.ndarray         # [C] float64 seconds: the keyframe's time
    copy_start: np.ndarray        # [C + 1] int: copy c is Gaussians copy_start[c]:copy_start[c + 1]
    gaussians: Gaussians          # the copies' Gaussians, each in its object's box frame
    # the ground under the objects that no frame saw (runtime.groundfill), scene frame, and each disc's object:
    # drawn in views that take an object away (runtime.scene.Scene.fill_for, cleared)
    fill: Gaussians | None = None
    fill_track: np.ndarray | None = None      # [F] int
    _ids: dict[str, int] | None = field(default=None, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.track_id)

    def span(self, a: int) -> tuple[float, float]:
        """(first, last) annotated time of object a, seconds."""
        t = self.pose_time[self.pose_track == a]
        return float(t.min()), float(t.max())

    def pose_at(self, a: int, time_s: float, slack_s: float) -> np.ndarray | None:
        """[4, 4] object a's box -> scene at ``time_s`` (interpolated between its annotated poses), or None outside
        its span widened by ``slack_s`` on either side (clamped to the end pose within the slack)."""
        m = self.pose_track == a
        times, poses = self.pose_time[m], self.pose[m]
        order = np.argsort(times)
        times, poses = times[order], poses[order]
        if time_s < times[0] - slack_s or time_s > times[-1] + slack_s:
            return None
        if time_s <= times[0]:
            return poses[0]
        if time_s >= times[-1]:
            return poses[-1]
        j = int(np.searchsorted(times, time_s))
        t = (time_s - times[j - 1]) / (times[j] - times[j - 1])
        out = np.eye(4)
        out[:3, 3] = (1 - t) * poses[j - 1][:3, 3] + t * poses[j][:3, 3]
        q = _slerp(rotmats_to_quats(poses[j - 1][None, :3, :3])[0], rotmats_to_quats(poses[j][None, :3, :3])[0], t)
        out[:3, :3] = quat_to_rotmat(q)
        return out

    def index(self, actor_id: str) -> int | None:
        """The index of the object ``actor_id``, None when the scene has none so named."""
        if self._ids is None:
            object.__setattr__(self, "_ids", {a: i for i, a in enumerate(self.track_id)})
        return self._ids.get(actor_id)

    def placements(self, time_s: float, slack_s: float, edits: Sequence[ActorEdit] = (),
                   reach: tuple[np.ndarray, float] | None = None, field: str = "actors"
                   ) -> list[tuple[int, np.ndarray]]:
        """(object, box -> scene [4, 4]) of every object drawn at ``time_s``: each at its recorded pose then
        (pose_at: none outside its span), with ``edits`` (common.wire.ActorEdit, a view's ``actors``) applied: an
        edited object at its ``pose`` (at any time) or ``offset`` (metres along its own axes from its recorded pose
        then), or not at all (``hide``); an edit with ``insert`` adds a copy of its object at that pose, the object
        itself untouched. ``reach``: (positions [P, 3] metres, scene frame; R metres): a pose farther than R from
        every position is refused (a pose kilometres away is a mistake in the caller's frame, not a place). Each
        refusal a ViewError naming the edit's field (``field``[i].id, .pose, .offset, .insert)."""
        edited: dict[int, np.ndarray | None] = {}
        inserted: list[tuple[int, np.ndarray]] = []
        names: set[str] = set()
        for i, e in enumerate(edits):
            where = f"{field}[{i}]"
            a = self.index(e.id)
            if a is None:
                known = ", ".join(self.track_id[:5]) + (f", ... ({len(self)} in all)" if len(self) > 5 else "")
                raise ViewError(f"{where}.id", f"no actor {e.id!r} in the scene (GET .../actors lists them: "
                                               f"{known or 'none'})")
            if e.insert is not None:
                if e.insert in names or self.index(e.insert) is not None:
                    raise ViewError(f"{where}.insert", f"{e.insert!r} is already an actor of this view (a new id "
                                                       f"is needed)")
                names.add(e.insert)
            elif a in edited:
                raise ViewError(f"{where}.id", f"{e.id!r} is edited twice in this view")
            if e.hide:
                edited[a] = None
                continue
            if e.pose is not None:
                try:        # a rotation and a translation (runtime.camera.check_pose)
                    T = check_pose(e.pose, key=f"{where}.pose")
                except CameraError as err:
                    raise ViewError(f"{where}.pose", err.message) from None
            else:
                here = self.pose_at(a, time_s, slack_s)
                if here is None:
                    lo, hi = self.span(a)
                    raise ViewError(f"{where}.offset", f"{e.id!r} is not in the scene at {time_s:.3f} s (its "
                                                       f"span is {lo:.3f}..{hi:.3f} s): give a pose")
                T = here.copy()
                T[:3, 3] = here[:3, 3] + here[:3, :3] @ np.asarray(e.offset, np.float64)
            if reach is not None and len(reach[0]):
                d = float(np.linalg.norm(np.asarray(reach[0], np.float64) - T[:3, 3], axis=1).min())
                if d > reach[1]:
                    key = "pose" if e.pose is not None else "offset"
                    raise ViewError(f"{where}.{key}", f"puts {e.id!r} {d:.0f} m from the drive (at most "
                                                      f"{reach[1]:.0f} m; poses are in the scene's frame)")
            if e.insert is not None:
                inserted.append((a, T))
            else:
                edited[a] = T
        out = []
        for a in range(len(self)):
            T = edited[a] if a in edited else self.pose_at(a, time_s, slack_s)
            if T is not None:
                out.append((a, T))
        return out + inserted

    def listing(self, time_s: float | None = None, slack_s: float = 0.0) -> list[dict]:
        """Every object as common.wire.ActorInfo's fields: id, label, tracked (False: cells that moved away without
        a track, label MOVED), size (metres: length, width, height), span_s (first, last annotated time),
        copies, gaussians; with ``time_s`` also its pose then (16 numbers row-major, box -> scene frame; None when
        it is not drawn then)."""
        counts = np.diff(self.copy_start)
        filled = self.filled_m2()
        out = []
        for a in range(len(self)):
            mine = self.copy_track == a
            row = {"id": self.track_id[a], "label": self.track_label[a],
                   "tracked": self.track_label[a] != MOVED_LABEL,
                   "size": [round(float(x), 4) for x in self.track_size[a]],
                   "span_s": [round(t, 6) for t in self.span(a)], "copies": int(mine.sum()),
                   "gaussians": int(counts[mine].sum()),
                   "filled_m2": round(float(filled[a]), 2)}
            if time_s is not None:
                T = self.pose_at(a, time_s, slack_s)
                row["pose"] = None if T is None else [round(float(x), 9) + 0.0 for x in T.ravel()]
            out.append(row)
        return out

    def filled_m2(self) -> np.ndarray:
        """[A] m^2: the ground under each object that no frame saw, filled (runtime.groundfill)."""
        from .groundfill import FILL_SPACING_M

        n = np.zeros(len(self), np.float64)
        if self.fill_track is not None:
            np.add.at(n, np.asarray(self.fill_track, np.int64), FILL_SPACING_M ** 2)
        return n

    def cleared(self, edits: Sequence[ActorEdit], time_s: float, slack_s: float) -> list[int]:
        """The objects ``edits`` take away from where the recording has them at ``time_s``: hidden, or placed
        (pose, offset) more than CLEARED_TOL from it. An inserted copy takes nothing away, nor does an edit of an
        object that is not there then (known ids only)."""
        out = {}
        for e in edits:
            a = self.index(e.id)
            if a is None or e.insert is not None:
                continue
            here = self.pose_at(a, time_s, slack_s)
            if here is None:
                continue
            if not e.hide:
                P = pose_matrix(e.pose, "pose") if e.pose is not None else None
                T = here[:3, 3] + here[:3, :3] @ np.asarray(e.offset, np.float64) if P is None else P[:3, 3]
                R = here[:3, :3] if P is None else P[:3, :3]
                turn = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R.T @ here[:3, :3])) - 1) / 2))))
                if np.linalg.norm(T - here[:3, 3]) <= CLEARED_TOL[0] and turn <= CLEARED_TOL[1]:
                    continue
            out[a] = here
        return sorted(out)

    def copy_of(self, a: int, time_s: float) -> Gaussians:
        """Object a's Gaussians in its box frame: its copy from the keyframe nearest ``time_s`` (empty without)."""
        copies = np.flatnonzero(self.copy_track == a)
        if not len(copies):
            return Gaussians.empty(self.gaussians.sh_degree)
        c = int(copies[np.argmin(np.abs(self.copy_time[copies] - time_s))])
        return self.gaussians.slice(int(self.copy_start[c]), int(self.copy_start[c + 1]))

    def at(self, time_s: float, slack_s: float, edits: Sequence[ActorEdit] = (),
           reach: tuple[np.ndarray, float] | None = None) -> tuple[Gaussians, list[int]]:
        """The Gaussians of every object drawn at ``time_s`` (scene frame; placements, with ``edits``) and which
        objects those are (an inserted copy: its object's index)."""
        parts, drawn = [], []
        for a, T in self.placements(time_s, slack_s, edits, reach):
            g = self.copy_of(a, time_s)
            if len(g):
                parts.append(g.transformed(T))
                drawn.append(a)
        if not parts:
            return Gaussians.empty(self.gaussians.sh_degree), drawn
        return Gaussians(*(np.concatenate([getattr(p, k) for p in parts]) for k in FIELDS)), drawn

    # -- files ------------------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        g = self.gaussians
        with open(path, "wb") as f:
            np.savez(f, means=g.means, quats=g.quats, log_scales=g.log_scales, opacity_logits=g.opacity_logits,
                     sh=g.sh, copy_track=self.copy_track.astype(np.int32), copy_time=self.copy_time,
                     copy_start=self.copy_start.astype(np.int64), track_id=np.array(self.track_id, dtype=str),
                     track_label=np.array(self.track_label, dtype=str), track_size=self.track_size,
                     pose_track=self.pose_track.astype(np.int32), pose_time=self.pose_time, pose=self.pose,
                     **({} if self.fill is None else {**{f"fill_{k}": getattr(self.fill, k) for k in FIELDS},
                                                      "fill_track": np.asarray(self.fill_track, np.int32)}))

    @classmethod
    def load(cls, path: str | os.PathLike) -> Actors:
        try:
            with np.load(path, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise ActorsError("actors", f"cannot read {str(path)!r} ({e})") from None
        missing = [k for k in (*FIELDS, "copy_track", "copy_time", "copy_start", "track_id", "track_label",
                               "track_size", "pose_track", "pose_time", "pose") if k not in d]
        if missing:
            raise ActorsError(missing[0], f"is missing from {str(path)!r}")
        n = len(d["means"])
        cs = d["copy_start"]
        if len(cs) != len(d["copy_track"]) + 1 or (len(cs) and (cs[0] != 0 or cs[-1] != n or np.any(np.diff(cs) < 0))):
            raise ActorsError("copy_start", f"does not split the {n} Gaussians into the copies ({str(path)!r})")
        a = len(d["track_id"])
        fill = fill_track = None
        if "fill_track" in d:           # written since the ground fill (runtime.groundfill)
            if any(f"fill_{k}" not in d for k in FIELDS):
                raise ActorsError("fill_means", f"the ground fill is incomplete ({str(path)!r})")
            fill = Gaussians(*(d[f"fill_{k}"] for k in FIELDS))
            fill_track = d["fill_track"]
            if len(fill_track) != len(fill):
                raise ActorsError("fill_track", f"names {len(fill_track)} discs' objects, not {len(fill)} "
                                                f"({str(path)!r})")
        for k in ("copy_track", "pose_track", *(("fill_track",) if fill_track is not None else ())):
            if len(d[k]) and (d[k].min() < 0 or d[k].max() >= a):
                raise ActorsError(k, f"names an object outside 0..{a - 1} ({str(path)!r})")
        return cls(track_id=tuple(str(x) for x in d["track_id"]), track_label=tuple(str(x) for x in d["track_label"]),
                   track_size=d["track_size"], pose_track=d["pose_track"], pose_time=d["pose_time"], pose=d["pose"],
                   copy_track=d["copy_track"], copy_time=d["copy_time"], copy_start=cs,
                   gaussians=Gaussians(*(d[k] for k in FIELDS)), fill=fill, fill_track=fill_track)


__all__ = ["ACTORS_NAME", "MOVED_LABEL", "Actors", "ActorsError", "frame_interval"]
