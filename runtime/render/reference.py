"""The slow, obviously correct reference renderer: float64 numpy, every pixel against every Gaussian, no tiles.

Same semantics as the fast renderer (culling, footprint cutoff, alpha clamp and threshold, early stop, depth
order with ties broken by Gaussian index). Used by the tests, never by the service.

Cameras with a lens (runtime.lenses) are drawn by casting each pixel's true ray (Camera.pixel_rays' inverse of the
lens, `Lens.unproject`) against the Gaussians: for fisheye and f-theta lenses the fast path linearises the lens at
each mean (its pixel offset from the mean is p - pi(mean), its footprint J Sigma J^T), this one never maps a
Gaussian through the lens (for opencv lenses the fast path computes this same power from each pixel's ray,
lensmap.opencv_plane_footprint). For each Gaussian it takes the plane tangent to the unit sphere at the mean's
direction m (frame e1, e2; projection.lens_reference): in the gnomonic coordinates g = (d.e1, d.e2) / (d.m) of a
ray d, the pinhole camera looking straight at the mean, EWA's footprint is the 3DGS one at its image centre, Jg
Sigma Jg^T with Jg = [e1; e2] / |mean|. A pixel's ray gives its g exactly; the lens enters only as its differential
DL = d(pixel)/dg at the mean, which expresses the low-pass filter (a pixel-space 0.3 px^2) and the cutoffs in the
same units as the fast path: power = 1/2 (DL g)^T (DL Jg Sigma Jg^T DL^T + low_pass I)^-1 (DL g). Against the fast
path's p - pi(mean), DL g differs by the lens's (and the gnomonic map's) curvature: O(|offset|^2 / R_c) pixels for
an offset |offset| from the mean and a radius of curvature R_c of the lens's image of the tangent plane (for a
fisheye, about the distance from the image centre), so the two renders agree the better the smaller the Gaussians
are on the image. Pixels whose ray is NaN (outside a fisheye / f-theta image circle, beyond an opencv lens's fold;
for an opencv lens also a ray beyond its unfolded disc, lensmap.opencv_valid_r2, where a lens that folds within the
image unfolds again) see no Gaussian; rays more than 90 degrees from a mean (d.m <= 0) see none of it."""

from __future__ import annotations

import numpy as np

from .gaussians import Gaussians
from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN, RenderOptions, project_reference
from .result import RenderResult, background_image


def render_reference(gaussians: Gaussians, camera, background=None, **options) -> RenderResult:
    """Same signature and outputs as `render`; float64 inside, float32 out (float64 with `_float64=True`)."""
    keep64 = bool(options.pop("_float64", False))
    opts = RenderOptions.from_kwargs(options)
    W, H = camera.width, camera.height
    bg = background_image(background, H, W).astype(np.float64)
    pr = project_reference(gaussians, camera, opts)
    idx = np.flatnonzero(pr["valid"])
    idx = idx[np.lexsort((idx, pr["depth"][idx].astype(np.float32)))]  # front to back (float32 depth, as the
    #                                                                   fast renderer's keys), ties by index
    mx, my = pr["mean2d"][idx, 0], pr["mean2d"][idx, 1]
    ca, cb, cc = pr["conic"][idx, 0], pr["conic"][idx, 1], pr["conic"][idx, 2]
    op, pmax, z, col = pr["opacity"][idx], pr["pmax"][idx], pr["depth"][idx], pr["colour"][idx]
    equirect = camera.is_equirect
    lens = pr["lens"]
    if lens is not None:
        from ..lenses import unproject

        frame, DL = lens["frame"][idx], lens["DL"][idx]                      # [G, 3, 3], [G, 2, 2]
        vv, uu = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
        rays = unproject(camera.K, camera.distortion, np.stack([uu, vv], axis=-1))[0]   # [H, W, 3] camera frame
        if camera.distortion.model == "opencv":
            # rays beyond the unfolded disc (a lens that folds back within the image) see nothing: no mean is
            # drawn there, and the fast path's footprints are defined on the unfolded part only
            from .lensmap import opencv_valid_r2

            r2v = opencv_valid_r2(tuple(camera.distortion.coeffs))
            with np.errstate(invalid="ignore"):
                rays[rays[..., 0] ** 2 + rays[..., 1] ** 2 > r2v * rays[..., 2] ** 2] = np.nan

    rgb = np.zeros((H, W, 3))
    alpha = np.zeros((H, W))
    depth = np.zeros((H, W))
    u = np.arange(W, dtype=np.float64)
    for v in range(H):
        if lens is None:
            dx = u[:, None] - mx[None, :]                   # [W, G]
            if equirect:
                dx = dx - W * np.floor(dx / W + 0.5)        # nearest copy across the azimuth seam
            dy = float(v) - my[None, :]
        else:
            dx, dy = _ray_offsets(rays[v], frame, DL)
        power = 0.5 * ca * dx * dx + cb * dx * dy + 0.5 * cc * dy * dy
        with np.errstate(invalid="ignore"):
            a = np.minimum(ALPHA_MAX, op * np.exp(-power))
            ok = (power >= 0) & (power <= pmax) & (a >= ALPHA_MIN)     # NaN (no ray, behind): not ok
        a = np.where(ok, a, 0.0)
        t_after = np.cumprod(1.0 - a, axis=1)
        t_before = np.concatenate([np.ones((W, 1)), t_after[:, :-1]], axis=1)
        stop = ok & (t_after <= T_MIN)
        blended = ok & (np.cumsum(stop, axis=1) == 0)       # everything before the first stop
        w = np.where(blended, a * t_before, 0.0)
        t_final = np.prod(np.where(blended, 1.0 - a, 1.0), axis=1)
        rgb[v] = w @ col + t_final[:, None] * bg[v]
        alpha[v] = 1.0 - t_final
        dn = w @ z
        depth[v] = np.where(alpha[v] > 0, dn / np.where(alpha[v] > 0, alpha[v], 1.0), 0.0)
    dt = np.float64 if keep64 else np.float32
    return RenderResult(rgb.astype(dt), alpha.astype(dt), depth.astype(dt))


def _ray_offsets(d: np.ndarray, frame: np.ndarray, DL: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays d [W, 3] (unit, camera frame; NaN: no ray) against G tangent frames (m, e1, e2) [G, 3, 3] -> the pixel
    offsets DL g [W, G] each (dx, dy) of the rays' gnomonic coordinates g about each mean's direction; NaN where
    there is no ray or it makes 90 degrees or more with the mean's direction."""
    proj = np.einsum("wk,gjk->wgj", d, frame)                # [W, G, 3]: d.m, d.e1, d.e2
    dm = proj[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        front = dm > 0
        g1 = np.where(front, proj[..., 1] / np.where(front, dm, 1.0), np.nan)
        g2 = np.where(front, proj[..., 2] / np.where(front, dm, 1.0), np.nan)
    return DL[None, :, 0, 0] * g1 + DL[None, :, 0, 1] * g2, DL[None, :, 1, 0] * g1 + DL[None, :, 1, 1] * g2
