"""Exact occupancy ground truth of a synthetic scene.

Grid: `range_m` = (xmin, ymin, zmin, xmax, ymax, zmax) ego metres, cubic voxels of `voxel` metres; arrays are
indexed [ix, iy, iz] with voxel centre = (xmin, ymin, zmin) + (index + 0.5) * voxel (paper grid:
[-40,-40,-3,40,40,13], 0.4 m -> 200 x 200 x 40).

A voxel is occupied when it overlaps a solid with positive volume (touching faces do not count). The tests are
exact: box vs voxel by the separating-axis theorem (both have vertical axes, so z overlap + 2D SAT on the four
edge normals), vertical cylinder vs voxel by z overlap + circle-rectangle distance, ellipsoid vs voxel by the
exact minimum of the ellipsoid's quadratic form over the voxel (z decouples; the xy minimum over the rectangle is
the centre if inside, else the minimum over its four edges, each a clamped 1D quadratic). The ground is the
solid slab -GROUND_THICKNESS <= z <= 0 everywhere; its voxels get the ground class (road / terrain) at the voxel
centre. A voxel touched by several solids takes the class of highest `classes.PRIORITY`.

BEV map: for each (ix, iy) column the class of its highest occupied voxel (0 if none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from xyzcyl.runtime.numba_cache import njit

from . import classes as C
from .scene import BOX, CYL, GROUND_THICKNESS, Scene
from .trace import ground_class

PAPER_RANGE = (-40.0, -40.0, -3.0, 40.0, 40.0, 13.0)


@dataclass(frozen=True)
class OccupancyGrid:
    """Grid geometry: range (xmin, ymin, zmin, xmax, ymax, zmax) metres, voxel edge metres."""

    range_m: tuple[float, float, float, float, float, float] = PAPER_RANGE
    voxel: float = 0.4

    @property
    def shape(self) -> tuple[int, int, int]:
        r, v = self.range_m, self.voxel
        return tuple(int(round((r[i + 3] - r[i]) / v)) for i in range(3))  # type: ignore[return-value]

    @property
    def tag(self) -> str:
        """Key suffix in occupancy.npz, e.g. '0p4' for 0.4 m."""
        return f"{self.voxel:g}".replace(".", "p")

    def __post_init__(self):
        if not self.voxel > 0:
            raise ValueError(f"voxel: must be > 0, got {self.voxel}")
        for i, n in enumerate(self.shape):
            if abs(n * self.voxel - (self.range_m[i + 3] - self.range_m[i])) > 1e-6:
                raise ValueError(f"voxel: {self.voxel} does not divide the range along axis {'xyz'[i]}")


def occupancy(scene: Scene, grid: OccupancyGrid = OccupancyGrid()) -> np.ndarray:
    """Semantic occupancy [X, Y, Z] uint8 (0 = free, else class id of classes.py). Binary = result > 0."""
    sem = np.zeros(grid.shape, np.uint8)
    _voxelize(scene.kind, scene.geo, scene.cls, scene.ground, np.asarray(grid.range_m, np.float64),
              float(grid.voxel), float(GROUND_THICKNESS), C.PRIORITY, sem)
    return sem


def bev(sem: np.ndarray) -> np.ndarray:
    """[X, Y] uint8: class of the highest occupied voxel of each column (0 if the column is empty)."""
    occ = sem > 0
    z = sem.shape[2] - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    top = np.take_along_axis(sem, z[..., None], axis=2)[..., 0]
    return np.where(occ.any(axis=2), top, 0).astype(np.uint8)


@njit(cache=True, error_model="numpy")
def box_overlaps(geo_p, vx, vy, vz, h):
    """Yaw-rotated box (geo row) vs axis-aligned cube (centre v, half edge h): positive-volume overlap."""
    cx, cy, cz, hx, hy, hz, c, s = geo_p[0], geo_p[1], geo_p[2], geo_p[3], geo_p[4], geo_p[5], geo_p[6], geo_p[7]
    if abs(vz - cz) >= hz + h:
        return False
    dx, dy = vx - cx, vy - cy
    ac, as_ = abs(c), abs(s)
    # world x and y axes
    if abs(dx) >= hx * ac + hy * as_ + h:
        return False
    if abs(dy) >= hx * as_ + hy * ac + h:
        return False
    # box local axes (c, s) and (-s, c)
    if abs(dx * c + dy * s) >= hx + h * (ac + as_):
        return False
    if abs(-dx * s + dy * c) >= hy + h * (ac + as_):
        return False
    return True


@njit(cache=True, error_model="numpy")
def cylinder_overlaps(geo_p, vx, vy, vz, h):
    cx, cy, cz, r, hz = geo_p[0], geo_p[1], geo_p[2], geo_p[3], geo_p[5]
    if abs(vz - cz) >= hz + h:
        return False
    qx = min(max(cx, vx - h), vx + h)
    qy = min(max(cy, vy - h), vy + h)
    return (qx - cx) ** 2 + (qy - cy) ** 2 < r * r


@njit(cache=True, error_model="numpy")
def _q(dx, dy, c, s, a2, b2):
    lx = dx * c + dy * s
    ly = -dx * s + dy * c
    return lx * lx / a2 + ly * ly / b2


@njit(cache=True, error_model="numpy")
def ellipsoid_overlaps(geo_p, vx, vy, vz, h):
    """min over the cube of the ellipsoid form ((R^T(p-c))/r)^2 < 1, computed exactly."""
    cx, cy, cz, a, b, cc, c, s = geo_p[0], geo_p[1], geo_p[2], geo_p[3], geo_p[4], geo_p[5], geo_p[6], geo_p[7]
    zq = min(max(cz, vz - h), vz + h) - cz
    qz = zq * zq / (cc * cc)
    if qz >= 1.0:
        return False
    x0, x1, y0, y1 = vx - h - cx, vx + h - cx, vy - h - cy, vy + h - cy
    if x0 <= 0.0 <= x1 and y0 <= 0.0 <= y1:
        return True
    a2, b2 = a * a, b * b
    # minimiser along a vertical edge (dx fixed): dy* = -dx * cs (1/a2 - 1/b2) / (s^2/a2 + c^2/b2)
    ky = c * s * (1.0 / a2 - 1.0 / b2) / (s * s / a2 + c * c / b2)
    kx = c * s * (1.0 / a2 - 1.0 / b2) / (c * c / a2 + s * s / b2)
    best = 1e300
    for dx in (x0, x1):
        dy = min(max(-dx * ky, y0), y1)
        best = min(best, _q(dx, dy, c, s, a2, b2))
    for dy in (y0, y1):
        dx = min(max(-dy * kx, x0), x1)
        best = min(best, _q(dx, dy, c, s, a2, b2))
    return best + qz < 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def _voxelize(kind, geo, cls, G, rng, v, thick, prio, sem):
    X, Y, Z = sem.shape
    h = 0.5 * v
    # ground slab
    k0 = max(0, int(math.floor((-thick - rng[2]) / v)))
    for i in range(X):
        x = rng[0] + (i + 0.5) * v
        for j in range(Y):
            y = rng[1] + (j + 0.5) * v
            gc = ground_class(x, y, G)
            for k in range(k0, Z):
                z0 = rng[2] + k * v
                if z0 >= 0.0:
                    break
                if z0 + v > -thick:
                    sem[i, j, k] = gc
    for p in range(kind.shape[0]):
        cx, cy, cz = geo[p, 0], geo[p, 1], geo[p, 2]
        hx, hy, hz = geo[p, 3], geo[p, 4], geo[p, 5]
        c, s = abs(geo[p, 6]), abs(geo[p, 7])
        if kind[p] == BOX:
            ex, ey = hx * c + hy * s, hx * s + hy * c
        elif kind[p] == CYL:
            ex, ey = hx, hx
        else:
            ex, ey = math.sqrt((hx * c) ** 2 + (hy * s) ** 2), math.sqrt((hx * s) ** 2 + (hy * c) ** 2)
        i0 = max(0, int(math.floor((cx - ex - rng[0]) / v)))
        i1 = min(X - 1, int(math.floor((cx + ex - rng[0]) / v)))
        j0 = max(0, int(math.floor((cy - ey - rng[1]) / v)))
        j1 = min(Y - 1, int(math.floor((cy + ey - rng[1]) / v)))
        k0 = max(0, int(math.floor((cz - hz - rng[2]) / v)))
        k1 = min(Z - 1, int(math.floor((cz + hz - rng[2]) / v)))
        cl = cls[p]
        for i in range(i0, i1 + 1):
            vx = rng[0] + (i + 0.5) * v
            for j in range(j0, j1 + 1):
                vy = rng[1] + (j + 0.5) * v
                for k in range(k0, k1 + 1):
                    if prio[sem[i, j, k]] >= prio[cl]:
                        continue
                    vz = rng[2] + (k + 0.5) * v
                    if kind[p] == BOX:
                        hit = box_overlaps(geo[p], vx, vy, vz, h)
                    elif kind[p] == CYL:
                        hit = cylinder_overlaps(geo[p], vx, vy, vz, h)
                    else:
                        hit = ellipsoid_overlaps(geo[p], vx, vy, vz, h)
                    if hit:
                        sem[i, j, k] = cl


# --------------------------------------------------------------------------------------------------------------
# slow references (numpy) for the tests


def signed_distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """[N, P] signed distance (metres; < 0 inside) of each point to each primitive, in numpy.

    Exact for boxes and cylinders. For ellipsoids a lower bound of |distance| outside ((s - 1) * r_min with
    s = |p/r|, since E + B(d) is inside (1 + d/r_min) E) and an upper-bound-free negative value inside.
    """
    p = np.asarray(points, np.float64)[:, None, :]
    g = scene.geo[None]
    r = p - g[..., :3]
    c, s = g[..., 6], g[..., 7]
    lx = r[..., 0] * c + r[..., 1] * s
    ly = -r[..., 0] * s + r[..., 1] * c
    lz = r[..., 2]
    h = g[..., 3:6]
    q = np.stack([np.abs(lx), np.abs(ly), np.abs(lz)], -1) - h
    d_box = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)
    rad = np.hypot(r[..., 0], r[..., 1]) - h[..., 0]
    qz = np.abs(lz) - h[..., 2]
    d_cyl = np.hypot(np.maximum(rad, 0), np.maximum(qz, 0)) + np.minimum(np.maximum(rad, qz), 0)
    sc = np.sqrt((lx / h[..., 0]) ** 2 + (ly / h[..., 1]) ** 2 + (lz / h[..., 2]) ** 2)
    d_ell = (sc - 1.0) * h.min(-1)
    k = scene.kind[None]
    return np.where(k == BOX, d_box, np.where(k == CYL, d_cyl, d_ell))


def inside_any(scene: Scene, points: np.ndarray) -> np.ndarray:
    """[N] class id of the highest-priority solid containing each point (0 if none); ground slab included."""
    d = signed_distance(scene, points)
    inside = d < 0
    pr = np.where(inside, C.PRIORITY[scene.cls][None], -1)
    best = np.argmax(pr, axis=1)
    out = np.where(inside.any(1), scene.cls[best], 0)
    pts = np.asarray(points)
    ground = (pts[:, 2] < 0) & (pts[:, 2] > -GROUND_THICKNESS)
    gcls = np.array([ground_class(x, y, scene.ground) for x, y in pts[:, :2]]) if len(pts) else np.zeros(0)
    out = np.where((out == 0) & ground, gcls, out)
    return out.astype(np.uint8)
