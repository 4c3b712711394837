"""The road where a moving object stood and no frame saw it (issue 38 item 2): a drive's actor leaves the static
scene, and the ground under and behind it is what the other keyframes saw there; where none saw it (the road under a
car the ego followed the whole drive), that ground is filled here with flat discs of the neighbouring road's colour,
kept with the actor (runtime.actors.Actors.fill) and drawn, behind everything else, when a view hides or moves it:
it leaves road, not the background panorama showing through the street.

fill_under(static, footprints) takes every annotated pose of the moving objects (its box: the ground is its bottom
face), lays a FILL_SPACING_M lattice over each footprint (grown by GROW_M), and keeps the lattice points that no
static Gaussian covers (none within one lattice step horizontally whose centre lies within GROUND_TOL_M of that
ground height). Each kept point is one disc (FILL_RADIUS_M across, FILL_THICK_M thick, opacity FILL_OPACITY) with the
median colour (SH DC) of the static Gaussians on the ground in a RING_M ring around that object's footprints (grey
when there are none). The filled area is counted per object (lattice points x spacing^2)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .render import Gaussians

FILL_SPACING_M = 0.2     # the lattice over a footprint (metres)
FILL_RADIUS_M = 0.14     # a disc's scale along the ground: neighbouring discs overlap (spacing / sqrt 2)
FILL_THICK_M = 0.02      # its scale across the ground
FILL_OPACITY = 0.95
GROW_M = 0.3             # a footprint grown by this on every side (a box's annotation is not exact)
GROUND_TOL_M = 0.35      # a static Gaussian this close to a footprint's ground height covers it
RING_M = 2.0             # the ring around a footprint whose ground colour fills it
GREY_DC = 0.0            # SH DC of mid grey (colour 0.5): no ground around to copy


def _frame(T: np.ndarray, size: np.ndarray) -> np.ndarray:
    """[4, 4] the frame of a box's bottom face: the box's axes, origin the bottom face's centre."""
    out = np.array(T, np.float64)
    out[:3, 3] = T[:3, 3] - 0.5 * float(size[2]) * T[:3, 2]
    return out


def _pack(k: np.ndarray) -> np.ndarray:
    """[N] int64 of [N, 2] int64 lattice keys (x in the high 32 bits)."""
    return k[:, 0] * (1 << 32) + (k[:, 1] & 0xFFFFFFFF)


def fill_under(static: Gaussians, footprints: Sequence[tuple[int, np.ndarray, np.ndarray]], n_objects: int
               ) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """(fill Gaussians [F] (scene frame, SH degree 0), the object under which each lies [F] int, the filled area
    per object [n_objects] m^2) for ``footprints``:
    (object index, box -> scene [4, 4], size [3] metres: length, width, height) of the moving objects' annotated
    poses, against the ``static`` Gaussians (scene frame; module docstring)."""
    area = np.zeros(n_objects, np.float64)
    if not len(footprints):
        return Gaussians.empty(0), np.zeros(0, np.int64), area
    s = FILL_SPACING_M
    keys, heights, owners, inner = [], [], [], []
    for a, T, size in footprints:
        F = _frame(np.asarray(T, np.float64), np.asarray(size, np.float64))
        hx, hy = 0.5 * float(size[0]) + GROW_M, 0.5 * float(size[1]) + GROW_M
        gx, gy = np.meshgrid(np.arange(-hx - RING_M, hx + RING_M + 1e-9, s),
                             np.arange(-hy - RING_M, hy + RING_M + 1e-9, s), indexing="ij")
        local = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
        pts = local @ F[:3, :3].T + F[:3, 3]
        keys.append(np.floor(pts[:, :2] / s).astype(np.int64))
        heights.append(pts[:, 2])
        owners.append(np.full(len(pts), a, np.int64))
        inner.append((np.abs(local[:, 0]) <= hx) & (np.abs(local[:, 1]) <= hy))
    key, z, owner, inner = (np.concatenate(x) for x in (keys, heights, owners, inner))
    # one point per lattice cell: a footprint's (inner) before a ring's, then the first
    order = np.lexsort((~inner, _pack(key)))
    packed = _pack(key)[order]
    first = np.ones(len(packed), bool)
    first[1:] = packed[1:] != packed[:-1]
    pick = order[first]
    packed, key, z, owner, inner = packed[first], key[pick], z[pick], owner[pick], inner[pick]

    # the static Gaussians on the ground of a lattice cell (within GROUND_TOL_M of its height)
    p = np.asarray(static.means, np.float64)
    lo, hi = key.min(axis=0) * s, (key.max(axis=0) + 1) * s
    cand = np.flatnonzero(np.all((p[:, :2] >= lo) & (p[:, :2] < hi), axis=1))
    pk = _pack(np.floor(p[cand, :2] / s).astype(np.int64))
    i = np.minimum(np.searchsorted(packed, pk), len(packed) - 1)
    hit = packed[i] == pk
    cand, j = cand[hit], i[hit]
    ground = np.abs(p[cand, 2] - z[j]) <= GROUND_TOL_M
    cand, j = cand[ground], j[ground]
    # a cell is covered by a Gaussian on its own ground or on one of the 8 around it
    covered = np.zeros(len(packed), bool)
    seen = np.unique(j)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            nk = _pack(key[seen] + np.array([dx, dy]))
            m = np.minimum(np.searchsorted(packed, nk), len(packed) - 1)
            covered[m[packed[m] == nk]] = True
    keep = inner & ~covered
    if not keep.any():
        return Gaussians.empty(0), np.zeros(0, np.int64), area

    # each object's ground colour: the median SH DC of the static Gaussians on its ring's cells
    colour = np.full((n_objects, 3), GREY_DC)
    ring = ~inner[j]
    dc = np.asarray(static.sh[cand[ring], 0, :], np.float64)
    who = owner[j[ring]]
    for a in np.unique(owner[keep]):
        mine = who == a
        if mine.any():
            colour[a] = np.median(dc[mine], axis=0)
    n = int(keep.sum())
    means = np.column_stack([(key[keep] + 0.5) * s, z[keep]]).astype(np.float32)
    fill = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                     np.tile(np.log(np.float32([FILL_RADIUS_M, FILL_RADIUS_M, FILL_THICK_M])), (n, 1)),
                     np.full(n, np.log(FILL_OPACITY / (1 - FILL_OPACITY)), np.float32),
                     colour[owner[keep]].astype(np.float32)[:, None, :])
    np.add.at(area, owner[keep], s * s)
    return fill, owner[keep], area


__all__ = ["FILL_SPACING_M", "fill_under"]
