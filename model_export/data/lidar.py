"""A simulated spinning LiDAR for synthetic scenes: exact first hits of a ring of beams (trace.closest_hit).

The pattern (`spin_directions`): BEAMS beams at evenly spaced elevations from ELEV_MIN_DEG to ELEV_MAX_DEG (a
64-beam roof LiDAR like PandaSet's Pandar64, whose beams span -25..+15 deg; its uneven spacing is not copied),
one column every AZIMUTH_STEP_DEG of a full turn. The sweep is instantaneous (every beam at the frame's time: no
rolling shutter over the 0.1 s turn), so its points are exact ground truth for that frame.
"""

from __future__ import annotations

import numpy as np
from numba import prange
from xyzcyl.runtime.numba_cache import njit

from .scene import Scene
from .trace import NO_HIT, Grid, _semantic, closest_hit

BEAMS = 64
ELEV_MIN_DEG, ELEV_MAX_DEG = -25.0, 15.0
AZIMUTH_STEP_DEG = 0.2      # 1800 columns a turn: 115 200 beams
MAX_RANGE_M = 200.0         # returns beyond are dropped (a Pandar64 reaches ~200 m)
MOUNT = (1.0, 0.0, 2.0)     # metres, ego frame: on the roof, above the tallest ego body (an SUV's 1.85 m)


def spin_directions(beams: int = BEAMS, elev_min_deg: float = ELEV_MIN_DEG, elev_max_deg: float = ELEV_MAX_DEG,
                    azimuth_step_deg: float = AZIMUTH_STEP_DEG) -> np.ndarray:
    """[A * beams, 3] unit directions in the LiDAR's (= the ego's) axes, column by column (azimuth 0 = +x, counter-
    clockwise), each column bottom beam first."""
    elev = np.radians(np.linspace(elev_min_deg, elev_max_deg, beams))
    az = np.radians(np.arange(0.0, 360.0, azimuth_step_deg))
    a, e = np.meshgrid(az, elev, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)
    return np.ascontiguousarray(d.reshape(-1, 3))


@njit(parallel=True, cache=True, nogil=True, error_model="numpy", fastmath=True)
def _trace_kernel(origin, dirs, skip_ego, kind, geo, cls, ego, meta, start, items, zmax, G, t_out, sem_out):
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in prange(dirs.shape[0]):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        t, p, _f = closest_hit(ox, oy, oz, dx, dy, dz, skip_ego, kind, geo, ego, meta, start, items, zmax)
        if p == NO_HIT:
            t_out[i] = np.inf
            sem_out[i] = 0
        else:
            t_out[i] = t
            sem_out[i] = _semantic(p, cls, G, ox + t * dx, oy + t * dy)


def trace_rays(scene: Scene, grid: Grid, origin: np.ndarray, dirs: np.ndarray,
               skip_ego: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays from one origin ([3] metres, the scene's frame) along ``dirs`` ([N, 3], the scene's
    frame): (t [N] float64, the hit at origin + t * dir, inf for none; semantic class [N] uint8, 0 for none)."""
    dirs = np.ascontiguousarray(dirs, np.float64)
    t = np.empty(len(dirs), np.float64)
    sem = np.empty(len(dirs), np.uint8)
    _trace_kernel(np.ascontiguousarray(origin, np.float64), dirs, bool(skip_ego), scene.kind, scene.geo, scene.cls,
                  scene.ego, grid.meta, grid.start, grid.items, grid.zmax, scene.ground, t, sem)
    return t, sem


def lidar_sweep(scene: Scene, grid: Grid, ego_to_world: np.ndarray, mount=MOUNT,
                max_range: float = MAX_RANGE_M) -> np.ndarray:
    """One sweep of the spinning LiDAR at ``mount`` (ego metres) on the ego at ``ego_to_world`` (the scene's
    frame = world), the ego's own body skipped: [N, 4] float32 rows x, y, z (metres, the ego frame), semantic
    class id (docs/data.md "Classes"), for the beams that hit something within ``max_range`` metres."""
    d_ego = spin_directions()
    R = np.asarray(ego_to_world, np.float64)[:3, :3]
    origin = R @ np.asarray(mount, np.float64) + np.asarray(ego_to_world, np.float64)[:3, 3]
    t, sem = trace_rays(scene, grid, origin, d_ego @ R.T)
    ok = np.isfinite(t) & (t <= max_range)
    pts = np.asarray(mount, np.float64) + t[ok, None] * d_ego[ok]   # the ego frame: no world round trip
    return np.concatenate([pts, sem[ok, None].astype(np.float64)], axis=1).astype(np.float32)


__all__ = ["lidar_sweep", "spin_directions", "trace_rays", "MOUNT", "BEAMS", "MAX_RANGE_M"]
