"""Procedural urban street scenes: primitives, ground layout and sky, sampled deterministically.

Frames: everything is in the ego frame (x forward, y left, z up, metres; nuScenes convention: origin at the
rear-axle centre on the ground, ground plane z = 0). The street is laid out in a "road frame" (u along the road,
v across it, ego at the origin) which is the ego frame turned by a small yaw `psi`:
p_ego = Rz(psi) @ p_road.

A scene is a set of solids: yaw-rotated boxes, vertical circular cylinders and yaw-rotated ellipsoids (all with
vertical z axis), plus the ground (the half space z <= 0, seen as the plane z = 0 and, for occupancy, a slab of
`GROUND_THICKNESS`), plus a sky. The ego car's primitives carry `ego = True`; rig views (inputs and
ego-forward targets) skip them, ego-inward views show them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import classes as C
from .photos import LUMA, photo_indices

GENERATOR_VERSION = "1"

BOX, CYL, ELL = 0, 1, 2  # primitive kinds
# texture ids
T_PLAIN, T_FACADE, T_SIDEWALK, T_FOLIAGE, T_GLASS, T_CARBODY, T_TLIGHT, T_SIGN, T_FENCE, T_BARK, T_PHOTO = range(11)
# T_PHOTO (a facade of a photo tile, photos.py): par = (tile index, metres per tile across, metres per tile up,
# luminance, 0, seed). T_SIDEWALK with par[1] > 0: its top shows tile par[1] - 1, par[2] metres per tile,
# luminance par[3].

GROUND_THICKNESS = 0.5  # metres: the ground is the solid slab -0.5 <= z <= 0 for occupancy
HALF_LENGTH = 110.0  # metres: the street runs over u in [-HALF_LENGTH, HALF_LENGTH]

# sky parameter vector layout (float64 [24])
S_ZENITH, S_HORIZON, S_SUNDIR, S_SUNCOL, S_CLOUD, S_CSCALE, S_COFF, S_AMB, S_FOG = 0, 3, 6, 9, 12, 13, 14, 16, 19
# ground parameter vector layout (float64 [32])
G_COS, G_SIN, G_VR, G_VL, G_LANEW, G_NLANES, G_VD0, G_NFWD, G_HASX, G_UX, G_WX, G_CSTYLE = range(12)
G_ASPH, G_TERR, G_XWALK, G_SEED, G_DASH, G_MARKCOL = 12, 15, 18, 19, 20, 21
G_PHOTO, G_PHOTO_TILE, G_PHOTO_L = 24, 25, 26  # road surface photo: tile index + 1 (0: none), metres, luminance


@dataclass(frozen=True, eq=False)
class Scene:
    """One sampled scene. Arrays are numba-ready (contiguous float64 / int32 / bool)."""

    kind: np.ndarray  # [P] int32: BOX, CYL, ELL
    geo: np.ndarray  # [P, 8] float64: centre xyz (m, ego), half extents / radii xyz (m), cos(yaw), sin(yaw)
    cls: np.ndarray  # [P] int32 semantic class (classes.py)
    tex: np.ndarray  # [P] int32 texture id (T_*)
    col: np.ndarray  # [P, 3] float64 base albedo 0..1
    col2: np.ndarray  # [P, 3] float64 secondary albedo (windows, curb, lights)
    par: np.ndarray  # [P, 6] float64 texture parameters
    ego: np.ndarray  # [P] bool: part of the ego car
    ground: np.ndarray  # [32] float64 road layout (G_* indices)
    sky: np.ndarray  # [24] float64 sky and light (S_* indices)
    lane_dir: np.ndarray  # [3] float64 unit vector along the ego lane, ego frame
    ego_centre: np.ndarray  # [3] float64 centre of the ego car's body (look-at point of ego-inward views)
    seed: int
    index: int

    @property
    def n(self) -> int:
        return int(self.kind.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("kind", "geo", "cls", "tex", "col", "col2", "par", "ego",
                                              "ground", "sky", "lane_dir", "ego_centre")}


def primitive_bounds(kind: np.ndarray, geo: np.ndarray) -> np.ndarray:
    """[P, 6] axis-aligned bounds (xmin, ymin, zmin, xmax, ymax, zmax), metres, exact for all three kinds."""
    c, s = np.abs(geo[:, 6]), np.abs(geo[:, 7])
    hx, hy, hz = geo[:, 3], geo[:, 4], geo[:, 5]
    ex = np.where(kind == BOX, hx * c + hy * s, 0.0)
    ey = np.where(kind == BOX, hx * s + hy * c, 0.0)
    # ellipse x^2/a^2 + y^2/b^2 rotated by yaw: extents sqrt(a^2 c^2 + b^2 s^2), sqrt(a^2 s^2 + b^2 c^2)
    ex = np.where(kind == ELL, np.sqrt((hx * c) ** 2 + (hy * s) ** 2), ex)
    ey = np.where(kind == ELL, np.sqrt((hx * s) ** 2 + (hy * c) ** 2), ey)
    ex = np.where(kind == CYL, hx, ex)
    ey = np.where(kind == CYL, hx, ey)
    x, y, z = geo[:, 0], geo[:, 1], geo[:, 2]
    return np.stack([x - ex, y - ey, z - hz, x + ex, y + ey, z + hz], axis=1)


@dataclass(frozen=True)
class SceneConfig:
    """Knobs of the sampler (defaults: the generator of docs/data.md)."""

    max_psi_deg: float = 3.0  # ego heading vs lane, degrees
    intersection_prob: float = 0.45
    with_ego: bool = True  # add the ego car (needed for ego-inward views)
    # probability that a scene has traffic beside the ego (real rigs do: a parked car 2-3 m from a side camera).
    # Such a scene keeps only the ego lane clear (not the 6 m discs around the ego that keep every other car
    # at >= 8 m), and each neighbouring driving lane and a neighbouring parking lane gets a car beside the ego
    # with probability BESIDE_P. 0 = the generator of docs/data.md, byte for byte (the draw is a side stream).
    near_cars: float = 0.0
    # probability that a scene's surfaces show real photo tiles (photos.py: facades, road, sidewalks) instead of
    # the procedural textures; real rigs see real facades. 0 = the generator of docs/data.md, byte for byte
    # (the draws are a side stream).
    photo_textures: float = 0.0

    def __post_init__(self):
        for name in ("near_cars", "photo_textures"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"{name}: must be in [0, 1], got {v}")


PHOTO_FACADE_P = 0.8  # per building of a photo_textures scene: a photo facade
PHOTO_ROAD_P = 0.6  # per photo_textures scene: a photo road surface (lane markings stay on top); sidewalks alike
PHOTO_FACADE_TILE = ((6.0, 16.0), (8.0, 24.0))  # metres per tile across and up (the tiles are squeezed crops)
PHOTO_GROUND_TILE = (3.0, 10.0)  # metres per ground tile
BESIDE_P = 0.7  # per neighbouring lane of a near_cars scene: a car beside the ego
BESIDE_U = (-4.0, 6.0)  # metres along the road, its centre (the ego's body centre is at u = 1.3)


class _Builder:
    """Accumulates primitives in the road frame."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, centre, half, yaw, cls, tex, col, col2=(0.0, 0.0, 0.0), par=(0.0,) * 6, ego=False):
        p = tuple(par) + (0.0,) * (6 - len(par))
        self.rows.append((kind, tuple(map(float, centre)), tuple(map(float, half)), float(yaw), int(cls),
                          int(tex), tuple(map(float, col)), tuple(map(float, col2)), p, bool(ego)))

    def box(self, u0, u1, v0, v1, z0, z1, cls, tex, col, col2=(0, 0, 0), par=(0,) * 6, yaw=0.0, ego=False):
        self.add(BOX, ((u0 + u1) / 2, (v0 + v1) / 2, (z0 + z1) / 2), ((u1 - u0) / 2, (v1 - v0) / 2,
                                                                      (z1 - z0) / 2),
                 yaw, cls, tex, col, col2, par, ego)


def _jit(rng, c, amount=0.06):
    return np.clip(np.asarray(c) + rng.uniform(-amount, amount, 3), 0.0, 1.0)


BUILDING_COLOURS = [(0.78, 0.72, 0.62), (0.62, 0.35, 0.27), (0.70, 0.70, 0.68), (0.86, 0.84, 0.78),
                    (0.55, 0.50, 0.45), (0.80, 0.62, 0.45), (0.45, 0.47, 0.50), (0.73, 0.55, 0.50),
                    (0.60, 0.62, 0.55), (0.88, 0.80, 0.62)]
CAR_COLOURS = [(0.92, 0.92, 0.92), (0.08, 0.08, 0.09), (0.62, 0.63, 0.65), (0.35, 0.36, 0.38),
               (0.65, 0.08, 0.07), (0.10, 0.18, 0.45), (0.12, 0.28, 0.18), (0.75, 0.68, 0.52),
               (0.85, 0.65, 0.10), (0.30, 0.45, 0.65)]


def _car(b: _Builder, rng, u, v, yaw, ego=False, kind=None):
    """A car centred at (u, v) on the ground, heading `yaw` (road frame)."""
    kind = kind if kind is not None else rng.choice(["sedan", "sedan", "hatch", "suv", "van", "bus"],
                                                    p=[0.32, 0.0, 0.25, 0.25, 0.13, 0.05])
    dims = {"sedan": (4.6, 1.82, 0.72, "ell"), "hatch": (4.0, 1.75, 0.75, "ell"), "suv": (4.7, 1.92, 0.95, "box"),
            "van": (5.2, 2.0, 1.75, "box"), "bus": (11.0, 2.5, 2.6, "box")}[kind]
    L, W, Hb, cab = dims
    L *= rng.uniform(0.93, 1.07)
    col = _jit(rng, CAR_COLOURS[rng.integers(len(CAR_COLOURS))], 0.04)
    glass = (0.10, 0.13, 0.17)
    c, s = math.cos(yaw), math.sin(yaw)

    def at(du, dv):
        return u + du * c - dv * s, v + du * s + dv * c

    z0 = 0.30
    cu, cv = at(0.0, 0.0)
    b.add(BOX, (cu, cv, z0 + Hb / 2), (L / 2, W / 2, Hb / 2), yaw, C.EGO if ego else C.VEHICLE, T_CARBODY, col,
          (0.9, 0.9, 0.8), ego=ego)
    if kind == "bus":
        # window band on a bus: a slightly wider glass box
        b.add(BOX, (cu, cv, z0 + Hb + 0.35), (L / 2 - 0.1, W / 2 - 0.02, 0.35), yaw,
              C.EGO if ego else C.VEHICLE, T_GLASS, glass, col, ego=ego)
    elif cab == "ell":
        gu, gv = at(-0.08 * L, 0.0)
        b.add(ELL, (gu, gv, z0 + Hb), (0.30 * L, 0.46 * W, 0.50), yaw, C.EGO if ego else C.VEHICLE, T_GLASS,
              glass, col, ego=ego)
    elif kind == "suv":
        gu, gv = at(-0.1 * L, 0.0)
        b.add(BOX, (gu, gv, z0 + Hb + 0.30), (0.32 * L, 0.45 * W, 0.30), yaw, C.EGO if ego else C.VEHICLE,
              T_GLASS, glass, col, ego=ego)
    for du in (L / 2 - 0.85, -(L / 2 - 0.85)):
        for dv in (W / 2 - 0.12, -(W / 2 - 0.12)):
            wu, wv = at(du, dv)
            b.add(BOX, (wu, wv, 0.32), (0.33, 0.12, 0.32), yaw, C.EGO if ego else C.VEHICLE, T_PLAIN,
                  (0.04, 0.04, 0.04), ego=ego)
    return L


def sample_scene(seed: int, index: int, config: SceneConfig = SceneConfig()) -> Scene:
    """The scene number `index` of the data set with `seed`; identical for identical arguments."""
    rng = np.random.default_rng([int(seed), int(index), 0x5CE7E])
    b = _Builder()
    L = HALF_LENGTH

    # -- cross-section of the main road (road frame, v = 0 at first on the centre line) --
    lane_w = rng.uniform(3.0, 3.7)
    n_lanes = int(rng.choice([2, 2, 3, 4, 4]))
    n_fwd = n_lanes // 2 if n_lanes > 2 else 1
    park_r, park_l = rng.random() < 0.6, rng.random() < 0.6
    park_w = 2.3
    vd0 = -n_fwd * lane_w  # right edge of the driving lanes (centre line at 0)
    ego_lane = int(rng.integers(n_fwd))
    shift = vd0 + (ego_lane + 0.5) * lane_w  # ego lane centre -> v = 0
    vd0 -= shift
    vr = vd0 - park_r * park_w
    vl = vd0 + n_lanes * lane_w + park_l * park_w
    sw_r, sw_l = rng.uniform(2.0, 5.0), rng.uniform(2.0, 5.0)
    curb = rng.uniform(0.12, 0.2)
    has_x = rng.random() < config.intersection_prob
    ux = rng.uniform(-30.0, 45.0) if has_x else 1e9
    wx = rng.uniform(4.0, 8.0)
    xwalk = has_x and rng.random() < 0.8
    # keep the ego's stretch of road clear of the crossing region so ego-forward poses stay on the road
    if has_x and abs(ux) < wx + 10:
        ux = math.copysign(wx + 10 + rng.uniform(0, 10), ux if ux != 0 else 1.0)
    xr0, xr1 = ux - wx - max(sw_r, sw_l), ux + wx + max(sw_r, sw_l)  # crossing incl. its sidewalks

    def in_cross(u0, u1, margin=0.0):
        return has_x and u1 > xr0 - margin and u0 < xr1 + margin

    sw_col = _jit(rng, (0.66, 0.64, 0.60), 0.08)
    curb_col = _jit(rng, (0.72, 0.72, 0.70), 0.05)
    tile = rng.uniform(0.5, 1.0)
    # sidewalks (raised boxes), split at the crossing
    segs = [(-L, ux - wx), (ux + wx, L)] if has_x else [(-L, L)]
    for u0, u1 in segs:
        b.box(u0, u1, vr - sw_r, vr, 0.0, curb, C.SIDEWALK, T_SIDEWALK, sw_col, curb_col, (tile,))
        b.box(u0, u1, vl, vl + sw_l, 0.0, curb, C.SIDEWALK, T_SIDEWALK, sw_col, curb_col, (tile,))
    if has_x:
        for uu0, uu1 in ((ux - wx - sw_r, ux - wx), (ux + wx, ux + wx + sw_l)):
            b.box(uu0, uu1, vl + sw_l, 80.0, 0.0, curb, C.SIDEWALK, T_SIDEWALK, sw_col, curb_col, (tile,))
            b.box(uu0, uu1, -80.0, vr - sw_r, 0.0, curb, C.SIDEWALK, T_SIDEWALK, sw_col, curb_col, (tile,))

    # -- buildings --
    palette = [BUILDING_COLOURS[i] for i in rng.choice(len(BUILDING_COLOURS), 4, replace=False)]
    tall_bias = rng.uniform(0.1, 0.5)

    def building(u0, u1, v0, v1, h=None):
        if h is None:
            h = rng.uniform(18.0, 40.0) if rng.random() < tall_bias else rng.uniform(4.0, 18.0)
        col = _jit(rng, palette[rng.integers(len(palette))], 0.05)
        glass = _jit(rng, rng.choice([0.18, 0.25, 0.32]) * np.array([0.8, 0.95, 1.1]), 0.04)
        storey = rng.uniform(2.8, 3.8)
        h = max(h, storey + 0.8)
        b.box(u0, u1, v0, v1, 0.0, h, C.BUILDING, T_FACADE, col, glass,
              (storey, rng.uniform(1.8, 3.4), rng.uniform(0.35, 0.7), rng.uniform(0.4, 0.62),
               float(rng.random() < 0.5), float(rng.integers(1 << 20))))

    def street_side(sign, v_edge):
        """Buildings along one side of the main road; v_edge = outer edge of the sidewalk."""
        u = -L - rng.uniform(0, 10)
        gaps = []
        while u < L:
            w = rng.uniform(8.0, 30.0)
            gap = rng.uniform(3.0, 14.0) if rng.random() < 0.3 else rng.uniform(0.0, 0.6)
            u0, u1 = u, u + w
            u = u1 + gap
            if gap > 2.5:
                gaps.append((u1, u1 + gap))
            if in_cross(u0, u1, 1.0):
                continue
            setback = 0.0 if rng.random() < 0.6 else rng.uniform(0.5, 4.0)
            depth = rng.uniform(8.0, 20.0)
            v0 = v_edge + sign * setback
            v1 = v0 + sign * depth
            building(u0, u1, min(v0, v1), max(v0, v1))
            if rng.random() < 0.6:  # second row behind, fills the gaps
                vb0 = v1 + sign * rng.uniform(3.0, 12.0)
                vb1 = vb0 + sign * rng.uniform(10.0, 25.0)
                building(u0 + rng.uniform(-5, 3), u1 + rng.uniform(-3, 5), min(vb0, vb1), max(vb0, vb1),
                         rng.uniform(8.0, 40.0))
        return gaps

    gaps_l = street_side(+1, vl + sw_l)
    gaps_r = street_side(-1, vr - sw_r)
    if has_x:
        for sign, v_edge in ((+1, vl + sw_l), (-1, vr - sw_r)):
            for side, u_face in ((-1, ux - wx - sw_r), (+1, ux + wx + sw_l)):
                v = v_edge + sign * rng.uniform(0.0, 2.0)
                while abs(v) < 75:
                    w = rng.uniform(8.0, 25.0)
                    u0 = u_face + side * rng.uniform(0.0, 2.0)
                    u1 = u0 + side * rng.uniform(10.0, 20.0)
                    building(min(u0, u1), max(u0, u1), min(v, v + sign * w), max(v, v + sign * w))
                    v += sign * (w + (rng.uniform(2.0, 8.0) if rng.random() < 0.3 else 0.0))

    # fences and hedges in the gaps
    for gaps, sign, v_edge in ((gaps_l, +1, vl + sw_l), (gaps_r, -1, vr - sw_r)):
        for g0, g1 in gaps:
            if in_cross(g0, g1, 1.0):
                continue
            r = rng.random()
            vf = v_edge + sign * 0.3
            if r < 0.45:
                hgt = rng.uniform(1.0, 2.2)
                b.box(g0, g1, vf - 0.04, vf + 0.04, 0.0, hgt, C.FENCE, T_FENCE,
                      _jit(rng, rng.choice([0.25, 0.5, 0.7]) * np.ones(3), 0.05), par=(rng.uniform(0.1, 0.3),))
            elif r < 0.7:
                b.box(g0 + 0.3, g1 - 0.3, vf - 0.5, vf + 0.5, 0.0, rng.uniform(0.8, 1.6), C.VEGETATION, T_FOLIAGE,
                      _jit(rng, (0.20, 0.35, 0.14), 0.05))
            elif r < 0.9:
                for _ in range(int(rng.integers(1, 3))):
                    tu = rng.uniform(g0 + 1, max(g0 + 1.01, g1 - 1))
                    _tree(b, rng, tu, v_edge + sign * rng.uniform(2.0, 6.0))

    # -- street furniture on the sidewalks --
    lamp_col = _jit(rng, (0.30, 0.31, 0.33), 0.05)
    lamp_spacing = rng.uniform(18.0, 32.0)
    for sign, v_curb, sw in ((+1, vl, sw_l), (-1, vr, sw_r)):
        u = -L + rng.uniform(0, lamp_spacing)
        while u < L:
            if not in_cross(u, u, 1.0):
                vp = v_curb + sign * 0.45
                h = rng.uniform(6.0, 9.0)
                b.add(CYL, (u, vp, h / 2), (0.09, 0.09, h / 2), 0.0, C.POLE, T_PLAIN, lamp_col)
                arm = rng.uniform(1.0, 2.2)
                b.box(u - 0.06, u + 0.06, min(vp, vp - sign * arm), max(vp, vp - sign * arm), h - 0.12, h,
                      C.POLE, T_PLAIN, lamp_col)
                b.box(u - 0.25, u + 0.25, vp - sign * arm - 0.35, vp - sign * arm + 0.35, h - 0.3, h - 0.05,
                      C.POLE, T_PLAIN, lamp_col, (1.0, 0.95, 0.8))
            u += lamp_spacing
        tree_p = rng.uniform(0.0, 0.9)
        if sw >= 2.5 and tree_p > 0.2:
            u = -L + rng.uniform(0, 8)
            while u < L:
                if not in_cross(u - 3, u + 3, 1.0) and rng.random() < tree_p:
                    _tree(b, rng, u, v_curb + sign * min(1.3, sw / 2))
                u += rng.uniform(7.0, 15.0)
        for _ in range(int(rng.integers(1, 4))):
            u = rng.uniform(-60, 60)
            if in_cross(u, u, 2.0):
                continue
            vp = v_curb + sign * 0.35
            h = rng.uniform(2.2, 3.0)
            b.add(CYL, (u, vp, h / 2), (0.04, 0.04, h / 2), 0.0, C.POLE, T_PLAIN, (0.55, 0.56, 0.58))
            plate = [(0.75, 0.08, 0.08), (0.08, 0.25, 0.65), (0.9, 0.75, 0.1), (0.95, 0.95, 0.95)]
            b.box(u - 0.02, u + 0.02, vp - 0.32, vp + 0.32, h - 0.1, h + 0.54, C.TRAFFIC_SIGN, T_SIGN,
                  plate[rng.integers(4)], (0.95, 0.95, 0.95))
    if has_x:  # traffic lights at the four corners
        lit = float(rng.integers(3))
        for uc, face in ((ux - wx - 0.5, -1.0), (ux + wx + 0.5, 1.0)):
            for vc in (vr - 0.5, vl + 0.5):
                h = rng.uniform(3.0, 4.0)
                b.add(CYL, (uc, vc, h / 2), (0.08, 0.08, h / 2), 0.0, C.POLE, T_PLAIN, (0.2, 0.21, 0.2))
                b.box(uc - 0.15, uc + 0.15, vc - 0.18, vc + 0.18, h, h + 0.95, C.TRAFFIC_SIGN, T_TLIGHT,
                      (0.06, 0.06, 0.06), par=(lit, face))

    # -- cars --
    def free(u, v, r, taken):
        return all((u - a) ** 2 + (v - bb) ** 2 > (r + rr) ** 2 for a, bb, rr in taken)

    # a side stream, so that near_cars = 0 leaves the main stream (and every other scene) as it was
    side = np.random.default_rng([int(seed), int(index), 0xBE51DE])
    near = config.near_cars > 0 and side.random() < config.near_cars
    taken: list[tuple[float, float, float]] = [] if near else [(0.0, 0.0, 6.0), (-2.0, 0.0, 6.0), (3.0, 0.0, 6.0)]
    if near:  # the ego lane stays clear (the lane rule below); its neighbours get a car beside the ego
        slots = [(vd0 + (lane + 0.5) * lane_w, 0.0 if lane < n_fwd else math.pi, None)
                 for lane in (ego_lane - 1, ego_lane + 1) if 0 <= lane < n_lanes]
        if park_r and ego_lane == 0:
            slots.append((vr + park_w / 2, 0.0, "parked"))
        for v_slot, yaw, parked in slots:
            u = side.uniform(*BESIDE_U)
            if side.random() < BESIDE_P and free(u, v_slot, 3.0, taken):
                kind = side.choice(["sedan", "hatch", "suv", "van"], p=[0.35, 0.3, 0.25, 0.1]) if parked else None
                length = _car(b, side, u, v_slot + side.uniform(-0.15, 0.15), yaw + side.uniform(-0.04, 0.04),
                              kind=kind)
                taken.append((u, v_slot, length / 2 + 0.5))
    for park, vpark, flip in ((park_r, vr + park_w / 2, 0.0), (park_l, vl - park_w / 2, math.pi)):
        if not park:
            continue
        occ = rng.uniform(0.3, 0.9)
        u = -L + rng.uniform(0, 5)
        while u < L:
            if rng.random() < occ and not in_cross(u - 3, u + 3, 4.0) and free(u, vpark, 2.3, taken):
                length = _car(b, rng, u, vpark + rng.uniform(-0.15, 0.15), flip + rng.uniform(-0.05, 0.05),
                              kind=rng.choice(["sedan", "hatch", "suv", "van"], p=[0.35, 0.3, 0.25, 0.1]))
                taken.append((u, vpark, length / 2))
                u += length + rng.uniform(0.6, 2.5)
            else:
                u += rng.uniform(2.0, 6.0)
    for lane in range(n_lanes):
        vlane = vd0 + (lane + 0.5) * lane_w
        yaw = 0.0 if lane < n_fwd else math.pi
        for _ in range(int(rng.integers(0, 6))):
            u = rng.uniform(-70, 70)
            if (abs(vlane) < 0.5 and abs(u) < 10.0) or not free(u, vlane, 3.0, taken):
                continue
            length = _car(b, rng, u, vlane + rng.uniform(-0.3, 0.3), yaw + rng.uniform(-0.04, 0.04))
            taken.append((u, vlane, length / 2 + 0.5))
    if has_x:
        for _ in range(int(rng.integers(0, 3))):
            v = rng.uniform(-50, 50)
            if vr - 2 < v < vl + 2 or not free(ux, v, 3.0, taken):
                continue
            side = 1 if rng.random() < 0.5 else -1
            length = _car(b, rng, ux + side * wx / 2, v, side * math.pi / 2)
            taken.append((ux, v, length / 2))

    # -- the ego car (in the ego frame: origin = rear axle on the ground, x forward) --
    psi = math.radians(rng.uniform(-config.max_psi_deg, config.max_psi_deg))
    ego_rows_start = len(b.rows)
    if config.with_ego:
        # body centre 1.3 m ahead of the rear axle (nuScenes-like: rear overhang 0.75 m, length 4.1 m)
        _car(b, rng, 1.3, 0.0, 0.0, ego=True, kind=rng.choice(["sedan", "hatch", "suv"]))
    ego_rows = set(range(ego_rows_start, len(b.rows)))

    # -- to arrays; road frame -> ego frame (ego parts are already in the ego frame) --
    P = len(b.rows)
    kind = np.array([r[0] for r in b.rows], np.int32)
    geo = np.zeros((P, 8))
    cp, sp = math.cos(psi), math.sin(psi)
    for i, r in enumerate(b.rows):
        (x, y, z), (hx, hy, hz), yaw = r[1], r[2], r[3]
        if i not in ego_rows:
            x, y = cp * x - sp * y, sp * x + cp * y
            yaw += psi
        geo[i] = (x, y, z, hx, hy, hz, math.cos(yaw), math.sin(yaw))
    cls = np.array([r[4] for r in b.rows], np.int32)
    tex = np.array([r[5] for r in b.rows], np.int32)
    col = np.array([r[6] for r in b.rows], np.float64)
    col2 = np.array([r[7] for r in b.rows], np.float64)
    par = np.array([r[8] for r in b.rows], np.float64)
    ego = np.array([r[9] for r in b.rows], bool)

    ground = np.zeros(32)
    ground[G_COS], ground[G_SIN] = cp, sp
    ground[G_VR], ground[G_VL], ground[G_LANEW], ground[G_NLANES] = vr, vl, lane_w, n_lanes
    ground[G_VD0], ground[G_NFWD] = vd0, n_fwd
    ground[G_HASX], ground[G_UX], ground[G_WX] = float(has_x), ux, wx
    ground[G_CSTYLE] = rng.integers(3)
    ground[G_ASPH:G_ASPH + 3] = _jit(rng, rng.uniform(0.22, 0.36) * np.array([1.0, 1.0, 1.03]), 0.02)
    ground[G_TERR:G_TERR + 3] = _jit(rng, [(0.30, 0.40, 0.18), (0.42, 0.38, 0.28), (0.36, 0.42, 0.22)]
                                     [rng.integers(3)], 0.04)
    ground[G_XWALK] = float(xwalk)
    ground[G_SEED] = float(rng.integers(1 << 20))
    ground[G_DASH] = rng.uniform(0, 9)
    ground[G_MARKCOL:G_MARKCOL + 3] = rng.uniform(0.75, 0.9) * np.ones(3)

    sky = np.zeros(24)
    overcast = rng.random() < 0.25
    zen = np.array([0.22, 0.42, 0.78]) * rng.uniform(0.8, 1.1)
    hor = np.array([0.72, 0.80, 0.90]) * rng.uniform(0.9, 1.05)
    if overcast:
        g = rng.uniform(0.6, 0.8)
        zen = np.array([g, g, g + 0.03]) * 0.9
        hor = np.array([g, g, g]) + 0.1
    elev = math.radians(rng.uniform(15.0, 65.0))
    az = rng.uniform(-math.pi, math.pi)
    sun = np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)])
    warm = rng.uniform(0.0, 1.0) * (1.0 - math.sin(elev))
    sun_col = np.array([1.0, 0.93 - 0.1 * warm, 0.82 - 0.2 * warm]) * (0.35 if overcast else rng.uniform(0.75, 0.95))
    sky[S_ZENITH:S_ZENITH + 3] = np.clip(zen, 0, 1)
    sky[S_HORIZON:S_HORIZON + 3] = np.clip(hor, 0, 1)
    sky[S_SUNDIR:S_SUNDIR + 3] = sun
    sky[S_SUNCOL:S_SUNCOL + 3] = sun_col
    sky[S_CLOUD] = rng.uniform(0.55, 0.9) if overcast else rng.uniform(0.0, 0.6)
    sky[S_CSCALE] = rng.uniform(0.3, 0.9)
    sky[S_COFF:S_COFF + 2] = rng.uniform(-100, 100, 2)
    amb = 0.5 * (zen + hor)
    amb = (0.6 * amb + 0.4 * amb.mean()) * (1.0 if overcast else 0.78)  # sky light, partly desaturated
    sky[S_AMB:S_AMB + 3] = amb
    sky[S_FOG] = rng.uniform(250.0, 900.0)

    # a side stream, so that photo_textures = 0 leaves every scene as it was
    photo = np.random.default_rng([int(seed), int(index), 0x9407])
    if config.photo_textures > 0 and photo.random() < config.photo_textures:
        _photo_textures(photo, tex, col, par, ground)

    lane_dir = np.array([cp, sp, 0.0])
    ego_centre = np.array([1.3, 0.0, 0.8])
    return Scene(kind, geo, cls, tex, col, col2, par, ego, ground, sky, lane_dir, ego_centre, int(seed), int(index))


def _luma(rgb) -> float:
    return float(np.dot(LUMA, rgb))


def _photo_textures(rng, tex: np.ndarray, col: np.ndarray, par: np.ndarray, ground: np.ndarray) -> None:
    """Give a scene's surfaces photo tiles, in place: each building (T_FACADE -> T_PHOTO) with probability
    PHOTO_FACADE_P, the road and the sidewalks (one ground tile each) with PHOTO_ROAD_P. Each keeps its luminance."""
    facades, grounds = photo_indices()
    for i in np.flatnonzero(tex == T_FACADE):
        if rng.random() < PHOTO_FACADE_P:
            (a0, a1), (u0, u1) = PHOTO_FACADE_TILE
            par[i, :5] = (rng.choice(facades), rng.uniform(a0, a1), rng.uniform(u0, u1), _luma(col[i]), 0.0)
            tex[i] = T_PHOTO
    if rng.random() < PHOTO_ROAD_P:
        ground[G_PHOTO] = 1 + rng.choice(grounds)
        ground[G_PHOTO_TILE] = rng.uniform(*PHOTO_GROUND_TILE)
        ground[G_PHOTO_L] = _luma(ground[G_ASPH:G_ASPH + 3])
    if rng.random() < PHOTO_ROAD_P:
        k, tile = 1 + rng.choice(grounds), rng.uniform(*PHOTO_GROUND_TILE)
        for i in np.flatnonzero(tex == T_SIDEWALK):
            par[i, 1:4] = (k, tile, _luma(col[i]))


def _tree(b: _Builder, rng, u, v):
    h_trunk = rng.uniform(1.8, 3.5)
    r_trunk = rng.uniform(0.12, 0.25)
    b.add(CYL, (u, v, h_trunk / 2), (r_trunk, r_trunk, h_trunk / 2), 0.0, C.VEGETATION, T_BARK,
          _jit(rng, (0.33, 0.24, 0.16), 0.04))
    rh = rng.uniform(1.6, 3.5)
    rv = rh * rng.uniform(0.8, 1.4)
    b.add(ELL, (u, v, h_trunk + rv * 0.75), (rh, rh, rv), 0.0, C.VEGETATION, T_FOLIAGE,
          _jit(rng, [(0.20, 0.36, 0.12), (0.28, 0.40, 0.15), (0.16, 0.30, 0.14), (0.35, 0.38, 0.14)]
               [rng.integers(4)], 0.04))
