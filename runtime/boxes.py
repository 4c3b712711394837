"""Points in oriented boxes (a drive's tracked objects): which box each point lies in, by a kernel that tests a
point only against the boxes within reach of it along x and y (a keyframe holds millions of cells, a drive dozens of
boxes). Used by the fusion (runtime.drive: what moves leaves the static scene) and the stereo (runtime.stereo: no
point inside what moves)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from .numba_cache import njit


def inside_boxes(points: np.ndarray, boxes: Sequence[tuple]) -> np.ndarray:
    """[N] bool: whether each point lies in one of ``boxes`` (each ending with (frame -> box [4, 4], half-sizes
    [3]), as moving_boxes gives them)."""
    return box_members(points, [b[-2:] for b in boxes]) >= 0


def box_members(points: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """[N] int: the index of the (first) box each point ([N, 3] metres) lies in, -1 for none (boxes: (frame -> box
    [4, 4], half-sizes [3])). A point is tested against a box only when it lies within the box's reach along x and
    y (a drive's keyframe holds millions of cells and dozens of boxes)."""
    p = np.asarray(points).reshape(-1, 3)
    # float32 centres as they are (a keyframe's cells: no float64 copy of millions; the kernel widens each exactly)
    p = np.ascontiguousarray(p, p.dtype if p.dtype in (np.float32, np.float64) else np.float64)
    if not len(p) or not boxes:
        return np.full(len(p), -1, np.int32)
    inv = np.array([np.asarray(b[0], np.float64)[:3] for b in boxes])          # [B, 3, 4]
    half = np.array([np.asarray(b[1], np.float64) for b in boxes])             # [B, 3]
    centre = np.array([-(m[:3, :3].T @ m[:3, 3]) for m in inv])                 # [B, 3] the box centres
    return _box_members(p, inv, half, np.ascontiguousarray(centre[:, :2]), np.linalg.norm(half, axis=1))


@njit(cache=True, nogil=True)
def _box_members(p, inv, half, centre_xy, reach):
    out = np.full(len(p), -1, np.int32)
    for i in range(len(p)):
        x, y, z = np.float64(p[i, 0]), np.float64(p[i, 1]), np.float64(p[i, 2])
        for b in range(len(inv)):
            # a point in the box is within its half-diagonal of the centre, so within it along x and along y
            if abs(x - centre_xy[b, 0]) > reach[b] or abs(y - centre_xy[b, 1]) > reach[b]:
                continue
            m = inv[b]
            if (abs(m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]) <= half[b, 0]
                    and abs(m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]) <= half[b, 1]
                    and abs(m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]) <= half[b, 2]):
                out[i] = b
                break
    return out


SNAP_NEAR, SNAP_FAR = 0.5, 2.0   # snap_into_boxes: a cell within [0.5 x entry, 2 x exit] along its ray through a box
SNAP_INTO_M = 0.3                # ... moves onto the box's near face and this far in (at most halfway through)


def snap_into_boxes(means: np.ndarray, origin: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray]]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Cells of a camera without measured depth whose ray passes through a moving object's box put into it: (means
    [N, 3], factor [N]). A cell (``means`` [N, 3] metres, scene frame) seen from ``origin`` [3] (the camera's
    centre) whose ray enters box b ((frame -> box [4, 4], half-sizes [3])) at distance e and leaves it at x, at a
    distance d with SNAP_NEAR e <= d <= SNAP_FAR x (the model's depth is that far off: AbsRel ~0.5 on real
    cameras), is moved along its ray to e + min(SNAP_INTO_M, (x - e) / 2), the object's near side; ``factor`` is
    its new distance over its old (1 for the others; a cell's size scales with it). Cells already inside a box,
    and those no box's ray passes through, stay; the first box along the list wins; a camera within a box's
    bounding sphere has no near side of it to snap to. One numba pass over the cells, each tested only against the
    boxes whose bounding cone holds its ray (snap_into_boxes_reference is the numpy definition; tested)."""
    p = np.ascontiguousarray(means, np.float64).reshape(-1, 3)
    o = np.asarray(origin, np.float64).reshape(3)
    out, factor = p.copy(), np.ones(len(p))
    if not len(p) or not boxes:
        return out, factor
    inv = np.ascontiguousarray([np.asarray(b[0], np.float64)[:3] for b in boxes])     # [B, 3, 4]
    half = np.ascontiguousarray([np.asarray(b[1], np.float64) for b in boxes])         # [B, 3]
    centre = -np.einsum("bji,bj->bi", inv[:, :, :3], inv[:, :, 3])                    # [B, 3] the boxes' centres
    to_c = centre - o
    r = np.linalg.norm(to_c, axis=1)
    reach = np.linalg.norm(half, axis=1)
    use = r > reach                    # the camera outside the box's bounding sphere (a near side to snap to)
    if not use.any():
        return out, factor
    axis = to_c[use] / r[use, None]
    cos_cone = np.sqrt(np.maximum(0.0, 1.0 - (reach[use] / r[use]) ** 2))       # the box's bounding cone
    _snap_kernel(p, o, np.ascontiguousarray(inv[use]), np.ascontiguousarray(half[use]), axis, cos_cone,
                 SNAP_NEAR, SNAP_FAR, SNAP_INTO_M, out, factor)
    return out, factor


@njit(cache=True, parallel=True, nogil=True)
def _snap_kernel(p, o, inv, half, axis, cos_cone, near, far, into, out, factor):
    for i in numba.prange(p.shape[0]):
        dx, dy, dz = p[i, 0] - o[0], p[i, 1] - o[1], p[i, 2] - o[2]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        ux, uy, uz = dx / max(dist, 1e-9), dy / max(dist, 1e-9), dz / max(dist, 1e-9)
        for b in range(inv.shape[0]):
            if ux * axis[b, 0] + uy * axis[b, 1] + uz * axis[b, 2] < cos_cone[b]:
                continue
            t_in, t_out = -np.inf, np.inf
            for a in range(3):
                ob = inv[b, a, 0] * o[0] + inv[b, a, 1] * o[1] + inv[b, a, 2] * o[2] + inv[b, a, 3]
                v = inv[b, a, 0] * ux + inv[b, a, 1] * uy + inv[b, a, 2] * uz
                t1, t2 = (-half[b, a] - ob) / v, (half[b, a] - ob) / v        # +-inf (or nan) for v == 0
                if t1 == t1 and t2 == t2:           # the reference's nan_to_num: a nan bound does not count
                    t_in = max(t_in, min(t1, t2))
                    t_out = min(t_out, max(t1, t2))
            t_in = max(t_in, 0.0)
            if not (t_out > t_in and dist >= near * t_in and dist <= far * t_out):
                continue
            if dist < t_in or dist > t_out:
                nd = t_in + min(into, 0.5 * (t_out - t_in))
                out[i, 0], out[i, 1], out[i, 2] = o[0] + ux * nd, o[1] + uy * nd, o[2] + uz * nd
                factor[i] = nd / dist
            break


def snap_into_boxes_reference(means: np.ndarray, origin: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray]]
                              ) -> tuple[np.ndarray, np.ndarray]:
    """snap_into_boxes in numpy: box after box, the cells in its bounding cone that no box before took."""
    p = np.asarray(means, np.float64).reshape(-1, 3)
    o = np.asarray(origin, np.float64).reshape(3)
    out, factor = p.copy(), np.ones(len(p))
    if not len(p) or not boxes:
        return out, factor
    d = p - o
    dist = np.linalg.norm(d, axis=1)
    u = d / np.maximum(dist, 1e-9)[:, None]
    done = np.zeros(len(p), bool)
    for inv, half in boxes:
        inv = np.asarray(inv, np.float64)
        half = np.asarray(half, np.float64)
        centre = -(inv[:3, :3].T @ inv[:3, 3])
        to_c = centre - o
        r = float(np.linalg.norm(to_c))
        reach = float(np.linalg.norm(half))
        if r <= reach:               # the camera inside (or at) the box: no near side to snap to
            continue
        cand = np.flatnonzero(~done & (u @ (to_c / r) >= np.sqrt(max(0.0, 1 - (reach / r) ** 2))))   # its cone
        if not len(cand):
            continue
        ob = inv[:3, :3] @ o + inv[:3, 3]                      # the ray in the box frame
        v = u[cand] @ inv[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - ob) / v, (half - ob) / v
        t_in = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf).max(axis=1)
        t_out = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(axis=1)
        t_in = np.maximum(t_in, 0.0)
        dc = dist[cand]
        hit = (t_out > t_in) & (dc >= SNAP_NEAR * t_in) & (dc <= SNAP_FAR * t_out)
        move = hit & ((dc < t_in) | (dc > t_out))
        new_d = t_in + np.minimum(SNAP_INTO_M, 0.5 * (t_out - t_in))
        idx = cand[move]
        out[idx] = o + u[idx] * new_d[move][:, None]
        factor[idx] = new_d[move] / dc[move]
        done[cand[hit]] = True
    return out, factor


__all__ = ["box_members", "inside_boxes", "snap_into_boxes", "snap_into_boxes_reference"]
