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


__all__ = ["box_members", "inside_boxes"]
