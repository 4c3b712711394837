"""Points in oriented boxes (a drive's tracked objects): which box each point lies in, by a kernel that tests a
point only against the boxes within reach of it along x (a keyframe holds millions of cells, a drive dozens of
boxes). Used by the fusion (runtime.drive: what moves leaves the static scene) and the stereo (runtime.stereo: no
point inside what moves)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .numba_cache import njit


def inside_boxes(points: np.ndarray, boxes: Sequence[tuple]) -> np.ndarray:
    """[N] bool: whether each point lies in one of ``boxes`` (each ending with (frame -> box [4, 4], half-sizes
    [3]), as moving_boxes gives them)."""
    return box_members(points, [b[-2:] for b in boxes]) >= 0


def box_members(points: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """[N] int: the index of the (first) box each point ([N, 3] metres) lies in, -1 for none (boxes: (frame -> box
    [4, 4], half-sizes [3])). A point is tested against a box only when it lies within the box's reach along x (a
    drive's keyframe holds millions of cells and dozens of boxes)."""
    p = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    if not len(p) or not boxes:
        return np.full(len(p), -1, np.int32)
    inv = np.array([np.asarray(b[0], np.float64)[:3] for b in boxes])          # [B, 3, 4]
    half = np.array([np.asarray(b[1], np.float64) for b in boxes])             # [B, 3]
    centre_x = np.array([-(m[:3, :3].T @ m[:3, 3])[0] for m in inv])            # the box centres' x
    return _box_members(p, inv, half, centre_x, np.linalg.norm(half, axis=1))


@njit(cache=True, nogil=True)
def _box_members(p, inv, half, centre_x, reach):
    out = np.full(len(p), -1, np.int32)
    for i in range(len(p)):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        for b in range(len(inv)):
            if abs(x - centre_x[b]) > reach[b]:
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
    and those no box's ray passes through, stay; the first box along the list wins."""
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


__all__ = ["box_members", "inside_boxes", "snap_into_boxes"]
