"""The Unified Cylinder Camera Model (UCCM) of XYZCylinder (paper Sec. 3.1 and appendix "Definition and
Derivation"), vectorised numpy.

Cylinder geometry (docs/conventions.md states all of it):
- centre c = mean camera position + (0, 0, dh), ego frame; axis vertical (ego z);
- Z_u = z_max - z_min (vertical extent of the occupancy grid), R_u = (Z_u / 2) / tan(rho * f_min / 2), f_min the
  smallest vertical FoV of the rig's cameras (each counted as at most pi: a wide fisheye's may exceed it);
- theta = atan2(y - c_y, x - c_x) (0 = ego forward, counter-clockwise positive seen from above);
- column: s = (pi - theta) / 2pi, j = s W_u - 1/2 (left -> right turns clockwise, forward at the centre column);
- row: p = 1/2 - dz R_u / (Z_u r) with dz = z - c_z and r the horizontal distance to the axis, i = p H_u - 1/2;
  on the cylinder surface (r = R_u) this is z = c_z + Z_u (1/2 - p), the top row highest;
- normalised sampling coordinates (align_corners=False): (2s - 1, 2p - 1) = ((2j + 1)/W_u - 1, (2i + 1)/H_u - 1).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .camera import Camera
from .errors import FieldError, plain
from .rig import Rig

# The paper's (rho, dh) per dataset and module: tables "Model architecture ... on nuScenes / Carla-Centric" and
# "UCCM Parameter Settings for Zero-shot Generalization". Argoverse's occupancy rho is printed as 0.09 in the
# paper; kept verbatim (it looks like a typo for 0.9, see docs/conventions.md).
PRESETS: dict[str, dict[str, tuple[float, float]]] = {
    "nuscenes": {"occupancy": (0.9, 0.0), "volume": (0.98, 0.4), "pixel": (0.98, 0.4)},
    "waymo": {"occupancy": (1.2, 0.0), "volume": (0.98, 0.4), "pixel": (0.98, 0.4)},
    "pandaset": {"occupancy": (2.0, 0.0), "volume": (1.6, 0.0), "pixel": (1.6, 0.0)},
    "once": {"occupancy": (1.8, 0.0), "volume": (1.0, 0.5), "pixel": (1.0, 0.5)},
    "argoverse": {"occupancy": (0.09, 0.0), "volume": (0.98, 0.0), "pixel": (0.98, 0.0)},
    "carla-centric": {"occupancy": (0.9, 0.0), "volume": (1.6, 0.0), "pixel": (1.6, 0.0)},
}
MODULES = ("occupancy", "volume", "pixel")
DEFAULT_Z_RANGE = (-3.0, 13.0)  # paper's nuScenes occupancy grid [-40, -40, -3, 40, 40, 13]
OFF_GRID = -2.0  # normalised grid value written for invalid cylinder pixels: fully outside, samples to 0

Order = Literal["cw", "ccw"]


class CylinderError(FieldError):
    """Invalid cylinder parameters: ``field`` the parameter (a scene.json background.cylinder key, or a
    from_rig / from_preset argument: "z_range", "rho", "dh", "preset", "module")."""


@dataclass(frozen=True, eq=False)
class CylinderSpec:
    centre: np.ndarray  # [3] metres, ego frame
    radius: float  # R_u, metres
    z_min: float  # occupancy grid vertical range, metres (ego); Z_u = z_max - z_min
    z_max: float
    height: int  # H_u
    width: int  # W_u
    rho: float | None = None  # the factor R_u was built with (record only)
    dh: float = 0.0  # the height offset included in centre (record only)

    def __post_init__(self) -> None:
        c = np.array(self.centre, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise CylinderError("centre", f"must be 3 finite numbers (got {plain(self.centre)!r})")
        c.setflags(write=False)
        object.__setattr__(self, "centre", c)
        for key in ("radius", "z_min", "z_max"):
            v = float(getattr(self, key))
            if not math.isfinite(v):
                raise CylinderError(key, f"must be finite (got {v})")
            object.__setattr__(self, key, v)
        if not self.radius > 0:
            raise CylinderError("radius", f"must be > 0 (got {self.radius})")
        if not self.z_max > self.z_min:
            raise CylinderError("z_max", f"must be > z_min (got {self.z_min}, {self.z_max})")
        for key in ("height", "width"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < int(v) <= 65536:
                raise CylinderError(key, f"must be an integer in 1..65536 (got {plain(v)!r})")
            object.__setattr__(self, key, int(v))

    @property
    def Z_u(self) -> float:
        """Cylinder height, metres: the occupancy grid's vertical extent."""
        return self.z_max - self.z_min

    @property
    def vertical_angle(self) -> float:
        """Full vertical angle the cylinder subtends from its axis, radians: 2 atan(Z_u / (2 R_u)) = rho f_min."""
        return 2.0 * math.atan(self.Z_u / (2.0 * self.radius))

    @classmethod
    def from_rig(cls, rig: Rig, z_range: tuple[float, float] = DEFAULT_Z_RANGE, rho: float = 0.9,
                 dh: float = 0.0, height: int = 224, width: int = 1024) -> CylinderSpec:
        """The paper's construction: centre = mean camera position + (0, 0, dh), R_u = (Z_u/2)/tan(rho f_min/2).

        f_min = min over cameras of the vertical FoV (pinhole 2 atan(H / 2 fy); equirectangular pi; a fisheye or
        f-theta lens: Camera.vertical_fov, which may exceed pi, counts as at most pi, as an equirectangular camera).
        Raises CylinderError naming the parameter when rho * f_min / 2 is not in (0, pi/2).
        """
        z_min, z_max = (float(z) for z in z_range)
        if not (math.isfinite(z_min) and math.isfinite(z_max)) or not z_max > z_min:
            raise CylinderError("z_range", f"need finite z_min < z_max (got {z_min}, {z_max})")
        rho, dh = float(rho), float(dh)
        if not math.isfinite(rho) or rho <= 0:
            raise CylinderError("rho", f"must be a finite number > 0 (got {rho})")
        if not math.isfinite(dh):
            raise CylinderError("dh", f"must be finite (got {dh})")
        f_min = min(min(c.vertical_fov, math.pi) for c in rig.cameras)
        half = rho * f_min / 2.0
        if half >= math.pi / 2.0:
            raise CylinderError(
                "rho", f"rho * f_min / 2 = {rho:g} * {f_min:.4f} / 2 = {half:.4f} rad >= pi/2, so "
                       f"tan(rho f_min / 2) is not positive and R_u is undefined; use rho < {math.pi / f_min:.4f} "
                       f"for this rig (f_min = {math.degrees(f_min):.2f} deg)")
        radius = (z_max - z_min) / 2.0 / math.tan(half)
        centre = np.mean([c.position for c in rig.cameras], axis=0) + np.array([0.0, 0.0, dh])
        return cls(centre=centre, radius=radius, z_min=z_min, z_max=z_max, height=height, width=width,
                   rho=rho, dh=dh)

    @classmethod
    def from_preset(cls, rig: Rig, dataset: str, module: str = "occupancy", **kwargs: Any) -> CylinderSpec:
        """from_rig with the paper's (rho, dh) for `dataset` and `module` (see PRESETS)."""
        if dataset not in PRESETS:
            raise CylinderError("preset", f"must be one of {sorted(PRESETS)} (got {dataset!r})")
        if module not in MODULES:
            raise CylinderError("module", f"must be one of {MODULES} (got {module!r})")
        rho, dh = PRESETS[dataset][module]
        return cls.from_rig(rig, rho=rho, dh=dh, **kwargs)

    # -- pixel <-> point ------------------------------------------------------------------------------------
    def pixel_to_point(self, i: np.ndarray | float, j: np.ndarray | float) -> np.ndarray:
        """Cylinder pixel (row i, column j; continuous allowed, centres at integers) -> [..., 3] ego metres on
        the surface: theta = pi - 2 pi (j + 1/2)/W_u, z = c_z + Z_u (1/2 - (i + 1/2)/H_u)."""
        i, j = np.broadcast_arrays(np.asarray(i, dtype=np.float64), np.asarray(j, dtype=np.float64))
        theta = np.pi - 2.0 * np.pi * (j + 0.5) / self.width
        p = (i + 0.5) / self.height
        c = self.centre
        return np.stack([c[0] + self.radius * np.cos(theta), c[1] + self.radius * np.sin(theta),
                         c[2] + self.Z_u * (0.5 - p)], axis=-1)

    def point_to_pixel(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[..., 3] ego points -> continuous (i, j), the central projection onto the cylinder through its axis:
        j = s W_u - 1/2 with s = (pi - theta)/2pi in [0, 1); i = p H_u - 1/2 with p = 1/2 - dz R_u / (Z_u r).
        Points on the axis (r = 0) give i = nan."""
        s, p, _ = self._cyl(points)
        return p * self.height - 0.5, s * self.width - 0.5

    def _cyl(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, p, r) of ego points [..., 3]: s = (pi - theta)/2pi in [0, 1), p = 1/2 - dz R_u/(Z_u r)."""
        d = np.asarray(points, dtype=np.float64) - self.centre
        r = np.hypot(d[..., 0], d[..., 1])
        theta = np.arctan2(d[..., 1], d[..., 0])
        s = (np.pi - theta) / (2.0 * np.pi)
        s = np.where(s >= 1.0, s - 1.0, s)  # theta = -pi (y = -0) is the same column as theta = pi
        with np.errstate(divide="ignore", invalid="ignore"):
            p = 0.5 - d[..., 2] * self.radius / (self.Z_u * np.where(r > 0, r, np.nan))
        return s, p, r

    def points(self) -> np.ndarray:
        """[H_u, W_u, 3] ego points of all cylinder pixel centres."""
        i, j = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        return self.pixel_to_point(i, j)

    # -- serialisation --------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"centre": self.centre.tolist(), "radius": self.radius, "z_min": self.z_min, "z_max": self.z_max,
                "height": self.height, "width": self.width, "rho": self.rho, "dh": self.dh}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CylinderSpec:
        missing = [k for k in ("centre", "radius", "z_min", "z_max", "height", "width") if k not in d]
        if missing:
            raise CylinderError(missing[0], "is missing from the cylinder spec")
        return cls(centre=d["centre"], radius=d["radius"], z_min=d["z_min"], z_max=d["z_max"],
                   height=d["height"], width=d["width"], rho=d.get("rho"), dh=d.get("dh", 0.0))


# -- per-camera sampling -----------------------------------------------------------------------------------------

def camera_sampling_grid(spec: CylinderSpec, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Where each cylinder pixel falls in `camera`.

    Returns grid [H_u, W_u, 2] float32, normalised (x, y) = ((2u + 1)/W - 1, (2v + 1)/H - 1) for bilinear
    sampling with align_corners=False semantics (torch.nn.functional.grid_sample's default), and valid
    [H_u, W_u] bool: in front of the camera and inside [-0.5, W-0.5] x [-0.5, H-0.5]. Invalid pixels get grid
    value (-2, -2), fully outside the image, so zero-padded sampling returns 0 there.
    """
    uv, _, in_front = camera.project(spec.points())
    valid = in_front & camera.inside(uv)
    grid = np.stack([(2.0 * uv[..., 0] + 1.0) / camera.width - 1.0,
                     (2.0 * uv[..., 1] + 1.0) / camera.height - 1.0], axis=-1)
    grid[~valid] = OFF_GRID
    return grid.astype(np.float32), valid


def rig_sampling_grids(spec: CylinderSpec, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """Stacked camera_sampling_grid for every camera: grids [N, H_u, W_u, 2] float32, valid [N, H_u, W_u]."""
    out = [camera_sampling_grid(spec, c) for c in rig.cameras]
    return np.stack([g for g, _ in out]), np.stack([v for _, v in out])


def sample_bilinear(image: np.ndarray, grid: np.ndarray, wrap_x: bool = False) -> np.ndarray:
    """Bilinear sampling, numpy; the semantics of torch grid_sample(mode="bilinear", padding_mode="zeros",
    align_corners=False).

    image: [H, W, C]; grid: [..., 2] normalised (x, y), x = (2u + 1)/W - 1 with u the pixel coordinate.
    wrap_x: columns wrap around (equirectangular images) instead of reading zeros left/right of the image.
    Returns [..., C] float32; taps outside the image contribute 0; nan grid entries give 0.
    """
    img = np.asarray(image)
    if img.ndim != 3:
        raise ValueError(f"image must be [H, W, C] (got shape {img.shape})")
    H, W, C = img.shape
    g = np.asarray(grid, dtype=np.float64)
    u = ((g[..., 0] + 1.0) * W - 1.0) / 2.0
    v = ((g[..., 1] + 1.0) * H - 1.0) / 2.0
    bad = ~(np.isfinite(u) & np.isfinite(v))
    u = np.where(bad, -10.0, u)
    v = np.where(bad, -10.0, v)
    u0 = np.floor(u)
    v0 = np.floor(v)
    fu, fv = u - u0, v - v0
    u0 = u0.astype(np.int64)
    v0 = v0.astype(np.int64)
    out = np.zeros(g.shape[:-1] + (C,), dtype=np.float32)
    for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = u0 + du, v0 + dv
        ok = (vv >= 0) & (vv < H)
        if wrap_x:
            uu = np.mod(uu, W)
        else:
            ok &= (uu >= 0) & (uu < W)
        vals = img[np.where(ok, vv, 0), np.where(ok, uu, 0)].astype(np.float32)
        out += np.where(ok, w, 0.0)[..., None].astype(np.float32) * vals
    return out


def sample_bilinear_reference(image: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Slow per-pixel reference of sample_bilinear (zero padding, no wrap), for tests."""
    H, W, C = image.shape
    flat = np.asarray(grid, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(flat), C), dtype=np.float64)
    for k, (x, y) in enumerate(flat):
        u = ((x + 1) * W - 1) / 2
        v = ((y + 1) * H - 1) / 2
        ui, vi = math.floor(u), math.floor(v)
        for uu in (ui, ui + 1):
            for vv in (vi, vi + 1):
                if 0 <= uu < W and 0 <= vv < H:
                    out[k] += (1 - abs(u - uu)) * (1 - abs(v - vv)) * image[vv, uu]
    return out.reshape(np.shape(grid)[:-1] + (C,)).astype(np.float32)


def overlay(per_camera: np.ndarray, order: Order = "cw", channel_axis: int = -1,
            valid: np.ndarray | None = None) -> np.ndarray:
    """The paper's ordered composition of N per-camera cylinder maps.

    per_camera: [N, H_u, W_u, C] (channel_axis=-1) or [N, C, H_u, W_u] (channel_axis=1), any C >= 1.
    gamma(a, b) = b where b != 0 (any channel nonzero) else a, folded over the cameras starting from zeros:
    "cw" (F+) visits cameras 0..N-1, so in an overlap the later camera wins; "ccw" (F-) visits N-1..0, so the
    earlier camera wins. valid: optional [N, H_u, W_u] bool used instead of the "!= 0" test (a pixel of a
    camera counts as present where valid), for maps whose real values may be exactly zero.
    Returns one map shaped like per_camera[0].
    """
    maps = np.asarray(per_camera)
    if maps.ndim < 2:
        raise ValueError(f"per_camera must be [N, ...] with a channel axis (got shape {maps.shape})")
    if order not in ("cw", "ccw"):
        raise ValueError(f"order must be 'cw' or 'ccw' (got {order!r})")
    ax = channel_axis % maps.ndim
    if ax == 0:
        raise ValueError("channel_axis must not be the camera axis 0")
    present = np.any(maps != 0, axis=ax) if valid is None else np.asarray(valid, dtype=bool)
    if present.shape != maps.shape[:ax] + maps.shape[ax + 1:]:
        raise ValueError(f"valid must have shape {maps.shape[:ax] + maps.shape[ax + 1:]} (got {present.shape})")
    present = np.expand_dims(present, ax)
    out = np.zeros_like(maps[0])
    seq = range(len(maps)) if order == "cw" else range(len(maps) - 1, -1, -1)
    for n in seq:
        out = np.where(present[n], maps[n], out)
    return out


def coverage(valid: np.ndarray) -> tuple[float, list[float]]:
    """valid [N, H_u, W_u] -> (fraction of cylinder pixels valid in >= 1 camera, per-camera fractions)."""
    valid = np.asarray(valid, dtype=bool)
    return float(valid.any(axis=0).mean()), [float(v.mean()) for v in valid]


def project_rig(spec: CylinderSpec, rig: Rig, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Sample each camera's image or feature map [h, w, C] onto the cylinder: per-camera maps [N, H_u, W_u, C]
    float32 (0 where invalid) and valid [N, H_u, W_u]. The grids are normalised, so a map of any resolution
    covering the camera's full field of view (e.g. a downsampled backbone feature map) samples correctly;
    validity is decided at the camera's image resolution. All maps need the same channel count C."""
    if len(images) != len(rig.cameras):
        raise ValueError(f"images: need {len(rig.cameras)} images, one per camera (got {len(images)})")
    grids, valid = rig_sampling_grids(spec, rig)
    maps = np.stack([sample_bilinear(img, g, wrap_x=cam.model == "equirectangular")
                     for img, g, cam in zip(images, grids, rig.cameras)])
    maps[~valid] = 0.0
    return maps, valid


# -- frustum-annulus (CPFG) coordinates ---------------------------------------------------------------------------

def frustum_annulus_coords(points: np.ndarray, spec: CylinderSpec, r_min: float, r_max: float) -> np.ndarray:
    """Appendix eq. 25-28: ego points [..., 3] -> normalised (2t - 1, 2s - 1, 2p - 1) [..., 3].

    r, theta about the cylinder axis through spec.centre; dz = z - centre_z;
    t = (r - r_min)/(r_max - r_min), s = (pi - theta)/2pi, p = 1/2 - dz R_u/(Z_u r).
    With align_corners=False these index a CPFG volume laid out [C, H_u (p), W_u (s), K (t)] as torch
    grid_sample (x, y, z) = (t, s, p) of a [N, C, D=H_u, H=W_u, W=K] input. Points on the axis give nan.
    """
    if not 0 <= r_min < r_max:
        raise ValueError(f"r_min, r_max: need 0 <= r_min < r_max (got {r_min}, {r_max})")
    s, p, r = spec._cyl(points)
    t = (r - r_min) / (r_max - r_min)
    return np.stack([2 * t - 1, 2 * s - 1, 2 * p - 1], axis=-1)


def frustum_annulus_points(coords: np.ndarray, spec: CylinderSpec, r_min: float, r_max: float) -> np.ndarray:
    """Inverse of frustum_annulus_coords: normalised [..., 3] -> ego points [..., 3]."""
    if not 0 <= r_min < r_max:
        raise ValueError(f"r_min, r_max: need 0 <= r_min < r_max (got {r_min}, {r_max})")
    c = np.asarray(coords, dtype=np.float64)
    r = r_min + (c[..., 0] + 1) / 2 * (r_max - r_min)
    theta = -np.pi * c[..., 1]  # 2s - 1 = -theta/pi
    p = (c[..., 2] + 1) / 2
    dz = (0.5 - p) * spec.Z_u * r / spec.radius
    return np.stack([spec.centre[0] + r * np.cos(theta), spec.centre[1] + r * np.sin(theta),
                     spec.centre[2] + dz], axis=-1)


# -- background rays ---------------------------------------------------------------------------------------------

def ray_cylinder_intersection(origins: np.ndarray, dirs: np.ndarray, spec: CylinderSpec,
                              paper_v: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Far intersection of rays with the infinite cylinder of radius R_u about the vertical axis through
    spec.centre (appendix "Sampling Background Feature on the Cylinder Plane Feature").

    origins, dirs: [..., 3] ego frame (dirs need not be unit). With o, d relative to the axis in xy:
    a = d_x^2 + d_y^2, b = o_x d_x + o_y d_y, c = o_x^2 + o_y^2 - R_u^2, t = (-b + sqrt(b^2 - a c)) / a (the
    larger root). Returns points [..., 3] and uv [..., 2] with u = -theta/pi (= 2s - 1, the cylinder's
    normalised column), theta = atan2 about the axis, and v = -dz/Z_u (paper_v, the paper's formula verbatim,
    dz = z - centre_z) or v = -2 dz/Z_u = 2p - 1 on the surface (paper_v=False: the cylinder plane's own
    normalised row). Rays that miss (vertical rays, a == 0, or an origin outside the cylinder looking away,
    or a far root t < 0) give nan in points and uv.
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    o, d = np.broadcast_arrays(o, d)
    ox, oy = o[..., 0] - spec.centre[0], o[..., 1] - spec.centre[1]
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = ox * d[..., 0] + oy * d[..., 1]
    c = ox ** 2 + oy ** 2 - spec.radius ** 2
    disc = b * b - a * c
    ok = (a > 0) & (disc >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b + np.sqrt(np.where(ok, disc, 0.0))) / np.where(ok, a, 1.0)
    ok &= t >= 0
    t = np.where(ok, t, np.nan)
    pts = o + t[..., None] * d
    theta = np.arctan2(pts[..., 1] - spec.centre[1], pts[..., 0] - spec.centre[0])
    dz = pts[..., 2] - spec.centre[2]
    v = -dz / spec.Z_u if paper_v else -2.0 * dz / spec.Z_u
    return pts, np.stack([-theta / np.pi, v], axis=-1)
