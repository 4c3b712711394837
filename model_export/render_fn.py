"""Differentiable Gaussian rendering for training: a torch.autograd.Function around the runtime's numba
renderer (xyzcyl.runtime.render.render / render_backward), several target views per call.

    rgb, alpha, depth = render_views(gaussians, cameras)      # [T, 3, H, W], [T, 1, H, W], [T, 1, H, W]
    image = blend(rgb, alpha, background)                       # I = I_fg + (1 - A_fg) * I_bg (model.blend)

The splat render is always over black; the background is blended in torch so its gradient flows to ZNet_bg.
All views of one call must share width and height. The renderer runs on the host CPU whatever the device of
the Gaussians: they are copied to numpy (float32, or float64 when the inputs are float64 -- used by the
finite-difference test), the images come back on the Gaussians' device and dtype, and each gradient on its
input's device and dtype (so a network on CUDA trains through the CPU renderer; `xyzcyl train --device`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, render, render_backward

KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def _np(t: torch.Tensor) -> np.ndarray:
    a = t.detach().cpu().numpy()
    return a if a.dtype == np.float64 else a.astype(np.float32, copy=False)


class RenderViews(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, sh, cameras, options):
        g = Gaussians(_np(means), _np(quats), _np(log_scales), _np(opacity_logits), _np(sh))
        results = [render(g, cam, None, **options) for cam in cameras]
        ctx.g, ctx.results, ctx.cameras, ctx.options = g, results, cameras, options
        ctx.inputs = [(t.device, t.dtype) for t in (means, quats, log_scales, opacity_logits, sh)]
        ref = means
        rgb = torch.as_tensor(np.stack([r.rgb for r in results]), device=ref.device, dtype=ref.dtype)
        alpha = torch.as_tensor(np.stack([r.alpha for r in results]), device=ref.device, dtype=ref.dtype)
        depth = torch.as_tensor(np.stack([r.depth for r in results]), device=ref.device, dtype=ref.dtype)
        return rgb, alpha, depth

    @staticmethod
    def backward(ctx, d_rgb, d_alpha, d_depth):
        acc = None
        for t, (cam, res) in enumerate(zip(ctx.cameras, ctx.results)):
            gr = render_backward(ctx.g, cam, res, _np(d_rgb[t]).astype(np.float32),
                                 _np(d_alpha[t]).astype(np.float32), _np(d_depth[t]).astype(np.float32),
                                 None, **ctx.options)
            parts = [gr.means, gr.quats, gr.log_scales, gr.opacity_logits, gr.sh]
            acc = parts if acc is None else [a + p for a, p in zip(acc, parts)]
        out = [torch.as_tensor(a, device=dev, dtype=dt) for a, (dev, dt) in zip(acc, ctx.inputs)]
        ctx.g = ctx.results = None
        return (*out, None, None)


def render_views(gaussians: dict[str, torch.Tensor], cameras: Sequence[Camera], **options):
    """Render T pinhole views of the same size over black.

    gaussians: dict means [G, 3], quats [G, 4], log_scales [G, 3], opacity_logits [G], sh [G, S, 3] (ego frame).
    Returns rgb [T, 3, H, W], alpha [T, 1, H, W], depth [T, 1, H, W] (camera z, metres; 0 where alpha = 0)."""
    if not cameras:
        raise ValueError("cameras: need at least one target view")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras: all target views of one call must share a size (got {sorted(sizes)})")
    rgb, alpha, depth = RenderViews.apply(*(gaussians[k] for k in KEYS), tuple(cameras), dict(options))
    return rgb.permute(0, 3, 1, 2), alpha.unsqueeze(1), depth.unsqueeze(1)

