"""The detail layer on cameras with lenses (issue 28 step 2): cells on each pixel's true ray, sized by the lens's
local footprint; the fusion (cull, carve) through the lens against its references; camera_detail on a fisheye."""

from __future__ import annotations

import math

import numpy as np
import pytest
from xyzcyl.runtime.detail import (
    CameraDetail,
    DetailOptions,
    camera_detail,
    carve_against,
    carve_against_reference,
    carve_details,
    carve_details_both,
    carve_details_reference,
    cell_footprint,
    cell_gaussians,
    cell_gaussians_reference,
    cell_geometry,
    cull_covered,
    cull_covered_reference,
    grid_camera,
    sphere_depth,
)
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.rig import Rig, ring_rig
from xyzcyl.runtime.rotations import quat_to_rotmat

FISHEYE = {"model": "opencv_fisheye", "k1": -0.03, "k2": 0.004, "k3": -2e-4, "k4": 0.0, "max_angle_deg": 100.0}
FTHETA = {"model": "ftheta", "reference_poly": "angle_to_pixeldist", "angle_to_pixeldist_poly": [0.0, 21.0, 0.0, -1.5],
          "max_angle_deg": 95.0, "linear_cde": [1.01, 0.002, -0.001]}
OPENCV = [-0.2, 0.05, 0.001, -0.002]
LENSES = pytest.mark.parametrize("lens", [FISHEYE, FTHETA, OPENCV], ids=["fisheye", "ftheta", "opencv"])


def lens_rig(lens, n: int = 4, width: int = 96, height: int = 64, f: float = 24.0) -> Rig:
    base = ring_rig(n, hfov_deg=90.0, width=width, height=height, ring_radius=0.6)
    if lens is OPENCV:
        f = 40.0
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Rig(cameras=tuple(c.replace(K=K, distortion=lens) for c in base.cameras))


@LENSES
def test_cells_sit_on_their_true_rays(lens):
    """Each cell's centre projects back (Camera.project, through the lens) onto its pixel within 0.01 px, at its
    depth; cells beyond 90 degrees too; no cell outside the image circle."""
    cam = lens_rig(lens).cameras[0]
    geo = cell_geometry(cam)
    rng = np.random.default_rng(1)
    depth = rng.uniform(2.0, 20.0, (cam.height, cam.width)).astype(np.float32)
    keep = geo.has_ray & (rng.random(depth.shape) < 0.9)
    colours = rng.random((cam.height, cam.width, 3)).astype(np.float32)
    g = cell_gaussians(cam, colours, depth, np.full(depth.shape, 0.9), keep, 0.5, 0.1)
    ys, xs = np.nonzero(keep)
    uv, d, front = cam.project_depth(g.means.astype(np.float64))
    assert front.all()
    # float32 means a few metres from the origin: ~1e-6 m rounding, well under 0.01 px
    np.testing.assert_allclose(uv, np.stack([xs, ys], -1), atol=0.01)
    np.testing.assert_allclose(d, depth[ys, xs], rtol=1e-5)
    if cam.depth_is_distance:
        assert (((g.means - cam.position) @ cam.rotation)[:, 2] < 0).any()      # behind the image plane
        assert not geo.has_ray.all()                                           # the corners lie outside


@LENSES
def test_cell_discs_face_their_ray_and_cover_the_lens_footprint(lens):
    """Without a surface, a disc lies across its cell's ray (its normal is the ray) with standard deviation
    footprint x depth x the cell's angular size, which the true rays through the cell's edges give."""
    cam = lens_rig(lens).cameras[0]
    geo = cell_geometry(cam)
    keep = geo.has_ray.copy()
    depth = np.full(keep.shape, 10.0, np.float32)
    g = cell_gaussians(cam, np.zeros(keep.shape + (3,), np.float32), depth, np.full(keep.shape, 0.9), keep, 0.5,
                       0.1)
    ys, xs = np.nonzero(keep)
    normal = quat_to_rotmat(g.quats)[:, :, 2]
    ray = g.means - cam.position
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", normal, ray)), 1.0, atol=1e-5)
    # the cell's angular size from the rays through its four edge midpoints (independent finite differences)
    def ang(a, b):
        return np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1))
    uv = np.stack([xs, ys], -1).astype(np.float64)
    r = {k: cam.pixel_rays(uv + o)[1] for k, o in (("l", [-0.5, 0]), ("r", [0.5, 0]), ("t", [0, -0.5]),
                                                     ("b", [0, 0.5]))}
    inner = np.isfinite(sum(r.values())).all(1)
    size = np.sqrt(ang(r["l"], r["r"]) * ang(r["t"], r["b"]))
    dist = np.linalg.norm(g.means - cam.position, axis=1)
    s = np.exp(g.log_scales.astype(np.float64))
    np.testing.assert_allclose(s[inner, 0], 0.5 * dist[inner] * size[inner], rtol=1e-4)
    np.testing.assert_allclose(s[inner, 2], 0.1 * s[inner, 0], rtol=1e-4)
    np.testing.assert_allclose(cell_footprint(cam, xs[inner], ys[inner], np.full(inner.sum(), 10.0)),
                               dist[inner] * size[inner], rtol=1e-4)


@LENSES
@pytest.mark.parametrize("stretch", [0.0, 30.0])
def test_cell_gaussians_matches_reference_through_a_lens(lens, stretch):
    cam = lens_rig(lens).cameras[0]
    rng = np.random.default_rng(3)
    h, w = cam.height, cam.width
    rows = np.arange(h, dtype=np.float64)[:, None] * np.ones((1, w))
    depth = (3.0 + 40.0 / (1.0 + np.maximum(rows - h / 3, 0.5)) + 0.05 * rng.random((h, w))).astype(np.float32)
    keep = cell_geometry(cam).has_ray & (rng.random((h, w)) > 0.15)
    colours = rng.random((h, w, 3)).astype(np.float32)
    a = cell_gaussians(cam, colours, depth, np.full((h, w), 0.95), keep, 0.5, 0.1, surface_stretch=stretch)
    b = cell_gaussians_reference(cam, colours, depth, np.full((h, w), 0.95), keep, 0.5, 0.1, surface_stretch=stretch)
    assert len(a) == len(b) == keep.sum()
    np.testing.assert_allclose(a.means, b.means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a.log_scales, b.log_scales, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(quat_to_rotmat(a.quats), quat_to_rotmat(b.quats), atol=1e-6)


def _lens_details(seed: int, lens) -> list[CameraDetail]:
    """As test_detail._random_details, with lens cameras (one pinhole among them) on a 12 m sphere."""
    rng = np.random.default_rng(seed)
    cams = list(lens_rig(lens, width=96, height=54).cameras)
    cams[1] = cams[1].replace(distortion=None)
    out = []
    for cam in cams:
        grid = grid_camera(cam, 2)
        base = sphere_depth(grid, 12.0)
        jitter = np.where(rng.random(base.shape) < 0.5, 1.0, rng.uniform(0.75, 1.3, base.shape))
        depth = (base * jitter).astype(np.float32)
        keep = (base > 0) & (rng.random(base.shape) < 0.85)
        measured = rng.random(base.shape) < 0.5
        g = cell_gaussians(grid, np.full((*base.shape, 3), 0.5, np.float32), depth, np.full(base.shape, 0.9),
                           keep, 0.5, 0.1)
        img = rng.choice([0.1, 0.35, 0.6, 0.9], base.shape)[..., None].repeat(3, 2)
        out.append(CameraDetail.build(grid, depth, keep, measured, g.means, img))
    return out


@LENSES
def test_see_through_with_colours_through_lenses_matches_reference(lens):
    """carve_against's colour test (runtime.detail.colour_seen) through a lens camera (and the one pinhole among
    them) against its cell-by-cell reference."""
    details = _lens_details(6, lens)
    dropped = {None: 0, (12.0, 0.15): 0}
    for j in (0, 1):
        others = [d for i, d in enumerate(details) if i != j]
        for photo in dropped:
            got = np.ones(len(details[j].means), bool)
            carve_against(details[j], others, got, 0.15, photo)
            want = np.ones_like(got)
            carve_against_reference(details[j], others, want, 0.15, photo)
            np.testing.assert_array_equal(got, want)
            dropped[photo] += int((~got).sum())
    assert dropped[None] > dropped[(12.0, 0.15)] > 5      # both outcomes of both tests occur


@LENSES
def test_fusion_through_lenses_matches_references(lens):
    details = _lens_details(4, lens)
    for dedupe in (0.0, 0.7):
        got = carve_details(details, 0.15, dedupe)
        want = carve_details_reference(details, 0.15, dedupe)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        assert sum(int((~a).sum()) for a in got) > 10
        keep, free = carve_details_both(details, 0.15, dedupe)       # and the free-space rule alone, one pass
        for a, b, c, d in zip(keep, free, want, carve_details_reference(details, 0.15, 0.0)):
            np.testing.assert_array_equal(a, c)
            np.testing.assert_array_equal(b, d)
    rng = np.random.default_rng(5)
    n = 300
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    means = dirs * rng.uniform(3.0, 25.0, (n, 1)) + [0, 0, 1.5]
    coarse = Gaussians(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                       rng.uniform(math.log(0.05), math.log(3.0), (n, 3)).astype(np.float32),
                       np.zeros(n, np.float32), np.zeros((n, 1, 3), np.float32))
    got = cull_covered(coarse, details, 0.15)
    np.testing.assert_array_equal(got, cull_covered_reference(coarse, details, 0.15))
    assert 0.1 * n < got.sum() < 0.9 * n


def test_camera_detail_on_a_fisheye_camera():
    """A fisheye camera inside a 12 m sphere of coarse Gaussians: its cells take the model's depth along their true
    rays (the distance, 12 m less the ring offset), beyond 90 degrees too, none outside the image circle."""
    cam = lens_rig(FISHEYE).cameras[0]
    k = np.arange(20000) + 0.5
    z = 1 - 2 * k / 20000
    a = math.pi * (3 - math.sqrt(5)) * k
    d = np.stack([np.sqrt(1 - z * z) * np.cos(a), np.sqrt(1 - z * z) * np.sin(a), z], 1)
    means = (cam.position + 12.0 * d).astype(np.float32)
    coarse = Gaussians(means, np.tile([[1.0, 0, 0, 0]], (len(d), 1)).astype(np.float32),
                       np.full((len(d), 3), math.log(0.25), np.float32), np.full(len(d), 6.0, np.float32),
                       np.full((len(d), 1, 3), 0.5, np.float32))
    img = np.random.default_rng(0).random((cam.height, cam.width, 3)).astype(np.float32)
    g, det, counts = camera_detail(cam, img, coarse, DetailOptions(far_depth=0.0, stride=1))
    assert counts["model"] > 0.8 * len(g) and len(g) == det.keep.sum()
    geo = cell_geometry(det.grid)
    assert not (det.keep & ~geo.has_ray).any()
    dist = np.linalg.norm(g.means - cam.position, axis=1)
    assert np.median(np.abs(dist - 12.0)) < 0.3
    assert (((g.means - cam.position) @ cam.rotation)[:, 2] < -1.0).any()


def test_cell_geometry_and_rays_are_cached_by_the_cameras_values():
    """A drive's keyframes make new grid cameras of the same rig: equal values share one CellGeometry and one
    grid_rays (read-only arrays); a camera that differs in its pose, K or lens gets its own, equal to a fresh one."""
    from xyzcyl.runtime.detail import _make_geometry, grid_rays

    cam = lens_rig(FISHEYE).cameras[1]
    twin = cam.replace(name="other")                         # the same values in a new object
    assert cell_geometry(cam) is cell_geometry(twin)
    assert grid_rays(cam)[0] is grid_rays(twin)[0]
    geo = cell_geometry(cam)
    for a in (geo.rays, geo.scale, geo.across, geo.has_ray, *grid_rays(cam)):
        assert not a.flags.writeable
    T = np.array(cam.cam_to_ego)
    T[:3, 3] += [0.5, 0.0, 0.0]
    K = np.array(cam.K)
    K[0, 0] *= 1.1
    for other in (cam.replace(cam_to_ego=T), cam.replace(K=K), cam.replace(distortion=FTHETA),
                  cam.replace(distortion=None)):
        g = cell_geometry(other)
        assert g is not geo
        d, cos = grid_rays(other)
        assert d is not grid_rays(cam)[0]
    R = np.array(cam.cam_to_ego)
    R[:3, :3] = quat_to_rotmat(np.array([0.9, 0.1, -0.2, 0.3])) @ R[:3, :3]
    turned = cam.replace(cam_to_ego=R)
    assert not np.allclose(grid_rays(turned)[0], grid_rays(cam)[0], equal_nan=True)    # ego-frame rays turn
    np.testing.assert_array_equal(cell_geometry(turned).rays, geo.rays)      # camera-frame rays do not
    fresh = _make_geometry(turned)
    np.testing.assert_array_equal(cell_geometry(turned).quats, fresh.quats)


def test_a_pinhole_moved_by_its_calibration_shares_its_camera_frame_rays():
    """A recorded drive's extrinsics move by millimetres from frame to frame: a pinhole grid camera that differs only
    in its pose shares the camera-frame arrays (lens_key) and gets its own pose's quats and ego-frame rays, the same
    bits as made from scratch: ((u - cx) / fx, (v - cy) / fy, 1) normalised, turned into the ego frame."""
    from xyzcyl.runtime.detail import grid_rays

    cam = lens_rig(None).cameras[2]
    T = np.array(cam.cam_to_ego)
    T[:3, :3] = quat_to_rotmat(np.array([0.99, 0.02, -0.01, 0.03])) @ T[:3, :3]
    T[:3, 3] += [0.003, -0.001, 0.0]
    moved = cam.replace(cam_to_ego=T)
    a, b = cell_geometry(cam), cell_geometry(moved)
    assert a is not b and a.rays is b.rays and a.across is b.across and a.scale is b.scale
    K = np.asarray(cam.K)
    x = (np.arange(cam.width) - K[0, 2]) / K[0, 0]
    y = (np.arange(cam.height) - K[1, 2]) / K[1, 1]
    rays = np.empty((cam.height, cam.width, 3))
    rays[..., 0], rays[..., 1], rays[..., 2] = x[None, :], y[:, None], 1.0
    n = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    for c in (cam, moved):
        d, cos = grid_rays(c)
        np.testing.assert_array_equal(d, (rays / n[..., None]) @ c.rotation.T)
        np.testing.assert_array_equal(cos, 1.0 / n)
        assert not d.flags.writeable and not cos.flags.writeable
    np.testing.assert_array_equal(b.rays, rays)
    assert not np.allclose(b.quats, a.quats) and np.allclose(b.quats[5, 7], b.quats[0, 0])


def test_a_detail_layers_cell_values_are_its_maps_at_its_kept_cells():
    """CameraDetail.cell_colours / cell_conf: the maps at the kept cells in row-major order (map[keep]), gathered by
    flat index."""
    from xyzcyl.runtime.detail import _at_cells

    rng = np.random.default_rng(4)
    keep = rng.random((37, 53)) < 0.7
    for a in (rng.integers(0, 255, (37, 53, 3), dtype=np.uint8), rng.integers(0, 3, (37, 53)).astype(np.int8)):
        got = _at_cells(a, keep)
        np.testing.assert_array_equal(got, a[keep])
        assert got.dtype == a.dtype
    assert _at_cells(np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5), bool)).shape == (0, 3)
