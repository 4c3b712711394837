"""render_backward against central finite differences of the float64 reference renderer."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import look_at, pinhole, random_gaussians
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, RenderOptions, render, render_backward, render_reference
from xyzcyl.runtime.render.projection import project_reference

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")
# 1e-2 relative (the bound). The analytic gradient comes from the float32 forward (polynomial exp,
# relative error ~1e-6) and float64 backward; central differences of the float64 reference with eps = 1e-5
# have truncation error ~eps^2 and round-off ~1e-16 / eps. Observed errors are ~1e-5 relative.
REL = 1e-2
# Gradients much smaller than the loss's typical gradient are dominated by float32 forward noise; they are
# compared against this floor (a fraction of the largest sampled gradient) instead of their own size.
FLOOR = 1e-3


def _smooth_scene(seed, n, degree):
    """Gaussians well inside the image, opacities in 0.1..0.6 (never at the 0.99 clamp), no exact ties."""
    rng = np.random.default_rng(seed)
    return random_gaussians(rng, n, lo=(-1.2, -0.9, 3), hi=(1.2, 0.9, 6), scale=(0.08, 0.4),
                            opacity=(-2.2, 0.4), degree=degree, sh_sigma=0.3)


def _fd_check(g32: Gaussians, cam, bg, n_params=50, seed=0, **options):
    rng = np.random.default_rng(seed)
    H, W = cam.height, cam.width
    w_rgb = rng.normal(size=(H, W, 3))
    w_alpha = rng.normal(size=(H, W))
    w_depth = rng.normal(size=(H, W)) * 0.1
    res = render(g32, cam, bg, **options)
    grads = render_backward(g32, cam, res, w_rgb, w_alpha, w_depth, background=bg, **options)
    g64 = g32.astype(np.float64)

    def loss(g):
        r = render_reference(g, cam, bg, _float64=True, **options)
        return (r.rgb * w_rgb).sum() + (r.alpha * w_alpha).sum() + (r.depth * w_depth).sum()

    picks = []
    for _ in range(n_params):
        name = FIELDS[rng.integers(len(FIELDS))]
        arr = getattr(g64, name)
        picks.append((name, tuple(int(rng.integers(s)) for s in arr.shape)))
    eps = 1e-5
    analytic, numeric = [], []
    for name, idx in picks:
        vals = []
        for sign in (1, -1):
            arrays = {f: getattr(g64, f).copy() for f in FIELDS}
            arrays[name][idx] += sign * eps
            vals.append(loss(Gaussians(**arrays)))
        numeric.append((vals[0] - vals[1]) / (2 * eps))
        analytic.append(getattr(grads, name)[idx])
    analytic, numeric = np.array(analytic), np.array(numeric)
    floor = FLOOR * np.abs(numeric).max()
    rel = np.abs(analytic - numeric) / np.maximum(np.maximum(np.abs(numeric), np.abs(analytic)), floor)
    worst = int(np.argmax(rel))
    assert rel.max() <= REL, (picks[worst], analytic[worst], numeric[worst])
    assert np.abs(numeric).max() > 0
    return grads


def test_backward_matches_finite_differences_sh3():
    g = _smooth_scene(0, 24, degree=3)
    _fd_check(g, pinhole(36, 28, f=26.0), (0.2, 0.3, 0.4), seed=1)


def test_backward_rotated_camera_antialiased_and_clamped_jacobian():
    # some Gaussians sit beyond the 0.3 tan_fov Jacobian clamp (their footprint still reaches the image)
    rng = np.random.default_rng(2)
    inside = _smooth_scene(3, 16, degree=1)
    outside = random_gaussians(rng, 4, lo=(3.4, -0.5, 3), hi=(3.7, 0.5, 3.2), scale=(0.9, 1.2),
                               opacity=(-2, 0), degree=1, sh_sigma=0.3)
    g = Gaussians(*(np.concatenate([getattr(inside, f), getattr(outside, f)]) for f in FIELDS))
    c2w = look_at((0.3, -0.2, -0.1), (0.2, 0.1, 5.0), up=(0, -1, 0))
    cam = pinhole(34, 26, f=24.0, c2w=c2w)
    assert project_reference(g, cam, RenderOptions(antialiased=True))["clamp"][:, 0].sum() == 4
    _fd_check(g, cam, None, seed=4, antialiased=True)


def test_background_gradient_and_argument_checks():
    g = _smooth_scene(5, 10, degree=0)
    cam = pinhole(20, 16, f=14.0)
    bg = np.random.default_rng(6).uniform(size=(16, 20, 3))
    res = render(g, cam, bg)
    d = np.ones((16, 20, 3))
    grads = render_backward(g, cam, res, d, background=bg)
    # dL/dbg = T_final per pixel for L = sum(rgb)
    assert np.allclose(grads.background, (1 - res.alpha)[..., None], atol=1e-6)
    grads3 = render_backward(g, cam, res, d, background=(0.1, 0.2, 0.3))
    assert grads3.background.shape == (3,)
    with pytest.raises(ValueError, match="d_rgb"):
        render_backward(g, cam, res, np.ones((3, 3, 3)))


def test_backward_equirect_across_the_seam():
    # Gaussians all around the camera, some straddling the azimuth seam (straight behind) and some high up
    rng = np.random.default_rng(7)
    ring = random_gaussians(rng, 14, lo=(-4, -1.5, -4), hi=(4, 1.5, 4), scale=(0.15, 0.5), opacity=(-2.2, 0.4),
                            degree=1, sh_sigma=0.3)
    seam = random_gaussians(rng, 4, lo=(-0.3, -0.5, -4), hi=(0.3, 0.5, -3), scale=(0.2, 0.4),
                            opacity=(-2, 0), degree=1, sh_sigma=0.3)
    high = random_gaussians(rng, 2, lo=(-0.8, -4, -0.8), hi=(0.8, -3, 0.8), scale=(0.2, 0.4),
                            opacity=(-2, 0), degree=1, sh_sigma=0.3)
    g = Gaussians(*(np.concatenate([getattr(a, f) for a in (ring, seam, high)]) for f in FIELDS))
    c2w = look_at((0.1, 0.2, -0.1), (0.3, 0.1, 5.0), up=(0, -1, 0))
    _fd_check(g, Camera(model="equirectangular", cam_to_ego=c2w, width=48, height=24), (0.1, 0.1, 0.2), seed=8)
