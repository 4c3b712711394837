"""Ray tracer through lenses: each pixel's true ray (fisheye beyond 90 degrees, f-theta) against an independent
per-pixel reference (the ray from the lens's definition, scalar Python, and the brute-force closest hit)."""

from __future__ import annotations

import math

import numpy as np
from xyzcyl.model_export.data.rigs import pose
from xyzcyl.model_export.data.scene import sample_scene
from xyzcyl.model_export.data.trace import NO_HIT, build_grid, reference_closest_hit, render_view
from xyzcyl.runtime.camera import Camera

FISHEYE = {"model": "opencv_fisheye", "k1": -0.02, "k2": 0.003, "k3": 0.0, "k4": 0.0, "max_angle_deg": 100.0}
FTHETA = {"model": "ftheta", "pixeldist_to_angle_poly": [0.0, 1.0 / 30.0, 2e-5], "max_angle_deg": 80.0}


def _fisheye_ray(cam: Camera, u: float, v: float) -> np.ndarray | None:
    """theta_d = r / f solved for theta by bisection on the definition (scalar, independent of runtime.lenses)."""
    K, k = cam.K, [FISHEYE[n] for n in ("k1", "k2", "k3", "k4")]
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    td = math.hypot(x, y)
    f = lambda t: t * (1 + k[0] * t ** 2 + k[1] * t ** 4 + k[2] * t ** 6 + k[3] * t ** 8)  # noqa: E731
    amax = math.radians(FISHEYE["max_angle_deg"])
    if td > f(amax):
        return None
    lo, hi = 0.0, amax
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < td else (lo, mid)
    th = 0.5 * (lo + hi)
    phi = math.atan2(y, x)
    return np.array([math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), math.cos(th)])


def _ftheta_ray(cam: Camera, u: float, v: float) -> np.ndarray | None:
    ox, oy = u - cam.K[0, 2], v - cam.K[1, 2]
    r = math.hypot(ox, oy)
    c = FTHETA["pixeldist_to_angle_poly"]
    th = c[1] * r + c[2] * r * r
    if th > math.radians(FTHETA["max_angle_deg"]):
        return None
    phi = math.atan2(oy, ox)
    return np.array([math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), math.cos(th)])


def test_lens_views_trace_each_pixels_true_ray():
    scene = sample_scene(11, 2)
    grid = build_grid(scene)
    rng = np.random.default_rng(4)
    checked = outside = 0
    for lens, ray in ((FISHEYE, _fisheye_ray), (FTHETA, _ftheta_ray)):
        for yaw in (0.0, 90.0):
            K = np.array([[30.0, 0, 47.5], [0, 30.0, 35.5], [0, 0, 1]])
            cam = Camera(K=K, width=96, height=72, cam_to_ego=pose((1.5, 0.0, 1.6), yaw), distortion=lens)
            view = render_view(scene, grid, cam, ss=2, shadows=False)
            assert view.valid is not None and view.valid.shape == (72, 96)
            uv = np.stack([rng.integers(0, 96, 30), rng.integers(0, 72, 30)], 1)
            uv = np.concatenate([uv, [[0, 0], [95, 0], [47, 35]]])      # corners beyond the image circle
            for u, v in uv:
                d = ray(cam, float(u), float(v))
                if d is None:
                    assert not view.valid[v, u] and view.depth[v, u] == 0
                    outside += 1
                    continue
                assert view.valid[v, u]
                t_ref, p_ref = reference_closest_hit(scene, cam.position[None], (cam.rotation @ d)[None], True)
                want = 0.0 if p_ref[0] == NO_HIT else t_ref[0]          # unit ray: t = the distance
                np.testing.assert_allclose(view.depth[v, u], want, rtol=1e-5, atol=1e-5)
                checked += 1
            assert not view.rgb[0, 0].any() and not view.rgb[0, 95].any()   # no supersample reaches a corner
    assert checked > 100 and outside >= 4


def test_fisheye_sees_behind_its_image_plane():
    scene = sample_scene(11, 2)
    grid = build_grid(scene)
    K = np.array([[30.0, 0, 47.5], [0, 30.0, 35.5], [0, 0, 1]])
    cam = Camera(K=K, width=96, height=72, cam_to_ego=pose((1.5, 0.0, 1.6), 0.0), distortion=FISHEYE)
    view = render_view(scene, grid, cam, ss=1, shadows=False)
    d = cam.depth_rays()                                                # unit rays: z < 0 beyond 90 degrees
    behind = view.valid & (d[..., 2] < -0.05) & (view.depth > 0)
    assert behind.any()
