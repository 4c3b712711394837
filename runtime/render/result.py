"""Render outputs and gradients."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RenderResult:
    rgb: np.ndarray     # [H, W, 3] float32, linear 0..1 (not clipped above 1)
    alpha: np.ndarray   # [H, W] float32 accumulated opacity 1 - T
    depth: np.ndarray   # [H, W] float32 metres: sum(w z) / alpha, 0 where alpha == 0
    state: Any = field(default=None, repr=False, compare=False)  # what render_backward needs (fast path only)


@dataclass(frozen=True)
class GaussianGrads:
    """dL/d(raw parameter), float64, same shapes as the Gaussians' arrays."""
    means: np.ndarray           # [N, 3]
    quats: np.ndarray           # [N, 4]
    log_scales: np.ndarray      # [N, 3]
    opacity_logits: np.ndarray  # [N]
    sh: np.ndarray              # [N, K, 3]
    background: np.ndarray | None = None  # [3] for an RGB background, [H, W, 3] for an image, None for black


def background_image(background, height: int, width: int) -> np.ndarray:
    """None -> black; an RGB triple -> constant; an image [H, W, 3]. Returns [H, W, 3] float32 (C-contiguous)."""
    if background is None:
        return np.zeros((height, width, 3), np.float32)
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape == (3,):
        out = np.empty((height, width, 3), np.float32)
        out[:] = bg
    elif bg.shape == (height, width, 3):
        out = np.ascontiguousarray(bg)
    else:
        raise ValueError(f"background: expected None, [3] or [{height}, {width}, 3], got {list(bg.shape)}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"background: {int(np.count_nonzero(~np.isfinite(out)))} non-finite values")
    return out
