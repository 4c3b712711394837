"""Scene builders shared by the renderer tests."""

from __future__ import annotations

import numpy as np
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians


def random_gaussians(rng, n, lo=(-3, -2, 2), hi=(3, 2, 10), scale=(0.05, 0.5), opacity=(-3.0, 3.0), degree=0,
                     sh_sigma=0.5) -> Gaussians:
    """float32 values (so float32 and float64 renders see exactly the same parameters)."""
    means = rng.uniform(lo, hi, size=(n, 3))
    k = (degree + 1) ** 2
    return Gaussians(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                     np.log(rng.uniform(*scale, size=(n, 3))).astype(np.float32),
                     rng.uniform(*opacity, size=n).astype(np.float32),
                     (rng.normal(size=(n, k, 3)) * sh_sigma).astype(np.float32))


def look_at(eye, target, up=(0, 0, 1)) -> np.ndarray:
    """cam_to_world for an OpenCV camera at eye looking at target (world z up)."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, d, f, eye
    return m


def pinhole(width=83, height=61, f=60.0, cx=None, cy=None, c2w=None) -> Camera:
    cx = (width - 1) / 2 + 0.3 if cx is None else cx
    cy = (height - 1) / 2 - 0.2 if cy is None else cy
    K = np.array([[f, 0, cx], [0, f * 1.05, cy], [0, 0, 1.0]])
    return Camera(K=K, cam_to_ego=np.eye(4) if c2w is None else c2w, width=width, height=height)


def concat(*gs: Gaussians) -> Gaussians:
    return Gaussians(*(np.concatenate([getattr(g, f) for g in gs]) for f in
                       ("means", "quats", "log_scales", "opacity_logits", "sh")))


def sphere_shell(radius: float, centre, n: int, rng=None) -> Gaussians:
    """n*n opaque flat discs tangent to a sphere about `centre` (a Fibonacci lattice; sigma = the lattice spacing,
    thickness 5 mm), facing the centre: a camera there sees the surface at `radius` along every ray. SH degree 0:
    grey, or a random colour per disc with rng (so an image compares every disc, not only the coverage)."""
    k = np.arange(n * n) + 0.5
    z = 1 - 2 * k / (n * n)
    a = np.pi * (3 - np.sqrt(5)) * k
    d = np.stack([np.sqrt(1 - z * z) * np.cos(a), np.sqrt(1 - z * z) * np.sin(a), z], 1)
    means = (np.asarray(centre, np.float64) + radius * d).astype(np.float32)
    step = radius * np.sqrt(4 * np.pi / (n * n))
    axis = np.cross([0.0, 0.0, 1.0], d)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.arctan2(s[:, 0], d[:, 2])
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), [1.0, 0.0, 0.0])
    quats = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], 1).astype(np.float32)
    log_scales = np.log(np.tile([[step, step, 0.005]], (len(means), 1))).astype(np.float32)
    sh = np.full((len(means), 1, 3), 0.5, np.float32) if rng is None else \
        rng.uniform(-1.5, 1.5, (len(means), 1, 3)).astype(np.float32)
    return Gaussians(means, quats, log_scales, np.full(len(means), 8.0, np.float32), sh)
