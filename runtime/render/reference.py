"""The slow, obviously correct reference renderer: float64 numpy, every pixel against every Gaussian, no tiles.

Same semantics as the fast renderer (culling, footprint cutoff, alpha clamp and threshold, early stop, depth
order with ties broken by Gaussian index). Used by the tests, never by the service."""

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

    rgb = np.zeros((H, W, 3))
    alpha = np.zeros((H, W))
    depth = np.zeros((H, W))
    u = np.arange(W, dtype=np.float64)
    for v in range(H):
        dx = u[:, None] - mx[None, :]                       # [W, G]
        if equirect:
            dx = dx - W * np.floor(dx / W + 0.5)            # nearest copy across the azimuth seam
        dy = float(v) - my[None, :]
        power = 0.5 * ca * dx * dx + cb * dx * dy + 0.5 * cc * dy * dy
        a = np.minimum(ALPHA_MAX, op * np.exp(-power))
        ok = (power >= 0) & (power <= pmax) & (a >= ALPHA_MIN)
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
