"""The plain numba peer renderer of benchmarks/peer_renderer.py renders the right picture: the same as our
reference where the two footprints cannot differ, and the same as an independent numpy implementation of
3DGS's tile footprint where they do."""

from __future__ import annotations

import math

import numpy as np
import peer_renderer as P  # benchmarks/peer_renderer.py (pyproject.toml: pytest's pythonpath)
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, RenderOptions, render, render_reference
from xyzcyl.runtime.render.projection import project_reference

# 1e-4 as in tests/runtime/render: the peer projects in float64, stores float32 features (3DGS) and blends in
# float64; a single missed or extra Gaussian changes a pixel by more than 1/255 x its colour (> 1e-3 here).
TOL = 1e-4
DEPTH_REL = 1e-5   # depth is sum(w z) / alpha in metres (2-10 m here): the same relative error, scaled
BG = (0.2, 0.3, 0.4)


def _scene(seed: int, n: int, logit_range: tuple[float, float]) -> Gaussians:
    """n random Gaussians 2-10 m in front of the camera, scales 5-50 cm, SH degree 0, float32."""
    rng = np.random.default_rng(seed)
    means = rng.uniform((-3, -2, 2), (3, 2, 10), size=(n, 3))
    return Gaussians(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                     np.log(rng.uniform(0.05, 0.5, size=(n, 3))).astype(np.float32),
                     rng.uniform(*logit_range, size=n).astype(np.float32),
                     rng.normal(scale=0.5, size=(n, 1, 3)).astype(np.float32))


def _camera() -> Camera:
    """64x48, off-centre principal point and fx != fy (so x / y mix-ups show)."""
    K = np.array([[40.0, 0, 31.8], [0, 42.0, 23.3], [0, 0, 1]])
    return Camera(K=K, cam_to_ego=np.eye(4), width=64, height=48)


def _tile_footprint_reference(g: Gaussians, camera: Camera, background) -> tuple[np.ndarray, ...]:
    """3DGS's forward in float64 numpy, per pixel against every Gaussian: a Gaussian is evaluated on every
    pixel of every 16x16 tile its 3-sigma circle (ceil(3 sqrt(largest eigenvalue of cov2d))) touches, with no
    cut at the ellipse; alpha = min(0.99, o exp(-power)), skipped below 1/255, the pixel stops before a
    Gaussian that would bring T below 1e-4. The projection is the project's float64 `project_reference`
    (same EWA covariance, low-pass and Jacobian clamp).
    Returns rgb [H, W, 3], alpha [H, W], depth [H, W] (float64)."""
    W, H = camera.width, camera.height
    pr = project_reference(g, camera, RenderOptions())
    cov2, det = pr["cov2"], pr["det"]
    mid = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
    rad = np.ceil(3.0 * np.sqrt(mid + np.sqrt(np.maximum(0.1, mid * mid - det))))
    mx, my = pr["mean2d"][:, 0], pr["mean2d"][:, 1]
    ntx, nty = math.ceil(W / 16), math.ceil(H / 16)
    tx0, tx1 = np.clip(np.floor((mx - rad) / 16), 0, ntx), np.clip(np.ceil((mx + rad) / 16), 0, ntx)
    ty0, ty1 = np.clip(np.floor((my - rad) / 16), 0, nty), np.clip(np.ceil((my + rad) / 16), 0, nty)
    idx = np.flatnonzero(pr["valid"] & (tx1 > tx0) & (ty1 > ty0))
    idx = idx[np.lexsort((idx, pr["depth"][idx].astype(np.float32)))]  # front to back by float32 depth (the
    #                                                                   peer's sort keys), ties by index
    mx, my, tx0, tx1, ty0, ty1 = mx[idx], my[idx], tx0[idx], tx1[idx], ty0[idx], ty1[idx]
    ca, cb, cc = pr["conic"][idx, 0], pr["conic"][idx, 1], pr["conic"][idx, 2]
    op, z, col = pr["opacity"][idx], pr["depth"][idx], pr["colour"][idx]
    u = np.arange(W, dtype=np.float64)
    in_x = ((u // 16)[:, None] >= tx0[None]) & ((u // 16)[:, None] < tx1[None])      # [W, G]
    bg = np.broadcast_to(np.asarray(background, np.float64), (H, W, 3))
    rgb, alpha, depth = np.zeros((H, W, 3)), np.zeros((H, W)), np.zeros((H, W))
    for v in range(H):
        dx, dy = u[:, None] - mx[None], float(v) - my[None]
        power = 0.5 * ca * dx * dx + cb * dx * dy + 0.5 * cc * dy * dy
        a = np.minimum(0.99, op * np.exp(-power))
        ok = in_x & ((v // 16 >= ty0) & (v // 16 < ty1))[None] & (a >= 1.0 / 255.0)
        a = np.where(ok, a, 0.0)
        t_after = np.cumprod(1.0 - a, axis=1)
        blended = ok & (np.cumsum(ok & (t_after < 1e-4), axis=1) == 0)
        t_before = np.concatenate([np.ones((W, 1)), t_after[:, :-1]], axis=1)
        w = np.where(blended, a * t_before, 0.0)
        t_final = np.prod(np.where(blended, 1.0 - a, 1.0), axis=1)
        rgb[v] = w @ col + t_final[:, None] * bg[v]
        alpha[v] = 1.0 - t_final
        depth[v] = np.where(alpha[v] > 0, (w @ z) / np.where(alpha[v] > 0, alpha[v], 1.0), 0.0)
    return rgb, alpha, depth


def _assert_close(rgb, alpha, depth, ref_rgb, ref_alpha, ref_depth) -> None:
    assert np.abs(rgb - ref_rgb).max() <= TOL
    assert np.abs(alpha - ref_alpha).max() <= TOL
    assert np.all(np.abs(depth - ref_depth) <= TOL + DEPTH_REL * ref_depth)
    assert np.array_equal(alpha == 0, ref_alpha == 0)


def test_low_opacity_scene_equals_the_reference():
    """With every opacity below 0.35, o exp(-4.5) < 1/255: beyond the 3-sigma ellipse the peer's alphas are
    all skipped, so its tile footprint and our ellipse cut give the same picture up to rounding. 2500
    overlapping Gaussians: 20-30 layers deep in places (alpha > 0.999), thin elsewhere."""
    g = _scene(0, 2500, (-4.0, -0.65))                     # sigmoid(-0.65) = 0.343
    cam = _camera()
    rgb, alpha, depth = P.render_peer(g, cam, BG)
    ref = render_reference(g, cam, BG)
    assert ref.alpha.max() > 0.999 and ref.alpha.min() < 0.6
    _assert_close(rgb, alpha, depth, ref.rgb, ref.alpha, ref.depth)
    # the box radius (gsplat >= 1.5) covers the same ellipse: the same picture
    _assert_close(*P.render_peer(g, cam, BG, radius="box"), ref.rgb, ref.alpha, ref.depth)


def test_high_opacity_scene_follows_the_tile_footprint():
    """Opacities up to the 0.99 clamp: the peer leaks faint alphas (<= 0.99 exp(-4.5) = 0.011) beyond 3 sigma
    inside the tiles a Gaussian's radius touches, as 3DGS does. It must match a numpy implementation of
    exactly that to 1e-4, and differ from our ellipse-cut renderer only by those faint alphas."""
    g = _scene(1, 400, (-3.0, 6.0))
    cam = _camera()
    rgb, alpha, depth = P.render_peer(g, cam, BG)
    ref_rgb, ref_alpha, ref_depth = _tile_footprint_reference(g, cam, BG)
    assert ref_alpha.max() > 0.999                          # the stop rule and the alpha clamp are exercised
    _assert_close(rgb, alpha, depth, ref_rgb, ref_alpha, ref_depth)
    ours = render(g, cam, BG)
    diff = np.abs(rgb - ours.rgb)
    assert diff.max() > 1e-3                                # the footprints really differ in this scene
    assert diff.mean() < 2e-3 and P.psnr(rgb, ours.rgb) > 45.0
