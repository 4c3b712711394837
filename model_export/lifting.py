"""UCCM lifting and CPFG sampling in torch (the numpy inputs come from xyzcyl.runtime.lifting).

Shapes: per-camera features ``feats`` [N, C, h, w]; sampling grids [N, H_u, W_u, 2]; selections [N, H_u, W_u].
Nothing here has a layer whose size depends on N.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from xyzcyl.runtime.lifting import LiftingParams, build_lifting_inputs
from xyzcyl.runtime.rig import Rig


def to_torch(inputs: dict[str, np.ndarray], device=None, dtype=torch.float32) -> dict[str, torch.Tensor]:
    """Tensors of ``inputs``. A read-only array (the runtime's lifting cache hands those out) is copied: torch would
    share its memory, and an in-place op on the tensor would write into the cache."""
    def tensor(v: np.ndarray) -> torch.Tensor:
        v = np.ascontiguousarray(v)
        return torch.as_tensor(v if v.flags.writeable else v.copy(), device=device, dtype=dtype)

    return {k: tensor(v) for k, v in inputs.items()}


def rig_inputs(rig: Rig, cfg, device=None) -> dict[str, torch.Tensor]:
    """Torch lifting inputs for ``rig`` under a ModelConfig ``cfg``."""
    return to_torch(build_lifting_inputs(rig, LiftingParams.from_config_dict(cfg.to_dict())), device)


def sample_cameras(feats: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """[N, C, h, w] x [N, H_u, W_u, 2] -> [N, C, H_u, W_u] bilinear, zero padding, align_corners=False."""
    return F.grid_sample(feats, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def overlay_sum(samples: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    """F = sum_n sel[n] * samples[n]: [N, C, H, W] x [N, H, W] -> [1, C, H, W]."""
    return (samples * sel.unsqueeze(1)).sum(dim=0, keepdim=True)


def lift(feats: torch.Tensor, grid: torch.Tensor, sel_cw: torch.Tensor, sel_ccw: torch.Tensor):
    """(F+, F-) [1, C, H_u, W_u] each, from per-camera features."""
    s = sample_cameras(feats, grid)
    return overlay_sum(s, sel_cw), overlay_sum(s, sel_ccw)


def wrap_pad_w(x: torch.Tensor, dim: int, pad: int = 1) -> torch.Tensor:
    """Circular padding of ``pad`` entries along ``dim`` (the theta axis)."""
    n = x.shape[dim]
    return torch.cat([x.narrow(dim, n - pad, pad), x, x.narrow(dim, 0, pad)], dim=dim)


def sample_plane_wrapped(plane: torch.Tensor, grid: torch.Tensor, padding_mode: str = "zeros") -> torch.Tensor:
    """Bilinear sampling of cylinder planes [B, C, H, W] at grid [B, h, w, 2] (x = 2s-1, y = 2p-1), theta
    wrapping around: the plane is padded circularly by one column and x rescaled by W/(W+2) (exact for
    align_corners=False: pixel u -> u+1)."""
    W = plane.shape[-1]
    g = torch.stack([grid[..., 0] * (W / (W + 2)), grid[..., 1]], dim=-1)
    return F.grid_sample(wrap_pad_w(plane, -1), g, mode="bilinear", padding_mode=padding_mode, align_corners=False)


def cpfg(feature: torch.Tensor, k: int) -> torch.Tensor:
    """CPFG reshape: [1, K*D, H, W] -> [1, D, K, H, W] (channel c = d*K + k)."""
    b, c, h, w = feature.shape
    return feature.reshape(b, c // k, k, h, w)


def sample_cpfg(group: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Trilinear sampling of a CPFG [1, D, K, H_u, W_u] at frustum-annulus coords [M, 3] = (2t-1, 2s-1, 2p-1)
    (runtime.cylinder.frustum_annulus_coords), theta wrapping -> [M, D]. Zero outside the annulus/frustum."""
    vol = group.permute(0, 1, 3, 4, 2)                     # [1, D, H(p), W(s), K(t)] as runtime.cylinder documents
    W = vol.shape[3]
    vol = wrap_pad_w(vol, 3)
    g = torch.stack([coords[:, 0], coords[:, 1] * (W / (W + 2)), coords[:, 2]], dim=-1)
    out = F.grid_sample(vol, g.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.view(vol.shape[1], -1).t()


def frustum_coords_torch(points: torch.Tensor, spec: torch.Tensor, r_min: float, r_max: float) -> torch.Tensor:
    """Torch twin of runtime.cylinder.frustum_annulus_coords: points [..., 3] ego, spec [6] =
    (c_x, c_y, c_z, R_u, z_min, z_max) -> (2t-1, 2s-1, 2p-1) [..., 3]; points within 1e-6 m of the axis give p
    from r = 1e-6 (far outside) instead of nan."""
    d = points - spec[:3]
    r = torch.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + 1e-12).clamp_min(1e-6)
    theta = torch.atan2(d[..., 1], d[..., 0])
    t = (r - r_min) / (r_max - r_min)
    zu = spec[5] - spec[4]
    p = 0.5 - d[..., 2] * spec[3] / (zu * r)
    return torch.stack([2 * t - 1, -theta / np.pi, 2 * p - 1], dim=-1)
