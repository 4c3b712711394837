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
from dataclasses import dataclass

import numba
import numpy as np

from .numba_cache import njit
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


@dataclass(frozen=True, eq=False)
class FillLattice:
    """The lattice of fill_under over the moving objects' footprints (fill_lattice): one point per lattice cell."""

    n_objects: int
    packed: np.ndarray      # [L] int64 ascending: the cells (_pack'ed keys)
    key: np.ndarray         # [L, 2] int64: floor(x / s), floor(y / s) of each cell
    z: np.ndarray           # [L] float64 metres, scene frame: its ground height
    owner: np.ndarray       # [L] int64: the object whose footprint (or ring) it is
    inner: np.ndarray       # [L] bool: in a footprint (else in a ring around one)


def fill_lattice(footprints: Sequence[tuple[int, np.ndarray, np.ndarray]], n_objects: int) -> FillLattice:
    """fill_under's lattice over ``footprints`` (fill_under's): it needs no static Gaussian, so a drive lays it
    while its shared cells are still being read (runtime.drive.reconstruct_drive)."""
    s = FILL_SPACING_M
    if not len(footprints):
        none = np.zeros(0, np.int64)
        return FillLattice(n_objects, none, np.zeros((0, 2), np.int64), np.zeros(0), none, np.zeros(0, bool))
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
    return FillLattice(n_objects, packed[first], key[pick], z[pick], owner[pick], inner[pick])


def fill_under(static: Gaussians, footprints: Sequence[tuple[int, np.ndarray, np.ndarray]], n_objects: int
               ) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """(fill Gaussians [F] (scene frame, SH degree 0), the object under which each lies [F] int, the filled area
    per object [n_objects] m^2) for ``footprints``:
    (object index, box -> scene [4, 4], size [3] metres: length, width, height) of the moving objects' annotated
    poses, against the ``static`` Gaussians (scene frame; module docstring)."""
    return fill_lattice_under(static, fill_lattice(footprints, n_objects))


def fill_lattice_under(static: Gaussians, lattice: FillLattice) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """fill_under on a lattice laid already (fill_lattice)."""
    s = FILL_SPACING_M
    area = np.zeros(lattice.n_objects, np.float64)
    if not len(lattice.packed):
        return Gaussians.empty(0), np.zeros(0, np.int64), area
    packed, key, z, owner, inner = lattice.packed, lattice.key, lattice.z, lattice.owner, lattice.inner

    # the static Gaussians on the ground of a lattice cell (within GROUND_TOL_M of its height)
    lo, hi = key.min(axis=0) * s, (key.max(axis=0) + 1) * s
    cand, j = ground_cells(static.means, lo, hi, s, packed, z)
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
    colour = np.full((lattice.n_objects, 3), GREY_DC)
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


def ground_cells_reference(means: np.ndarray, lo: np.ndarray, hi: np.ndarray, s: float, packed: np.ndarray,
                           z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ground_cells with numpy (obviously correct; for the tests)."""
    p = np.asarray(means, np.float64)
    cand = np.flatnonzero(np.all((p[:, :2] >= lo) & (p[:, :2] < hi), axis=1))
    pk = _pack(np.floor(p[cand, :2] / s).astype(np.int64))
    i = np.minimum(np.searchsorted(packed, pk), len(packed) - 1)
    hit = packed[i] == pk
    cand, j = cand[hit], i[hit]
    ground = np.abs(p[cand, 2] - z[j]) <= GROUND_TOL_M
    return cand[ground], j[ground]


def ground_cells(means: np.ndarray, lo: np.ndarray, hi: np.ndarray, s: float, packed: np.ndarray, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(the static Gaussians on the ground of a lattice cell [M] int64 ascending, that cell [M] int64) of ``means``
    ([N, 3] float32 metres, scene frame): those within [lo, hi) ([2] metres, x y), whose lattice cell (floor(x / s),
    floor(y / s); ``s`` metres) is one of ``packed`` ([L] int64 ascending: _pack'ed cells), within GROUND_TOL_M of
    that cell's ground height ``z`` ([L] metres). One pass over the Gaussians (a drive's ~9 M: the numpy of
    ground_cells_reference made seven arrays of them, 0.7 s warm, 2.4 s cold, the most of fill_under)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    at = _ground_kernel(np.ascontiguousarray(means, np.float32), float(lo[0]), float(lo[1]), float(hi[0]),
                        float(hi[1]), float(s), np.ascontiguousarray(packed, np.int64),
                        np.ascontiguousarray(z, np.float64), float(GROUND_TOL_M))
    cand = np.flatnonzero(at >= 0)
    return cand, at[cand].astype(np.int64)


@njit(cache=True, parallel=True, nogil=True)
def _ground_kernel(means, lo_x, lo_y, hi_x, hi_y, s, packed, z, tol):
    """[N] int32: the lattice cell (row of ``packed``) whose ground each Gaussian lies on, or -1 (ground_cells;
    the same float64 arithmetic as ground_cells_reference, so the same cells)."""
    n, m = means.shape[0], packed.shape[0]
    out = np.full(n, -1, np.int32)
    for k in numba.prange(n):
        x, y = np.float64(means[k, 0]), np.float64(means[k, 1])
        if not (x >= lo_x and y >= lo_y and x < hi_x and y < hi_y):
            continue
        kx, ky = np.int64(np.floor(x / s)), np.int64(np.floor(y / s))
        pk = kx * (np.int64(1) << 32) + (ky & np.int64(0xFFFFFFFF))
        i = min(np.searchsorted(packed, pk), m - 1)
        if packed[i] == pk and abs(np.float64(means[k, 2]) - z[i]) <= tol:
            out[k] = i
    return out


__all__ = ["FILL_SPACING_M", "FillLattice", "fill_lattice", "fill_lattice_under", "fill_under", "ground_cells", "ground_cells_reference"]
