"""Ray tracer: determinism, depth on surfaces, agreement with the brute-force numpy reference."""

from __future__ import annotations

import numpy as np
from xyzcyl.model_export.data.occupancy import signed_distance
from xyzcyl.model_export.data.scene import ELL, sample_scene
from xyzcyl.model_export.data.synth import render_scene
from xyzcyl.model_export.data.trace import NO_HIT, build_grid, reference_closest_hit, render_view
from xyzcyl.runtime.camera import Camera

SURFACE_TOL = 0.01  # metres: the bound for "lies on a primitive surface"


def _views(data):
    yield data.inputs, data.input_views, True
    for setting, cams in data.targets.items():
        yield cams, data.target_views[setting], setting != "ego-inward"


def _unproject(cam, uv, depth):
    x = (uv[:, 0] - cam.K[0, 2]) / cam.K[0, 0]
    y = (uv[:, 1] - cam.K[1, 2]) / cam.K[1, 1]
    pc = np.stack([x * depth, y * depth, depth], 1)
    return pc @ cam.cam_to_ego[:3, :3].T + cam.cam_to_ego[:3, 3]


def _surface_distance(scene, pts, skip_ego):
    """[N] an upper bound of the distance of each point to the nearest primitive surface or the ground."""
    d = signed_distance(scene, pts)  # exact |.| for boxes and cylinders
    g = scene.geo[None]
    r = pts[:, None, :] - g[..., :3]
    c, s = g[..., 6], g[..., 7]
    lx = r[..., 0] * c + r[..., 1] * s
    ly = -r[..., 0] * s + r[..., 1] * c
    h = g[..., 3:6]
    # ellipsoid shell: p within SURFACE_TOL of the surface if |p/(r+tol)| <= 1 <= |p/(r-tol)|
    outer = (lx / (h[..., 0] + SURFACE_TOL)) ** 2 + (ly / (h[..., 1] + SURFACE_TOL)) ** 2 + (
        r[..., 2] / (h[..., 2] + SURFACE_TOL)) ** 2
    inner = (lx / (h[..., 0] - SURFACE_TOL)) ** 2 + (ly / (h[..., 1] - SURFACE_TOL)) ** 2 + (
        r[..., 2] / (h[..., 2] - SURFACE_TOL)) ** 2
    ell_ok = np.where((outer <= 1) & (inner >= 1), 0.0, np.inf)
    dist = np.where(scene.kind[None] == ELL, ell_ok, np.abs(d))
    if skip_ego:
        dist = np.where(scene.ego[None], np.inf, dist)
    return np.minimum(dist.min(1), np.abs(pts[:, 2]))


def test_render_is_deterministic(tiny_cfg, tiny_scenes):
    again = render_scene(tiny_cfg, 0)
    first = tiny_scenes[0]
    for a, b in zip(first.input_views + first.target_views["ego-inward"],
                    again.input_views + again.target_views["ego-inward"]):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.semantic, b.semantic)
    for tag in first.occupancy:
        assert np.array_equal(first.occupancy[tag], again.occupancy[tag])
    assert not np.array_equal(first.input_views[0].rgb, tiny_scenes[1].input_views[0].rgb)


def test_depth_lies_on_surfaces_and_matches_reference(tiny_scenes):
    rng = np.random.default_rng(0)
    n_checked = 0
    for data in tiny_scenes:
        for cams, views, skip_ego in _views(data):
            for cam, view in zip(cams, views):
                uv = np.stack([rng.integers(0, cam.width, 40), rng.integers(0, cam.height, 40)], 1)
                depth = view.depth[uv[:, 1], uv[:, 0]].astype(np.float64)
                hit = depth > 0
                assert np.array_equal(hit, ~view.sky[uv[:, 1], uv[:, 0]])
                pts = _unproject(cam, uv[hit].astype(np.float64), depth[hit])
                dist = _surface_distance(data.scene, pts, skip_ego)
                assert np.all(dist <= SURFACE_TOL), dist.max()
                # brute force over all primitives: same first hit, and sky rays hit nothing at all
                o = np.repeat(cam.cam_to_ego[None, :3, 3], len(uv), 0)
                dc = np.stack([(uv[:, 0] - cam.K[0, 2]) / cam.K[0, 0], (uv[:, 1] - cam.K[1, 2]) / cam.K[1, 1],
                               np.ones(len(uv))], 1)
                t_ref, p_ref = reference_closest_hit(data.scene, o, dc @ cam.cam_to_ego[:3, :3].T, skip_ego)
                assert np.all(p_ref[~hit] == NO_HIT)
                # float32 storage: relative 1e-6; 1e-5 leaves room for the kernel's fastmath rounding
                np.testing.assert_allclose(depth[hit], t_ref[hit], rtol=1e-5, atol=1e-5)
                n_checked += int(hit.sum())
    assert n_checked > 500


def test_grid_traversal_matches_brute_force_on_many_rays():
    scene = sample_scene(11, 2)
    grid = build_grid(scene)
    rng = np.random.default_rng(1)
    # random rays from street-level points in all directions, through a tiny 1-pixel camera each
    for _ in range(60):
        eye = np.array([rng.uniform(-30, 30), rng.uniform(-2, 2), rng.uniform(0.5, 12.0)])
        yaw, pitch = rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2)
        f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        x = np.cross(f, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(f, x), f, eye
        K = np.array([[40.0, 0, 3.5], [0, 40.0, 2.5], [0, 0, 1]])
        v = render_view(scene, grid, Camera(K=K, cam_to_ego=T, width=8, height=6), ss=1, skip_ego=True, shadows=False)
        uu, vv = np.meshgrid(np.arange(8.0), np.arange(6.0))
        dc = np.stack([(uu.ravel() - 3.5) / 40, (vv.ravel() - 2.5) / 40, np.ones(48)], 1)
        t_ref, p_ref = reference_closest_hit(scene, np.repeat(eye[None], 48, 0), dc @ T[:3, :3].T, True)
        t_ref = np.where(p_ref == NO_HIT, 0.0, t_ref)
        np.testing.assert_allclose(v.depth.ravel(), t_ref, rtol=1e-5, atol=1e-5)


def test_ego_is_hidden_from_rig_views_and_shown_inward(tiny_scenes):
    for data in tiny_scenes:
        for view in data.input_views + data.target_views["ego-forward"]:
            assert not np.any(view.semantic == 10)
        shown = sum(int(np.sum(v.semantic == 10)) for v in data.target_views["ego-inward"])
        assert shown > 0
