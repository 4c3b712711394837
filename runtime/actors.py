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
``pose_time`` / ``pose`` (every annotated pose: object, time, box -> scene [4, 4])."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .errors import FieldError
from .render import Gaussians
from .rotations import quat_to_rotmat, rotmats_to_quats

ACTORS_NAME = "actors.npz"
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


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

    def at(self, time_s: float, slack_s: float) -> tuple[Gaussians, list[int]]:
        """The Gaussians of every object drawn at ``time_s`` (scene frame) and which objects those are."""
        parts, drawn = [], []
        for a in range(len(self)):
            T = self.pose_at(a, time_s, slack_s)
            copies = np.flatnonzero(self.copy_track == a)
            if T is None or not len(copies):
                continue
            c = int(copies[np.argmin(np.abs(self.copy_time[copies] - time_s))])
            g = self.gaussians.subset(np.arange(self.copy_start[c], self.copy_start[c + 1]))
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
                     pose_track=self.pose_track.astype(np.int32), pose_time=self.pose_time, pose=self.pose)

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
        for k in ("copy_track", "pose_track"):
            if len(d[k]) and (d[k].min() < 0 or d[k].max() >= a):
                raise ActorsError(k, f"names an object outside 0..{a - 1} ({str(path)!r})")
        return cls(track_id=tuple(str(x) for x in d["track_id"]), track_label=tuple(str(x) for x in d["track_label"]),
                   track_size=d["track_size"], pose_track=d["pose_track"], pose_time=d["pose_time"], pose=d["pose"],
                   copy_track=d["copy_track"], copy_time=d["copy_time"], copy_start=cs,
                   gaussians=Gaussians(*(d[k] for k in FIELDS)))


__all__ = ["ACTORS_NAME", "Actors", "ActorsError"]
