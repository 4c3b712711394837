"""Inputs of the network's UCCM lifting, computed from a rig in numpy (no torch: the server uses this too).

The network never sees a camera count in its layers: everything that depends on the rig is an input array
built here, so one set of weights (and one ONNX graph with a dynamic camera axis) serves 5, 6 or 7 cameras.

Per module m in (occupancy, volume, pixel), each with its own cylinder (rho_m, dh_m):
- ``grid_m``    [N, H_u, W_u, 2] float32: normalised (x, y) of each cylinder pixel in camera n's image
  (align_corners=False; off-image pixels get -2, fully outside);
- ``sel_cw_m``, ``sel_ccw_m`` [N, H_u, W_u] float32: one-hot overlay selection over cameras, 0 where no camera
  sees the pixel. cw (F+): the LAST valid camera in order 0..N-1 wins; ccw (F-): the FIRST valid camera wins.
  The network computes F = sum_n sel[n] * grid_sample(feat_n, grid_n). This equals the paper's ordered
  composition gamma (eq. 8) applied to zero-padded samples whenever every valid sample is nonzero, and stays
  right where a real feature is exactly zero (gamma would then let an earlier camera show through).
Pixel module only (depth geometry; see docs/architecture.md "pixel Gaussians"):
- ``pix_rays`` [N, H_u, W_u, 3] float32: (P - c_n) / z_n(P), P the cylinder pixel's surface point, c_n the
  camera centre, z_n(P) P's camera depth (Camera.project_depth: optical-axis z for a pinhole or an opencv lens;
  the distance for a fisheye, f-theta or equirect camera, so points beyond 90 degrees have a depth too). A camera depth D
  sampled at the cylinder pixel then back-projects to X = c_n + D * pix_rays[n] (ego frame, exact);
- ``pix_offsets`` [N, 3]: c_n - centre_pix, so X - centre_pix = pix_offsets[n] + D * pix_rays[n];
- ``focal_n`` [N]: sqrt(fx / W * fy / H) per camera, fx, fy paraxial (``backbone.depth_focal_ref``'s
  focal-aware depth);
- ``pix_dirs`` [k H_u, k W_u, 3]: (P' - centre)/R_u for the upsampled (k = k_i k_o) pixel lattice, i.e. the
  horizontal-unit direction of the cylinder ray: a point at horizontal radius r along it is centre + r * dir.
- ``grid_pixc`` [N, k H_u, k W_u, 2], ``sel_pixc`` [N, k H_u, k W_u]: ``grid_pix`` / ``sel_cw_pix`` of that
  upsampled lattice (the colour path samples the input images there: one colour per pixel Gaussian).
Grid:
- ``voxel_centres`` [L_z, L_y, L_x, 3] ego metres; ``occ_coords`` / ``vol_coords`` [L_z, L_y, L_x, 3]: the
  frustum-annulus coordinates (2t-1, 2s-1, 2p-1) of the voxel centres for the occupancy / volume cylinders
  (runtime.cylinder.frustum_annulus_coords; nan on the axis is replaced by -2: outside).
Background (per target view): ``background_grid`` [H_t, W_t, 2]: (u, v) = (2s-1, 2p-1) where the target
pixel's ray leaves the volume cylinder (ray_cylinder_intersection, paper_v=False); -2 where it misses.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .cylinder import (
    MODULES,
    CylinderSpec,
    frustum_annulus_coords,
    ray_cylinder_intersection,
    rig_sampling_grids,
)
from .rig import Rig

SHORT = {"occupancy": "occ", "volume": "vol", "pixel": "pix"}
OUTSIDE = -2.0


@dataclass(frozen=True)
class LiftingParams:
    """The geometry half of a model config (xyzcyl.model_export.config.ModelConfig), torch-free.

    rho / dh are keyed by module name. Build it from a model config dict with ``from_config_dict``.
    """

    height: int                                   # H_u
    width: int                                    # W_u
    z_range: tuple[float, float]                  # ego metres
    rho: Mapping[str, float]
    dh: Mapping[str, float]
    pc_range: tuple[float, float, float, float, float, float]
    voxel_size: float
    r_min: float
    r_max: float
    pixel_upsample: int = 2                       # k_i * k_o

    @classmethod
    def from_config_dict(cls, d: Mapping[str, Any]) -> LiftingParams:
        try:
            cyl, grid, pix = d["cylinder"], d["grid"], d["pixel"]
            return cls(height=int(cyl["height"]), width=int(cyl["width"]), z_range=tuple(cyl["z_range"]),
                       rho={m: float(cyl[f"rho_{SHORT[m]}"]) for m in MODULES},
                       dh={m: float(cyl[f"dh_{SHORT[m]}"]) for m in MODULES},
                       pc_range=tuple(grid["pc_range"]), voxel_size=float(grid["voxel_size"]),
                       r_min=float(grid["r_min"]), r_max=float(grid["r_max"]),
                       pixel_upsample=int(pix["k_in"]) * int(pix["k_out"]))
        except KeyError as e:
            raise ValueError(f"model config: missing field {e.args[0]!r}") from None

    def spec(self, rig: Rig, module: str) -> CylinderSpec:
        return CylinderSpec.from_rig(rig, z_range=self.z_range, rho=self.rho[module], dh=self.dh[module],
                                     height=self.height, width=self.width)


def overlay_selection(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """valid [N, H, W] bool -> (sel_cw, sel_ccw) [N, H, W] float32 one-hot over cameras (0 where none valid).

    cw: the last valid camera in 0..N-1 wins; ccw: the first valid camera wins."""
    valid = np.asarray(valid, dtype=bool)
    n = valid.shape[0]
    idx = np.arange(n).reshape((n,) + (1,) * (valid.ndim - 1))
    any_valid = valid.any(axis=0)
    last = np.where(valid, idx, -1).max(axis=0)
    first = np.where(valid, idx, n).min(axis=0)
    sel_cw = (idx == last) & any_valid
    sel_ccw = (idx == first) & any_valid
    return sel_cw.astype(np.float32), sel_ccw.astype(np.float32)


def overlay_selection_reference(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slow reference: the gamma fold of runtime.cylinder.overlay applied to one-hot camera indicators."""
    valid = np.asarray(valid, dtype=bool)
    n = valid.shape[0]
    out = []
    for order in (range(n), range(n - 1, -1, -1)):
        sel = np.zeros(valid.shape, dtype=np.float32)
        for cam in order:  # gamma(a, b) = b where camera `cam` is present, else a
            onehot = np.zeros(valid.shape, dtype=np.float32)
            onehot[cam] = 1.0
            sel = np.where(valid[cam][None], onehot, sel)
        out.append(sel)
    return out[0], out[1]


def module_inputs(rig: Rig, spec: CylinderSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(grids [N, H_u, W_u, 2], sel_cw [N, H_u, W_u], sel_ccw [N, H_u, W_u]) for one module's cylinder."""
    grids, valid = rig_sampling_grids(spec, rig)
    sel_cw, sel_ccw = overlay_selection(valid)
    return grids.astype(np.float32), sel_cw, sel_ccw


def depth_rays(rig: Rig, spec: CylinderSpec) -> tuple[np.ndarray, np.ndarray]:
    """(pix_rays [N, H_u, W_u, 3], pix_offsets [N, 3]) float32 -- see the module docstring."""
    P = spec.points()                                     # [H, W, 3]
    rays, offs = [], []
    for cam in rig.cameras:
        _, z, in_front = cam.project_depth(P)
        zs = np.where(in_front, z, 1.0)
        rays.append(np.where(in_front[..., None], (P - cam.position) / zs[..., None], 0.0))
        offs.append(cam.position - spec.centre)
    return np.stack(rays).astype(np.float32), np.stack(offs).astype(np.float32)


def focal_n(rig: Rig) -> np.ndarray:
    """[N] float32: each camera's normalised focal length sqrt(fx / W * fy / H), pixels per radian over the image
    size (unchanged by resizing the image; the focal-aware depth head scales its depth by it). fx, fy are the
    paraxial focal lengths (Camera.paraxial_focal: K's for a pinhole, an opencv or a fisheye lens; an f-theta
    lens's polynomial slope at the axis), the magnification at the image centre. An equirectangular camera has
    W / (2 pi) and H / pi pixels per radian: 1 / (pi sqrt 2)."""
    out = []
    for c in rig.cameras:
        if c.model == "equirectangular":
            out.append(1.0 / (math.pi * math.sqrt(2.0)))
        else:
            fx, fy = (c.K[0, 0], c.K[1, 1]) if c.distortion is None else c.paraxial_focal
            out.append(math.sqrt(fx / c.width * fy / c.height))
    return np.array(out, np.float32)


def pixel_directions(spec: CylinderSpec, k: int) -> np.ndarray:
    """[k H_u, k W_u, 3] float32: (P - centre)/R_u at the centres of the k-times upsampled cylinder lattice
    (pixel i' of the fine lattice is at coarse row (i' + 1/2)/k - 1/2, same for columns)."""
    ii = (np.arange(k * spec.height) + 0.5) / k - 0.5
    jj = (np.arange(k * spec.width) + 0.5) / k - 0.5
    i, j = np.meshgrid(ii, jj, indexing="ij")
    return ((spec.pixel_to_point(i, j) - spec.centre) / spec.radius).astype(np.float32)


def fine_module_inputs(rig: Rig, spec: CylinderSpec, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(grid [N, k H_u, k W_u, 2], sel_cw [N, k H_u, k W_u]) of the k-times upsampled lattice of ``spec``: the
    cylinder with k H_u x k W_u pixels, whose pixel i' sits at coarse row (i' + 1/2)/k - 1/2 (as pix_dirs)."""
    g, cw, _ = module_inputs(rig, dataclasses.replace(spec, height=k * spec.height, width=k * spec.width))
    return g, cw


def voxel_centres(pc_range, voxel_size: float) -> np.ndarray:
    """[L_z, L_y, L_x, 3] ego metres: centres of the occupancy grid's voxels (z slowest, x fastest)."""
    x0, y0, z0, x1, y1, z1 = (float(v) for v in pc_range)
    n = [round((b - a) / voxel_size) for a, b in ((x0, x1), (y0, y1), (z0, z1))]
    xs = x0 + (np.arange(n[0]) + 0.5) * voxel_size
    ys = y0 + (np.arange(n[1]) + 0.5) * voxel_size
    zs = z0 + (np.arange(n[2]) + 0.5) * voxel_size
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    return np.stack([x, y, z], axis=-1).astype(np.float32)


def voxel_coords(centres: np.ndarray, spec: CylinderSpec, r_min: float, r_max: float) -> np.ndarray:
    """Frustum-annulus coordinates [..., 3] float32 of voxel centres; nan (on the axis) -> -2 (outside)."""
    c = frustum_annulus_coords(centres, spec, r_min, r_max)
    return np.where(np.isfinite(c), c, OUTSIDE).astype(np.float32)


def background_grid(spec: CylinderSpec, K: np.ndarray, cam_to_ego: np.ndarray, width: int,
                    height: int) -> np.ndarray:
    """[H, W, 2] float32 (u, v) = (2s-1, 2p-1) where each target pixel's ray (OpenCV pinhole K [3, 3] pixels,
    cam_to_ego [4, 4]) leaves the cylinder; rays that miss get -2 in both (outside)."""
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(cam_to_ego, dtype=np.float64)
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) @ T[:3, :3].T
    _, uv = ray_cylinder_intersection(np.broadcast_to(T[:3, 3], d.shape), d, spec, paper_v=False)
    return np.where(np.isfinite(uv), uv, OUTSIDE).astype(np.float32)


def build_lifting_inputs(rig: Rig, params: LiftingParams) -> dict[str, np.ndarray]:
    """All rig-dependent network inputs (float32 arrays; names as in the module docstring), plus each module's
    cylinder as ``spec_<m>`` = [c_x, c_y, c_z, R_u, z_min, z_max] (float32 [6])."""
    out: dict[str, np.ndarray] = {}
    specs = {m: params.spec(rig, m) for m in MODULES}
    for m, spec in specs.items():
        g, cw, ccw = module_inputs(rig, spec)
        s = SHORT[m]
        out[f"grid_{s}"], out[f"sel_cw_{s}"], out[f"sel_ccw_{s}"] = g, cw, ccw
        out[f"spec_{s}"] = np.array([*spec.centre, spec.radius, spec.z_min, spec.z_max], dtype=np.float32)
    out["pix_rays"], out["pix_offsets"] = depth_rays(rig, specs["pixel"])
    out["focal_n"] = focal_n(rig)
    out["pix_dirs"] = pixel_directions(specs["pixel"], params.pixel_upsample)
    out["grid_pixc"], out["sel_pixc"] = fine_module_inputs(rig, specs["pixel"], params.pixel_upsample)
    centres = voxel_centres(params.pc_range, params.voxel_size)
    out["voxel_centres"] = centres
    out["occ_coords"] = voxel_coords(centres, specs["occupancy"], params.r_min, params.r_max)
    out["vol_coords"] = voxel_coords(centres, specs["volume"], params.r_min, params.r_max)
    return out


def spec_from_array(a: np.ndarray, height: int, width: int) -> CylinderSpec:
    """Inverse of the ``spec_<m>`` packing."""
    a = np.asarray(a, dtype=np.float64)
    return CylinderSpec(centre=a[:3], radius=float(a[3]), z_min=float(a[4]), z_max=float(a[5]), height=height,
                        width=width)
