"""Analytic ray tracer for synthetic scenes (numba, parallel over image rows).

Exact ray-primitive intersection (ground plane z = 0, yaw-rotated boxes, vertical circular cylinders,
yaw-rotated ellipsoids) accelerated by a uniform 2D grid over the ground plane (cells list the primitives whose
xy bounds overlap them; each cell also stores the top z of its primitives so rays passing above are skipped).
Shading: procedural textures at the hit point, Lambertian sun + ambient sky light, hard sun shadows (one shadow
ray per shaded sample), distance haze, a procedural sky (gradient, sun, value-noise clouds).

Per pinhole view: RGB uint8 from ss x ss supersamples at pixel offsets ((i + 0.5)/ss - 0.5); depth (float32
metres along the optical axis) and semantic class from one extra geometry-only ray through the exact pixel
centre, so `p = cam_to_ego @ [depth * inv(K) @ [u, v, 1], 1]` lies on the surface. Sky pixels: depth 0, class 0.
A camera with a lens casts each sample's true ray (Camera.depth_rays, computed in numpy and passed to the kernel):
`p = cam_to_ego @ [depth * depth_rays(uv), 1]`, depth the camera's (distance for a fisheye or f-theta lens).

The slow, obviously-correct reference (`reference_closest_hit`) intersects rays with every primitive in numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.numba_cache import njit

from . import classes as C
from .photos import NO_PHOTOS, photo_bank
from .scene import (
    BOX,
    CYL,
    ELL,
    G_ASPH,
    G_COS,
    G_CSTYLE,
    G_DASH,
    G_HASX,
    G_LANEW,
    G_MARKCOL,
    G_NFWD,
    G_NLANES,
    G_PHOTO,
    G_PHOTO_L,
    G_PHOTO_TILE,
    G_SEED,
    G_SIN,
    G_TERR,
    G_UX,
    G_VD0,
    G_VL,
    G_VR,
    G_WX,
    G_XWALK,
    S_AMB,
    S_CLOUD,
    S_COFF,
    S_CSCALE,
    S_FOG,
    S_HORIZON,
    S_SUNCOL,
    S_SUNDIR,
    S_ZENITH,
    T_BARK,
    T_CARBODY,
    T_FACADE,
    T_FENCE,
    T_FOLIAGE,
    T_GLASS,
    T_PHOTO,
    T_SIDEWALK,
    T_SIGN,
    T_TLIGHT,
    Scene,
    primitive_bounds,
)

BIG = 1e30
NO_HIT = -1
GROUND = -2
EXPOSURE = 1.7  # surface tone curve c -> 1 - exp(-EXPOSURE c)
T_EPS = 1e-7  # metres (times |d|): hits closer than this to the ray origin are ignored


@dataclass(frozen=True, eq=False)
class Grid:
    """Uniform 2D grid over the ground plane (CSR primitive lists)."""

    meta: np.ndarray  # [6] float64: x0, y0, cell size (m), nx, ny, global top z (m)
    start: np.ndarray  # [nx*ny+1] int32 offsets into items
    items: np.ndarray  # [M] int32 primitive ids
    zmax: np.ndarray  # [nx*ny] float64 top z of the primitives listed in each cell (-BIG if empty)


def build_grid(scene: Scene, cell: float = 2.0) -> Grid:
    """Bin the scene's primitives into square cells of `cell` metres."""
    bb = primitive_bounds(scene.kind, scene.geo)
    x0, y0 = math.floor(bb[:, 0].min()) - 1.0, math.floor(bb[:, 1].min()) - 1.0
    nx = int(math.ceil((bb[:, 3].max() + 1.0 - x0) / cell))
    ny = int(math.ceil((bb[:, 4].max() + 1.0 - y0) / cell))
    start, items, zmax = _bin(bb, x0, y0, cell, nx, ny)
    meta = np.array([x0, y0, cell, nx, ny, bb[:, 5].max()], np.float64)
    return Grid(meta, start, items, zmax)


@njit(cache=True, error_model="numpy", fastmath=True)
def _cells(bb, p, x0, y0, cs, nx, ny):
    """Inclusive cell index ranges (i0, i1, j0, j1) covered by primitive p's xy bounds."""
    i0 = max(0, int(math.floor((bb[p, 0] - x0) / cs)))
    i1 = min(nx - 1, int(math.floor((bb[p, 3] - x0) / cs)))
    j0 = max(0, int(math.floor((bb[p, 1] - y0) / cs)))
    j1 = min(ny - 1, int(math.floor((bb[p, 4] - y0) / cs)))
    return i0, i1, j0, j1


@njit(cache=True, error_model="numpy", fastmath=True)
def _bin(bb, x0, y0, cs, nx, ny):
    P = bb.shape[0]
    counts = np.zeros(nx * ny + 1, np.int32)
    for p in range(P):
        i0, i1, j0, j1 = _cells(bb, p, x0, y0, cs, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                counts[i * ny + j + 1] += 1
    start = np.cumsum(counts).astype(np.int32)
    fill = start[:-1].copy()
    items = np.zeros(start[-1], np.int32)
    zmax = np.full(nx * ny, -BIG)
    for p in range(P):
        i0, i1, j0, j1 = _cells(bb, p, x0, y0, cs, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                c = i * ny + j
                items[fill[c]] = p
                fill[c] += 1
                if bb[p, 5] > zmax[c]:
                    zmax[c] = bb[p, 5]
    return start, items, zmax


# --------------------------------------------------------------------------------------------------------------
# intersection


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _slab(lo, ld, h, tn, tf, face, face0):
    """Clip the ray's [tn, tf] to the slab |lo + t ld| <= h; the entry face is face0 (-side) or face0 + 1.
    Returns (tn, tf, face, miss)."""
    if ld != 0.0:
        t1 = (-h - lo) / ld
        t2 = (h - lo) / ld
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > tn:
            tn = t1
            face = face0 if ld > 0.0 else face0 + 1
        return tn, min(tf, t2), face, False
    return tn, tf, face, abs(lo) > h


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _hit_prim(p, kind, geo, ox, oy, oz, dx, dy, dz, tmax):
    """(t, face) of the first entry of the ray into primitive p with T_EPS < t < tmax, else (BIG, -1).

    Faces: box 0..5 = local -x,+x,-y,+y,-z,+z; cylinder 0 side, 1 top, 2 bottom; ellipsoid 0.
    Rays starting inside a solid do not hit it (cameras are placed outside all solids).
    """
    cx, cy, cz = geo[p, 0], geo[p, 1], geo[p, 2]
    hx, hy, hz = geo[p, 3], geo[p, 4], geo[p, 5]
    c, s = geo[p, 6], geo[p, 7]
    rx, ry, rz = ox - cx, oy - cy, oz - cz
    k = kind[p]
    if k == CYL:
        a = dx * dx + dy * dy
        best = BIG
        face = -1
        if a > 0.0:
            bq = rx * dx + ry * dy
            cq = rx * rx + ry * ry - hx * hx
            disc = bq * bq - a * cq
            if disc >= 0.0:
                t = (-bq - math.sqrt(disc)) / a
                if T_EPS < t < tmax:
                    z = rz + t * dz
                    if -hz <= z <= hz:
                        best = t
                        face = 0
        if dz != 0.0:
            for f in range(2):
                zc = hz if f == 0 else -hz
                t = (zc - rz) / dz
                if T_EPS < t < min(best, tmax):
                    x = rx + t * dx
                    y = ry + t * dy
                    if x * x + y * y <= hx * hx:
                        best = t
                        face = 1 + f
        return best, face
    lx = rx * c + ry * s
    ly = -rx * s + ry * c
    ldx = dx * c + dy * s
    ldy = -dx * s + dy * c
    if k == BOX:
        tn, tf, face, miss = _slab(lx, ldx, hx, -BIG, BIG, -1, 0)
        if not miss:
            tn, tf, face, miss = _slab(ly, ldy, hy, tn, tf, face, 2)
        if not miss:
            tn, tf, face, miss = _slab(rz, dz, hz, tn, tf, face, 4)
        if miss:
            return BIG, -1
        if tn <= tf and T_EPS < tn < tmax:
            return tn, face
        return BIG, -1
    # ellipsoid
    ex, ey, ez = lx / hx, ly / hy, rz / hz
    edx, edy, edz = ldx / hx, ldy / hy, dz / hz
    a = edx * edx + edy * edy + edz * edz
    bq = ex * edx + ey * edy + ez * edz
    cq = ex * ex + ey * ey + ez * ez - 1.0
    if cq <= 0.0:
        return BIG, -1
    disc = bq * bq - a * cq
    if disc < 0.0:
        return BIG, -1
    t = (-bq - math.sqrt(disc)) / a
    if T_EPS < t < tmax:
        return t, 0
    return BIG, -1


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _dda_axis(o, d, lo, i, cs):
    """Grid walk along one axis from cell i: (step, t of the next cell boundary, t per cell)."""
    if d > 0.0:
        return 1, (lo + (i + 1) * cs - o) / d, cs / d
    if d < 0.0:
        return -1, (lo + i * cs - o) / d, -cs / d
    return 0, BIG, BIG


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def trace(ox, oy, oz, dx, dy, dz, tmax, any_hit, skip_ego, kind, geo, ego, meta, start, items, zmax):
    """Closest (or any, if any_hit) hit with t < tmax among the primitives: (t, prim, face); (BIG, -1, -1)."""
    x0, y0, cs = meta[0], meta[1], meta[2]
    nx, ny = int(meta[3]), int(meta[4])
    ztop = meta[5]
    x1, y1 = x0 + nx * cs, y0 + ny * cs
    # clip the ray to the grid's xy rectangle
    t0, t1, _f, miss = _slab(ox - 0.5 * (x0 + x1), dx, 0.5 * (x1 - x0), 0.0, tmax, -1, 0)
    if not miss:
        t0, t1, _f, miss = _slab(oy - 0.5 * (y0 + y1), dy, 0.5 * (y1 - y0), t0, t1, -1, 0)
    if miss or t0 >= t1:
        return BIG, -1, -1
    px, py = ox + t0 * dx, oy + t0 * dy
    ix = min(nx - 1, max(0, int(math.floor((px - x0) / cs))))
    iy = min(ny - 1, max(0, int(math.floor((py - y0) / cs))))
    sx, tnx, dtx = _dda_axis(ox, dx, x0, ix, cs)
    sy, tny, dty = _dda_axis(oy, dy, y0, iy, cs)
    best, bp, bf = BIG, -1, -1
    t = t0
    while True:
        tout = min(tnx, tny, t1)
        za = oz + t * dz
        zb = oz + tout * dz if tout < BIG else (BIG if dz > 0 else (-BIG if dz < 0 else oz))
        if dz >= 0.0 and za > ztop:
            break
        c = ix * ny + iy
        zlo = min(za, zb)
        if zlo <= zmax[c]:
            zhi = max(za, zb)
            for q in range(start[c], start[c + 1]):
                p = items[q]
                if (skip_ego and ego[p]) or zlo > geo[p, 2] + geo[p, 5] or zhi < geo[p, 2] - geo[p, 5]:
                    continue
                th, f = _hit_prim(p, kind, geo, ox, oy, oz, dx, dy, dz, best)
                if th < best:
                    best, bp, bf = th, p, f
                    if any_hit:
                        return best, bp, bf
        if best <= tout or tout >= t1:
            break
        t = tout
        if tnx < tny:
            ix += sx
            tnx += dtx
            if ix < 0 or ix >= nx:
                break
        else:
            iy += sy
            tny += dty
            if iy < 0 or iy >= ny:
                break
    return best, bp, bf


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def closest_hit(ox, oy, oz, dx, dy, dz, skip_ego, kind, geo, ego, meta, start, items, zmax):
    """Closest hit including the ground plane z = 0: (t, prim or GROUND or NO_HIT, face)."""
    tg = BIG
    if dz < 0.0 and oz > 0.0:
        tg = -oz / dz
    t, p, f = trace(ox, oy, oz, dx, dy, dz, tg, False, skip_ego, kind, geo, ego, meta, start, items, zmax)
    if p >= 0:
        return t, p, f
    if tg < BIG:
        return tg, GROUND, 0
    return BIG, NO_HIT, -1


# --------------------------------------------------------------------------------------------------------------
# procedural textures


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _hash(ix, iy, iz, seed):
    h = (ix * 374761393 + iy * 668265263 + iz * 1440662683 + seed * 2246822519) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h / 4294967296.0


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _smooth(t):
    return t * t * (3.0 - 2.0 * t)


@njit(cache=True, error_model="numpy", fastmath=True)
def _noise2(x, y, seed):
    ix, iy = math.floor(x), math.floor(y)
    fx, fy = _smooth(x - ix), _smooth(y - iy)
    i, j = int(ix), int(iy)
    a = _hash(i, j, 0, seed)
    b = _hash(i + 1, j, 0, seed)
    c = _hash(i, j + 1, 0, seed)
    d = _hash(i + 1, j + 1, 0, seed)
    return (a + (b - a) * fx) + ((c + (d - c) * fx) - (a + (b - a) * fx)) * fy


@njit(cache=True, error_model="numpy", fastmath=True)
def _noise3(x, y, z, seed):
    ix, iy, iz = math.floor(x), math.floor(y), math.floor(z)
    fx, fy, fz = _smooth(x - ix), _smooth(y - iy), _smooth(z - iz)
    i, j, k = int(ix), int(iy), int(iz)
    r0 = 0.0
    r1 = 0.0
    for dk in range(2):
        a = _hash(i, j, k + dk, seed)
        b = _hash(i + 1, j, k + dk, seed)
        c = _hash(i, j + 1, k + dk, seed)
        d = _hash(i + 1, j + 1, k + dk, seed)
        v = (a + (b - a) * fx) + ((c + (d - c) * fx) - (a + (b - a) * fx)) * fy
        if dk == 0:
            r0 = v
        else:
            r1 = v
    return r0 + (r1 - r0) * fz


@njit(cache=True, error_model="numpy", fastmath=True)
def photo_texel(photo, i, s, t, mirror_t):
    """Bilinear RGB of photo tile i (photo [N, H, W, 3]) at tile coordinates s (across) and t (up; t = 0 is
    the tile's bottom row): mirrored repeat across, plain repeat up unless mirror_t (ground tiles)."""
    s = abs(s) % 2.0
    if s > 1.0:
        s = 2.0 - s
    if mirror_t:
        t = abs(t) % 2.0
        if t > 1.0:
            t = 2.0 - t
    else:
        t = t - math.floor(t)
    H, W = photo.shape[1], photo.shape[2]
    x = s * (W - 1)
    y = (1.0 - t) * (H - 1)
    x0 = min(int(x), W - 2)
    y0 = min(int(y), H - 2)
    fx, fy = x - x0, y - y0
    return (_lerp2(photo, i, y0, x0, 0, fx, fy), _lerp2(photo, i, y0, x0, 1, fx, fy),
            _lerp2(photo, i, y0, x0, 2, fx, fy))


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _lerp2(photo, i, y0, x0, c, fx, fy):
    """Bilinear blend of channel c of the 2 x 2 texels at (y0, x0) of tile i (no allocation in the pixel loop)."""
    top = photo[i, y0, x0, c] + (photo[i, y0, x0 + 1, c] - photo[i, y0, x0, c]) * fx
    bot = photo[i, y0 + 1, x0, c] + (photo[i, y0 + 1, x0 + 1, c] - photo[i, y0 + 1, x0, c]) * fx
    return top + (bot - top) * fy


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _road(x, y, G):
    """(u, v) road-frame coordinates of ego point (x, y), on the main road, on the crossing road."""
    c, s = G[G_COS], G[G_SIN]
    u = c * x + s * y
    v = -s * x + c * y
    return u, v, G[G_VR] <= v <= G[G_VL], G[G_HASX] > 0.5 and abs(u - G[G_UX]) <= G[G_WX]


@njit(cache=True, error_model="numpy", fastmath=True)
def ground_class(x, y, G):
    """Class of the ground at ego point (x, y): ROAD or TERRAIN (ground_albedo's class, without its colour)."""
    _u, _v, on_main, on_cross = _road(x, y, G)
    return C.ROAD if on_main or on_cross else C.TERRAIN


@njit(cache=True, error_model="numpy", fastmath=True)
def ground_albedo(x, y, G, photo):
    """Albedo (r, g, b) and class of the ground at ego point (x, y); road layout in G; photo: the photo bank
    (photo_bank(), used when G names a road tile: G_PHOTO > 0)."""
    u, v, on_main, on_cross = _road(x, y, G)
    seed = int(G[G_SEED])
    if on_main or on_cross:
        if G[G_PHOTO] > 0.5:
            L = G[G_PHOTO_L]
            r, g, b = photo_texel(photo, int(G[G_PHOTO]) - 1, u / G[G_PHOTO_TILE], v / G[G_PHOTO_TILE], True)
            r, g, b = r * L, g * L, b * L
        else:
            n = 0.86 + 0.18 * _noise2(u * 0.7, v * 0.7, seed) + 0.08 * _noise2(u * 5.0, v * 5.0, seed + 1)
            r, g, b = G[G_ASPH] * n, G[G_ASPH + 1] * n, G[G_ASPH + 2] * n
        mark = 0  # 0 none, 1 white, 2 yellow
        if on_main and not on_cross:
            lw = G[G_LANEW]
            kf = (v - G[G_VD0]) / lw
            k = int(math.floor(kf + 0.5))
            if 0 <= k <= int(G[G_NLANES]) and abs(v - (G[G_VD0] + k * lw)) < 0.075:
                if k == 0 or k == int(G[G_NLANES]):
                    mark = 1
                elif k == int(G[G_NFWD]):
                    style = int(G[G_CSTYLE])
                    if style == 0:
                        if (u + G[G_DASH]) / 9.0 - math.floor((u + G[G_DASH]) / 9.0) < 0.35:
                            mark = 1
                    else:
                        mark = 2
                elif (u + G[G_DASH]) / 9.0 - math.floor((u + G[G_DASH]) / 9.0) < 0.33:
                    mark = 1
            if int(G[G_CSTYLE]) == 1 and mark == 0 and int(G[G_NFWD]) > 0:
                vc = G[G_VD0] + G[G_NFWD] * lw  # double yellow: second line
                if abs(v - vc - 0.25) < 0.06:
                    mark = 2
            if G[G_HASX] > 0.5 and G[G_XWALK] > 0.5:
                du = abs(u - G[G_UX]) - G[G_WX]
                if 0.5 < du < 4.0 and (v / 1.1 - math.floor(v / 1.1)) < 0.5:
                    mark = 1
        elif on_cross and not on_main:
            du = u - G[G_UX]
            if abs(du) < 0.075 and (v / 9.0 - math.floor(v / 9.0)) < 0.35:
                mark = 1
            if G[G_XWALK] > 0.5:
                dv = v - G[G_VL] if v > G[G_VL] else G[G_VR] - v
                if 0.5 < dv < 4.0 and (u / 1.1 - math.floor(u / 1.1)) < 0.5:
                    mark = 1
        if mark > 0:
            wear = 0.75 + 0.25 * _noise2(u * 3.0, v * 3.0, seed + 2)
            m = G[G_MARKCOL] * wear
            if mark == 1:
                r, g, b = m, m, m
            else:
                r, g, b = 0.85 * wear, 0.68 * wear, 0.15 * wear
        return r, g, b, C.ROAD
    n = 0.75 + 0.35 * _noise2(u * 0.5, v * 0.5, seed + 3) + 0.12 * _noise2(u * 4.0, v * 4.0, seed + 4)
    return G[G_TERR] * n, G[G_TERR + 1] * n, G[G_TERR + 2] * n, C.TERRAIN


@njit(cache=True, error_model="numpy", fastmath=True)
def _sky(dx, dy, dz, S):
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / n, dy / n, dz / n
    h = max(dz, 0.0)
    w = math.sqrt(h)
    r = S[S_HORIZON] + (S[S_ZENITH] - S[S_HORIZON]) * w
    g = S[S_HORIZON + 1] + (S[S_ZENITH + 1] - S[S_HORIZON + 1]) * w
    b = S[S_HORIZON + 2] + (S[S_ZENITH + 2] - S[S_HORIZON + 2]) * w
    cos_sun = dx * S[S_SUNDIR] + dy * S[S_SUNDIR + 1] + dz * S[S_SUNDIR + 2]
    if cos_sun > 0.0:
        glow = 0.35 * cos_sun ** 16 + (1.5 if cos_sun > 0.99965 else 0.0)
        r += glow * S[S_SUNCOL]
        g += glow * S[S_SUNCOL + 1]
        b += glow * S[S_SUNCOL + 2]
    cover = S[S_CLOUD]
    if cover > 0.0 and dz > 0.02:
        sc = S[S_CSCALE]
        px = dx / dz * sc + S[S_COFF]
        py = dy / dz * sc + S[S_COFF + 1]
        f = 0.5 * _noise2(px, py, 11) + 0.3 * _noise2(px * 2.3, py * 2.3, 12) + 0.2 * _noise2(px * 5.1, py * 5.1, 13)
        a = (f - (1.0 - cover)) / 0.25
        if a > 0.0:
            a = min(a, 1.0) * min(1.0, (dz - 0.02) * 8.0)
            shade = 0.95 - 0.25 * f
            r += (shade - r) * a
            g += (shade - g) * a
            b += (shade * 1.02 - b) * a
    return r, g, b


@njit(cache=True, error_model="numpy", fastmath=True)
def _material(p, face, px, py, pz, kind, geo, tex, col, col2, par, photo):
    """(albedo rgb, emission rgb, normal xyz) of primitive p at ego point (px, py, pz); photo: the photo bank
    (T_PHOTO, photo sidewalks)."""
    cx, cy, cz = geo[p, 0], geo[p, 1], geo[p, 2]
    hx, hy, hz = geo[p, 3], geo[p, 4], geo[p, 5]
    c, s = geo[p, 6], geo[p, 7]
    rx, ry, rz = px - cx, py - cy, pz - cz
    lx = rx * c + ry * s
    ly = -rx * s + ry * c
    k = kind[p]
    # normal
    if k == BOX:
        sg = -1.0 if face % 2 == 0 else 1.0
        ax = face // 2
        if ax == 0:
            nx, ny, nz = c * sg, s * sg, 0.0
        elif ax == 1:
            nx, ny, nz = -s * sg, c * sg, 0.0
        else:
            nx, ny, nz = 0.0, 0.0, sg
    elif k == CYL:
        if face == 0:
            rr = math.sqrt(rx * rx + ry * ry) + 1e-12
            nx, ny, nz = rx / rr, ry / rr, 0.0
        elif face == 1:
            nx, ny, nz = 0.0, 0.0, 1.0
        else:
            nx, ny, nz = 0.0, 0.0, -1.0
    else:
        gx, gy, gz = lx / (hx * hx), ly / (hy * hy), rz / (hz * hz)
        wx_ = gx * c - gy * s
        wy_ = gx * s + gy * c
        nn = math.sqrt(wx_ * wx_ + wy_ * wy_ + gz * gz) + 1e-12
        nx, ny, nz = wx_ / nn, wy_ / nn, gz / nn
    r, g, b = col[p, 0], col[p, 1], col[p, 2]
    er, eg, eb = 0.0, 0.0, 0.0
    t = tex[p]
    if t == T_PHOTO and face < 4:
        along = ly + hy if face < 2 else lx + hx
        L = par[p, 3]
        r, g, b = photo_texel(photo, int(par[p, 0]), along / par[p, 1], (pz - (cz - hz)) / par[p, 2], False)
        r, g, b = r * L, g * L, b * L
    elif t == T_FACADE or t == T_PHOTO:
        if face < 4:
            along = ly + hy if face < 2 else lx + hx
            width = 2.0 * (hy if face < 2 else hx)
            zr = pz - (cz - hz)
            sh, pitch, wf, hf = par[p, 0], par[p, 1], par[p, 2], par[p, 3]
            seed = int(par[p, 5])
            st = math.floor(zr / sh)
            fz = zr / sh - st
            ci = math.floor(along / pitch)
            fs = along / pitch - ci
            n = 0.9 + 0.16 * _noise2(along * 0.6, zr * 0.6, seed)
            r, g, b = r * n, g * n, b * n
            top_storey = math.floor((2.0 * hz - 0.6) / sh)
            win = False
            if 0.5 < along < width - 0.5 and st < top_storey:
                if st == 0 and par[p, 4] > 0.5:
                    win = 0.06 < fs < 0.94 and 0.06 < fz < 0.8
                else:
                    win = abs(fs - 0.5) < wf * 0.5 and 0.28 < fz < 0.28 + hf
                if win:
                    hsh = _hash(int(ci), int(st), face, seed)
                    q = 0.55 + 0.8 * hsh
                    r, g, b = col2[p, 0] * q, col2[p, 1] * q, col2[p, 2] * q
                    if hsh > 0.95:
                        er, eg, eb = 0.35, 0.3, 0.18
                elif (abs(fs - 0.5) < wf * 0.5 + 0.05 / pitch and 0.28 - 0.05 / sh < fz < 0.28 + hf + 0.05 / sh
                      and not (st == 0 and par[p, 4] > 0.5)):
                    r, g, b = 0.85, 0.85, 0.82
            if fz < 0.04 and st > 0:
                r, g, b = r * 0.75, g * 0.75, b * 0.75
        else:
            m = 0.45 + 0.1 * _noise2(lx * 0.5, ly * 0.5, 5)
            r, g, b = m, m * 0.98, m * 0.95
    elif t == T_SIDEWALK:
        if face == 5 and par[p, 1] > 0.5:
            L = par[p, 3]
            r, g, b = photo_texel(photo, int(par[p, 1]) - 1, lx / par[p, 2], ly / par[p, 2], True)
            r, g, b = r * L, g * L, b * L
        elif face == 5:
            tl = par[p, 0]
            fu = (px * 0.0 + lx) / tl
            fv = ly / tl
            n = 0.92 + 0.12 * _noise2(lx * 1.5, ly * 1.5, 7)
            if fu - math.floor(fu) < 0.05 or fv - math.floor(fv) < 0.05:
                n *= 0.8
            r, g, b = r * n, g * n, b * n
        else:
            r, g, b = col2[p, 0], col2[p, 1], col2[p, 2]
    elif t == T_FOLIAGE:
        n = 0.5 + 0.55 * _noise3(px * 1.7, py * 1.7, pz * 1.7, 21) + 0.3 * _noise3(px * 5.0, py * 5.0, pz * 5.0, 22)
        r, g, b = r * n, g * n, b * n
    elif t == T_BARK:
        n = 0.75 + 0.4 * _noise2(math.atan2(ry, rx) * 3.0, pz * 4.0, 23)
        r, g, b = r * n, g * n, b * n
    elif t == T_GLASS:
        if nz > 0.8:  # roof in the body colour (col2)
            r, g, b = col2[p, 0], col2[p, 1], col2[p, 2]
        else:  # fake reflection: upward-facing glass shows more sky
            q = 0.6 + 0.6 * max(nz, 0.0)
            r, g, b = r * q, g * q, b * q
    elif t == T_CARBODY:
        if face < 2:
            zr = rz / hz
            if abs(ly) > hy - 0.42 and 0.1 < zr < 0.6:
                if face == 1:
                    er, eg, eb = 0.5, 0.5, 0.45
                    r, g, b = 0.9, 0.9, 0.85
                else:
                    er, eg, eb = 0.35, 0.02, 0.02
                    r, g, b = 0.7, 0.05, 0.05
            elif zr < -0.55:
                r, g, b = 0.08, 0.08, 0.08
        elif face < 4 and rz < -hz + 0.12:
            r, g, b = 0.08, 0.08, 0.08
    elif t == T_TLIGHT:
        if face < 2:
            zr = (rz + hz) / (2.0 * hz)
            slot = int(zr * 3.0)
            dz_ = zr * 3.0 - slot - 0.5
            if dz_ * dz_ * (2.0 * hz / 3.0) ** 2 + ly * ly < 0.11 * 0.11:
                lit = int(par[p, 0]) == (2 - slot)
                if slot == 2:
                    cr, cg, cb = 1.0, 0.1, 0.05
                elif slot == 1:
                    cr, cg, cb = 1.0, 0.75, 0.05
                else:
                    cr, cg, cb = 0.1, 1.0, 0.3
                if lit:
                    er, eg, eb = cr * 0.9, cg * 0.9, cb * 0.9
                r, g, b = cr * 0.25, cg * 0.25, cb * 0.25
    elif t == T_SIGN:
        if face < 2:
            e = max(abs(ly) / hy, abs(rz) / hz)
            if e > 0.82:
                r, g, b = col2[p, 0], col2[p, 1], col2[p, 2]
            elif abs(rz) / hz < 0.18 and abs(ly) / hy < 0.55:
                r, g, b = col2[p, 0], col2[p, 1], col2[p, 2]
        else:
            r, g, b = 0.5, 0.5, 0.52
    elif t == T_FENCE:
        along = lx + hx
        zr = pz - (cz - hz)
        bar = par[p, 0]
        if along / bar - math.floor(along / bar) > 0.45 and zr < 2.0 * hz - 0.12:
            r, g, b = r * 0.55, g * 0.55, b * 0.55
    return r, g, b, er, eg, eb, nx, ny, nz


@njit(cache=True, inline="always", error_model="numpy", fastmath=True)
def _shade(ox, oy, oz, dx, dy, dz, t, p, face, skip_ego, shadows, vis_given, kind, geo, cls, tex, col, col2, par, ego,
           meta, start, items, zmax, G, S, photo):
    if p == NO_HIT:
        r, g, b = _sky(dx, dy, dz, S)
        return r, g, b, 1.0
    px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
    if p == GROUND:
        r, g, b, _c = ground_albedo(px, py, G, photo)
        er, eg, eb = 0.0, 0.0, 0.0
        nx, ny, nz = 0.0, 0.0, 1.0
        pz = 0.0
    else:
        r, g, b, er, eg, eb, nx, ny, nz = _material(p, face, px, py, pz, kind, geo, tex, col, col2, par, photo)
    lx, ly, lz = S[S_SUNDIR], S[S_SUNDIR + 1], S[S_SUNDIR + 2]
    ndl = nx * lx + ny * ly + nz * lz
    vis = 0.0
    if ndl > 0.0:
        vis = 1.0
        if vis_given >= 0.0:
            vis = vis_given
        elif shadows:
            eps = 2e-3
            ts, ps, _f = trace(px + nx * eps, py + ny * eps, pz + nz * eps, lx, ly, lz, BIG, True, skip_ego,
                               kind, geo, ego, meta, start, items, zmax)
            if ps >= 0:
                vis = 0.0
    amb = 0.8 + 0.2 * nz
    sr = r * (S[S_AMB] * amb + S[S_SUNCOL] * ndl * vis) + er
    sg = g * (S[S_AMB + 1] * amb + S[S_SUNCOL + 1] * ndl * vis) + eg
    sb = b * (S[S_AMB + 2] * amb + S[S_SUNCOL + 2] * ndl * vis) + eb
    # exposure / tone curve for lit surfaces (lifts shade, compresses highlights); the sky is shown as is
    sr = 1.0 - math.exp(-EXPOSURE * sr)
    sg = 1.0 - math.exp(-EXPOSURE * sg)
    sb = 1.0 - math.exp(-EXPOSURE * sb)
    dist = t * math.sqrt(dx * dx + dy * dy + dz * dz)
    f = math.exp(-dist / S[S_FOG])
    hr, hg, hb = S[S_HORIZON], S[S_HORIZON + 1], S[S_HORIZON + 2]
    return sr * f + hr * (1.0 - f), sg * f + hg * (1.0 - f), sb * f + hb * (1.0 - f), vis


@njit(cache=True, error_model="numpy", fastmath=True)
def _semantic(p, cls, G, px, py):
    if p == NO_HIT:
        return C.SKY
    if p == GROUND:
        return ground_class(px, py, G)
    return cls[p]


@njit(parallel=True, cache=True, nogil=True, error_model="numpy", fastmath=True)
def render_kernel(fx, fy, cx, cy, Rm, T, H, W, ss, skip_ego, shadows, kind, geo, cls, tex, col, col2, par, ego,
                  meta, start, items, zmax, G, S, photo, rays, has_ray, rgb, depth, sem):
    """Render one view into rgb [H,W,3] uint8, depth [H,W] float32, sem [H,W] uint8; photo: the photo
    bank [N, H_t, W_t, 3] (NO_PHOTOS when the scene uses none). Pinhole (rays of shape [0, ...]): the rays of
    fx, fy, cx, cy. Otherwise rays [S, H, W, 3] float64, ego frame, one per sample (S = 1 for ss == 1, else
    ss * ss + 1: the pixel centre, then the supersamples), scaled so that t is the camera's depth, and has_ray
    [S, H, W] bool: samples without a ray add black, a pixel centre without one gets depth 0 and class 0."""
    ox, oy, oz = T[0], T[1], T[2]
    inv = 1.0 / (ss * ss)
    half = (H + 1) // 2
    given_rays = rays.shape[0] > 0
    for k in prange(H):
        v = 2 * k if k < half else 2 * (k - half) + 1  # even rows, then odd rows: balances sky vs ground
        for u in range(W):
            ar, ag, ab = 0.0, 0.0, 0.0
            vis_c = -1.0  # sun visibility of the first shaded sample, reused by samples on the same face
            p_c, f_c = -3, -3
            # sample 0: geometry ray through the pixel centre (depth, class; shaded too when ss == 1);
            # samples 1..ss*ss: colour rays at offsets ((j + 0.5)/ss - 0.5, (i + 0.5)/ss - 0.5). One call site
            # of closest_hit keeps the inlined traversal code (and the compile time) small.
            for si in range(1 if ss == 1 else ss * ss + 1):
                if given_rays:
                    if not has_ray[si, v, u]:
                        if si == 0:
                            depth[v, u] = 0.0
                            sem[v, u] = 0
                        continue
                    dx, dy, dz = rays[si, v, u, 0], rays[si, v, u, 1], rays[si, v, u, 2]
                else:
                    if si == 0:
                        xs = (u - cx) / fx
                        ys = (v - cy) / fy
                    else:
                        xs = (u + ((si - 1) % ss + 0.5) / ss - 0.5 - cx) / fx
                        ys = (v + ((si - 1) // ss + 0.5) / ss - 0.5 - cy) / fy
                    # camera-frame direction (x, y, 1), so that t is the depth along the optical axis
                    dx = Rm[0, 0] * xs + Rm[0, 1] * ys + Rm[0, 2]
                    dy = Rm[1, 0] * xs + Rm[1, 1] * ys + Rm[1, 2]
                    dz = Rm[2, 0] * xs + Rm[2, 1] * ys + Rm[2, 2]
                t, p, f = closest_hit(ox, oy, oz, dx, dy, dz, skip_ego, kind, geo, ego, meta, start, items, zmax)
                if si == 0:
                    if p == NO_HIT:
                        depth[v, u] = 0.0
                        sem[v, u] = 0
                    else:
                        depth[v, u] = t
                        sem[v, u] = _semantic(p, cls, G, ox + t * dx, oy + t * dy)
                    if ss > 1:
                        continue
                given = vis_c if (p == p_c and f == f_c) else -1.0
                r, g, b, vis = _shade(ox, oy, oz, dx, dy, dz, t, p, f, skip_ego, shadows, given, kind,
                                      geo, cls, tex, col, col2, par, ego, meta, start, items, zmax, G, S, photo)
                if p_c == -3:
                    p_c, f_c, vis_c = p, f, vis
                ar += r
                ag += g
                ab += b
            rgb[v, u, 0] = np.uint8(min(255.0, max(0.0, ar * inv * 255.0 + 0.5)))
            rgb[v, u, 1] = np.uint8(min(255.0, max(0.0, ag * inv * 255.0 + 0.5)))
            rgb[v, u, 2] = np.uint8(min(255.0, max(0.0, ab * inv * 255.0 + 0.5)))


@dataclass(frozen=True, eq=False)
class View:
    """Rendered view: rgb [H,W,3] uint8; depth [H,W] float32, the camera's depth (Camera.depth_is_distance:
    metres along the optical axis for a pinhole or an opencv lens, from the camera centre for a fisheye or
    f-theta lens; 0 = sky or no ray); semantic [H,W] uint8 class ids (0 = sky or no ray); valid [H,W] bool, the
    pixels whose centre has a ray (None: all, a pinhole camera)."""

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    valid: np.ndarray | None = None

    @property
    def sky(self) -> np.ndarray:
        return self.semantic == C.SKY


NO_RAYS = np.zeros((0, 1, 1, 3), np.float64)   # render_kernel's rays for a pinhole camera
NO_RAY_MASK = np.zeros((0, 1, 1), np.bool_)


def sample_rays(camera: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """(rays [S, H, W, 3] float64 ego frame, has_ray [S, H, W] bool) of render_kernel for a camera with a lens:
    Camera.depth_rays through the pixel centre and the ss x ss supersample positions ((j + 0.5)/ss - 0.5 from
    the centre), rotated to ego; NaN rays (no ray reaches the position) are marked in has_ray and zeroed."""
    vv, uu = np.meshgrid(np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64),
                         indexing="ij")
    offsets = [(0.0, 0.0)] if ss == 1 else \
        [(0.0, 0.0)] + [((j + 0.5) / ss - 0.5, (i + 0.5) / ss - 0.5) for i in range(ss) for j in range(ss)]
    uv = np.stack([np.stack([uu + du, vv + dv], axis=-1) for du, dv in offsets])
    rays = camera.depth_rays(uv) @ camera.rotation.T
    ok = np.all(np.isfinite(rays), axis=-1)
    rays[~ok] = 0.0
    return np.ascontiguousarray(rays), ok


def render_view(scene: Scene, grid: Grid, camera: Camera, ss: int = 2, skip_ego: bool = True,
                shadows: bool = True) -> View:
    """Ray trace one camera (runtime.camera.Camera: K [3,3] px, OpenCV; cam_to_ego [4,4]) of `scene`: an ideal
    pinhole from K; a camera with a lens (docs/conventions.md "Lens models") or an equirectangular one along each
    sample's true ray (sample_rays; depth in the camera's convention, pixels without a ray black with depth 0,
    View.valid)."""
    K, cam_to_ego, width, height = camera.K, camera.cam_to_ego, camera.width, camera.height
    rgb = np.empty((height, width, 3), np.uint8)
    depth = np.empty((height, width), np.float32)
    sem = np.empty((height, width), np.uint8)
    Rm = np.ascontiguousarray(cam_to_ego[:3, :3], dtype=np.float64)
    T = np.ascontiguousarray(cam_to_ego[:3, 3], dtype=np.float64)
    pinhole = camera.is_ideal and not camera.is_equirect
    rays, has_ray = (NO_RAYS, NO_RAY_MASK) if pinhole else sample_rays(camera, int(ss))
    K = K if pinhole else np.eye(3)
    render_kernel(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), Rm, T, int(height), int(width),
                  int(ss), bool(skip_ego), bool(shadows), scene.kind, scene.geo, scene.cls, scene.tex, scene.col,
                  scene.col2, scene.par, scene.ego, grid.meta, grid.start, grid.items, grid.zmax, scene.ground,
                  scene.sky, scene_photos(scene), rays, has_ray, rgb, depth, sem)
    return View(rgb, depth, sem, None if pinhole else has_ray[0].copy())


def scene_photos(scene: Scene) -> np.ndarray:
    """The photo bank [N, H_t, W_t, 3] if the scene shows a photo tile (photo_textures), else NO_PHOTOS."""
    uses = (np.any(scene.tex == T_PHOTO) or scene.ground[G_PHOTO] > 0.5
            or np.any((scene.tex == T_SIDEWALK) & (scene.par[:, 1] > 0.5)))
    return photo_bank()[0] if uses else NO_PHOTOS


@njit(cache=True, error_model="numpy", fastmath=True)
def segment_blocked(a, b, skip_ego, kind, geo, ego, meta, start, items, zmax):
    """True if the open segment a -> b (ego points [3]) passes through a primitive or below the ground."""
    dx, dy, dz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    if a[2] <= 0.0 or b[2] <= 0.0:
        return True
    t, p, f = trace(a[0], a[1], a[2], dx, dy, dz, 1.0, True, skip_ego, kind, geo, ego, meta, start, items, zmax)
    return p >= 0


@njit(cache=True, error_model="numpy", fastmath=True)
def point_inside(x, y, z, margin, kind, geo):
    """True if the point is inside (or within `margin` metres of the bounds of) any primitive or below z=margin."""
    if z < margin:
        return True
    for p in range(kind.shape[0]):
        cx, cy, cz = geo[p, 0], geo[p, 1], geo[p, 2]
        hx, hy, hz = geo[p, 3] + margin, geo[p, 4] + margin, geo[p, 5] + margin
        c, s = geo[p, 6], geo[p, 7]
        rx, ry, rz = x - cx, y - cy, z - cz
        if abs(rz) > hz:
            continue
        if kind[p] == CYL:
            if rx * rx + ry * ry <= hx * hx:
                return True
            continue
        lx = rx * c + ry * s
        ly = -rx * s + ry * c
        if kind[p] == BOX:
            if abs(lx) <= hx and abs(ly) <= hy:
                return True
        elif (lx / hx) ** 2 + (ly / hy) ** 2 + (rz / hz) ** 2 <= 1.0:
            return True
    return False


# --------------------------------------------------------------------------------------------------------------
# slow reference (numpy, brute force over all primitives, no grid)


def reference_closest_hit(scene: Scene, origins: np.ndarray, dirs: np.ndarray, skip_ego: bool = True):
    """Closest hit of each ray with all primitives and the ground plane, by brute force.

    origins, dirs: [N, 3] ego metres (dirs need not be unit). Returns (t [N] with inf for no hit,
    prim [N] int: primitive id, GROUND or NO_HIT).
    """
    o = np.asarray(origins, np.float64)[:, None, :]
    d = np.asarray(dirs, np.float64)[:, None, :]
    g = scene.geo[None]
    c, s = g[..., 6], g[..., 7]
    r = o - g[..., :3]
    lx = r[..., 0] * c + r[..., 1] * s
    ly = -r[..., 0] * s + r[..., 1] * c
    lz = r[..., 2]
    dlx = d[..., 0] * c + d[..., 1] * s
    dly = -d[..., 0] * s + d[..., 1] * c
    dlz = np.broadcast_to(d[..., 2], lx.shape)
    h = g[..., 3:6]
    with np.errstate(divide="ignore", invalid="ignore"):
        # boxes: slabs
        tn = np.full(lx.shape, -np.inf)
        tf = np.full(lx.shape, np.inf)
        for lo, dl, hh in ((lx, dlx, h[..., 0]), (ly, dly, h[..., 1]), (lz, dlz, h[..., 2])):
            t1 = (-hh - lo) / dl
            t2 = (hh - lo) / dl
            par = dl == 0
            lo_ok = np.abs(lo) <= hh
            t1 = np.where(par, np.where(lo_ok, -np.inf, np.inf), t1)
            t2 = np.where(par, np.where(lo_ok, np.inf, -np.inf), t2)
            tn = np.maximum(tn, np.minimum(t1, t2))
            tf = np.minimum(tf, np.maximum(t1, t2))
        t_box = np.where((tn <= tf) & (tn > 0), tn, np.inf)
        # ellipsoids
        ex, ey, ez = lx / h[..., 0], ly / h[..., 1], lz / h[..., 2]
        edx, edy, edz = dlx / h[..., 0], dly / h[..., 1], dlz / h[..., 2]
        a = edx ** 2 + edy ** 2 + edz ** 2
        bq = ex * edx + ey * edy + ez * edz
        cq = ex ** 2 + ey ** 2 + ez ** 2 - 1
        disc = bq ** 2 - a * cq
        te = (-bq - np.sqrt(np.maximum(disc, 0))) / a
        t_ell = np.where((disc >= 0) & (cq > 0) & (te > 0), te, np.inf)
        # cylinders: side and caps
        rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
        dx, dy, dz = (np.broadcast_to(d[..., i], rx.shape) for i in range(3))
        a2 = dx ** 2 + dy ** 2
        b2 = rx * dx + ry * dy
        c2 = rx ** 2 + ry ** 2 - h[..., 0] ** 2
        disc2 = b2 ** 2 - a2 * c2
        ts = (-b2 - np.sqrt(np.maximum(disc2, 0))) / a2
        zs = rz + ts * dz
        t_side = np.where((disc2 >= 0) & (a2 > 0) & (ts > 0) & (np.abs(zs) <= h[..., 2]), ts, np.inf)
        t_cap = np.full(rx.shape, np.inf)
        for zc in (h[..., 2], -h[..., 2]):
            tc = (zc - rz) / dz
            inside = (rx + tc * dx) ** 2 + (ry + tc * dy) ** 2 <= h[..., 0] ** 2
            t_cap = np.minimum(t_cap, np.where((tc > 0) & inside & np.isfinite(tc), tc, np.inf))
        t_cyl = np.minimum(t_side, t_cap)
    k = scene.kind[None]
    t_all = np.where(k == BOX, t_box, np.where(k == ELL, t_ell, t_cyl))
    if skip_ego:
        t_all = np.where(scene.ego[None], np.inf, t_all)
    prim = np.argmin(t_all, axis=1)
    t = t_all[np.arange(len(prim)), prim]
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where((d[:, 0, 2] < 0) & (o[:, 0, 2] > 0), -o[:, 0, 2] / d[:, 0, 2], np.inf)
    out_p = np.where(np.isfinite(t), prim, np.where(np.isfinite(tg), GROUND, NO_HIT))
    return np.minimum(t, tg), out_p
