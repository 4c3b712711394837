"""UCCM geometry: cylinder pixels <-> points, camera sampling, overlay, CPFG coordinates, background rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
from xyzcyl.runtime.cylinder import (
    PRESETS,
    CylinderError,
    CylinderSpec,
    camera_sampling_grid,
    coverage,
    frustum_annulus_coords,
    frustum_annulus_points,
    overlay,
    project_rig,
    ray_cylinder_intersection,
    rig_sampling_grids,
    sample_bilinear,
    sample_bilinear_reference,
)
from xyzcyl.runtime.rig import ring_rig


def _spec(**kw):
    args = dict(centre=[1.0, -0.5, 1.6], radius=20.0, z_min=-3.0, z_max=13.0, height=32, width=128)
    args.update(kw)
    return CylinderSpec(**args)


def test_from_rig_formula():
    rig = ring_rig(6, hfov_deg=70, width=160, height=90)
    spec = CylinderSpec.from_rig(rig, z_range=(-3, 13), rho=0.9, dh=0.4)
    f_min = 2 * math.atan(90 / (2 * rig.cameras[0].K[1, 1]))
    assert spec.radius == pytest.approx(8.0 / math.tan(0.9 * f_min / 2), rel=1e-12)
    assert spec.vertical_angle == pytest.approx(0.9 * f_min, rel=1e-12)
    np.testing.assert_allclose(spec.centre, [0, 0, 1.5 + 0.4], atol=1e-12)
    assert (spec.height, spec.width, spec.Z_u) == (224, 1024, 16.0)


def test_from_rig_refuses_bad_rho_and_range():
    rig = ring_rig(6, hfov_deg=70, width=160, height=90)
    f_min = rig.cameras[0].vertical_fov
    with pytest.raises(CylinderError, match=r"^rho: .* >= pi/2"):
        CylinderSpec.from_rig(rig, rho=math.pi / f_min + 0.01)
    with pytest.raises(CylinderError, match="^rho"):
        CylinderSpec.from_rig(rig, rho=0.0)
    with pytest.raises(CylinderError, match="^z_range"):
        CylinderSpec.from_rig(rig, z_range=(5.0, 5.0))
    with pytest.raises(CylinderError, match="^dh"):
        CylinderSpec.from_rig(rig, dh=float("nan"))
    # an equirectangular camera counts as a vertical FoV of pi: any rho >= 1 is refused
    pano = ring_rig(1).cameras[0].replace(model="equirectangular", K=None)
    from xyzcyl.runtime.rig import Rig

    assert CylinderSpec.from_rig(Rig((pano,)), rho=0.9).radius == pytest.approx(8.0 / math.tan(0.45 * math.pi))
    with pytest.raises(CylinderError, match="^rho"):
        CylinderSpec.from_rig(Rig((pano,)), rho=1.0)


def test_presets_are_the_papers():
    assert PRESETS["nuscenes"] == {"occupancy": (0.9, 0.0), "volume": (0.98, 0.4), "pixel": (0.98, 0.4)}
    assert PRESETS["carla-centric"]["volume"] == (1.6, 0.0)
    assert PRESETS["argoverse"]["occupancy"] == (0.09, 0.0)
    rig = ring_rig(6, hfov_deg=70, width=160, height=90)
    spec = CylinderSpec.from_preset(rig, "once", "volume")
    assert (spec.rho, spec.dh) == (1.0, 0.5)


def test_pixel_point_round_trip_and_conventions():
    spec = _spec()
    rng = np.random.default_rng(0)
    i = rng.uniform(-0.5, spec.height - 0.5, 500)
    j = rng.uniform(-0.5, spec.width - 0.5 - 1e-9, 500)
    p = spec.pixel_to_point(i, j)
    np.testing.assert_allclose(np.hypot(p[:, 0] - 1.0, p[:, 1] + 0.5), spec.radius, rtol=1e-12)
    i2, j2 = spec.point_to_pixel(p)
    # 1e-9 px: float64 trig round trip
    np.testing.assert_allclose(i2, i, atol=1e-9)
    np.testing.assert_allclose(j2, j, atol=1e-9)
    # off-surface points project centrally through the axis: scaling (dx, dy, dz) keeps the pixel
    far = spec.centre + 3.0 * (p - spec.centre)
    np.testing.assert_allclose(np.stack(spec.point_to_pixel(far)), np.stack([i, j]), atol=1e-9)
    c = spec.centre
    W, H = spec.width, spec.height
    # theta = 0 (ego forward) -> s = 1/2; theta = +90 deg (left) -> s = 1/4; right -> 3/4; behind -> s = 0
    pts = np.array([c + [5, 0, 0], c + [0, 5, 0], c + [0, -5, 0], c + [-5, 0, 0]])
    np.testing.assert_allclose(spec.point_to_pixel(pts)[1], [W / 2 - 0.5, W / 4 - 0.5, 3 * W / 4 - 0.5, -0.5])
    # top edge of the cylinder: z = c_z + Z_u/2 at r = R_u -> i = -0.5 (row p = 0); the axis height -> middle
    top = c + [spec.radius, 0, spec.Z_u / 2]
    assert spec.point_to_pixel(top)[0] == pytest.approx(-0.5)
    assert spec.point_to_pixel(c + [3, 0, 0])[0] == pytest.approx(H / 2 - 0.5)
    assert spec.points().shape == (H, W, 3)


def test_cylinder_camera_round_trip():
    """cylinder pixel -> 3D -> camera pixel -> ray back to 3D -> the same cylinder pixel."""
    rig = ring_rig(6, hfov_deg=70, width=160, height=90)
    spec = CylinderSpec.from_rig(rig, height=24, width=96)
    ii, jj = np.meshgrid(np.arange(spec.height), np.arange(spec.width), indexing="ij")
    pts = spec.pixel_to_point(ii, jj)
    n_valid = 0
    for cam in rig.cameras:
        grid, valid = camera_sampling_grid(spec, cam)
        uv, _, _ = cam.project(pts[valid])
        # the grid is the align_corners=False normalisation of uv
        np.testing.assert_allclose(grid[valid][:, 0], (2 * uv[:, 0] + 1) / cam.width - 1, atol=1e-6)
        o, d = cam.pixel_rays(uv)
        dist = np.linalg.norm(pts[valid] - cam.position, axis=-1)
        back_i, back_j = spec.point_to_pixel(o + dist[:, None] * d)
        # 1e-6 px: float64 projection + inverse
        np.testing.assert_allclose(back_i, ii[valid], atol=1e-6)
        np.testing.assert_allclose(back_j, jj[valid], atol=1e-6)
        assert np.all(np.abs(grid[valid]) <= 1.0) and np.all(grid[~valid] == -2.0)
        n_valid += valid.sum()
    assert n_valid > spec.height * spec.width  # every camera sees part of it and they overlap


def _flat_colour_rig():
    # 4 cameras clockwise (front, right, back, left), 100 deg horizontal FoV: 10 deg overlaps at the diagonals.
    rig = ring_rig(4, hfov_deg=100, width=200, height=150, ring_radius=0.05)
    colours = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], np.float32)
    images = [np.broadcast_to(c, (150, 200, 3)).copy() for c in colours]
    return rig, colours, images


def test_flat_colours_land_at_expected_columns():
    rig, colours, images = _flat_colour_rig()
    spec = CylinderSpec.from_rig(rig, height=32, width=360)
    maps, valid = project_rig(spec, rig, images)
    f_plus = overlay(maps, "cw")
    f_minus = overlay(maps, "ccw")
    row = spec.height // 2

    def col(theta_deg):  # column whose centre is at azimuth theta
        return int(round((180.0 - theta_deg) / 360.0 * spec.width - 0.5))

    for k, theta in enumerate([0, -90, 180, 90]):  # camera k looks at these azimuths
        for off in (-35, 0, 35):  # well inside +-45 deg (the exclusive region)
            j = col(theta + off) % spec.width
            np.testing.assert_array_equal(f_plus[row, j], colours[k])
            np.testing.assert_array_equal(f_minus[row, j], colours[k])
    # overlaps at the diagonals: F+ keeps the later camera, F- the earlier one
    for a, b, theta in [(0, 1, -45), (1, 2, -135), (2, 3, 135)]:
        j = col(theta)
        assert valid[a, row, j] and valid[b, row, j]
        np.testing.assert_array_equal(f_plus[row, j], colours[b])
        np.testing.assert_array_equal(f_minus[row, j], colours[a])
    # cam3 (left) and cam0 (front) overlap at +45: F+ = cam3 (later), F- = cam0
    np.testing.assert_array_equal(f_plus[row, col(45)], colours[3])
    np.testing.assert_array_equal(f_minus[row, col(45)], colours[0])
    total, per = coverage(valid)
    assert valid.any(axis=0)[row].all() and len(per) == 4
    # < 1: 45 deg off-axis a 100x84 deg camera sees only +-32 deg vertically, the cylinder spans +-37.5 deg,
    # so its top/bottom corners at the four diagonals stay uncovered.
    assert 0.95 < total < 1.0


def test_overlay_semantics_hand_made():
    a = np.zeros((3, 2, 3, 2), np.float32)  # N=3, H=2, W=3, C=2
    a[0, :, 0:2] = [1, 1]
    a[1, :, 1:3] = [0, 2]  # a value with a zero channel still counts as present
    a[2, 0, 2] = [3, 0]
    plus = overlay(a, "cw")
    minus = overlay(a, "ccw")
    np.testing.assert_array_equal(plus[0], [[1, 1], [0, 2], [3, 0]])
    np.testing.assert_array_equal(minus[0], [[1, 1], [1, 1], [0, 2]])
    np.testing.assert_array_equal(plus[1], [[1, 1], [0, 2], [0, 2]])
    np.testing.assert_array_equal(minus[1], [[1, 1], [1, 1], [0, 2]])
    # channels-first layout gives the same result
    cf = overlay(np.moveaxis(a, -1, 1), "cw", channel_axis=1)
    np.testing.assert_array_equal(np.moveaxis(cf, 0, -1), plus)
    # an explicit valid mask overrides the != 0 test: a zero-valued but valid pixel overwrites
    valid = np.any(a != 0, axis=-1)
    valid[2, 1, 0] = True
    np.testing.assert_array_equal(overlay(a, "cw", valid=valid)[1, 0], [0, 0])
    with pytest.raises(ValueError, match="order"):
        overlay(a, "up")


def test_sample_bilinear_matches_reference_and_torch():
    rng = np.random.default_rng(3)
    img = rng.random((7, 9, 4)).astype(np.float32)
    grid = rng.uniform(-1.3, 1.3, (5, 6, 2)).astype(np.float32)
    grid[0, 0] = [-1, -1]  # exact corner: half/quarter zero padding
    ours = sample_bilinear(img, grid)
    # 1e-5: float32 accumulation vs float64 reference
    np.testing.assert_allclose(ours, sample_bilinear_reference(img, grid), atol=1e-5)
    np.testing.assert_allclose(ours[0, 0], img[0, 0] / 4, atol=1e-6)
    torch = pytest.importorskip("torch")
    ref = torch.nn.functional.grid_sample(torch.from_numpy(img).permute(2, 0, 1)[None], torch.from_numpy(grid)[None],
                                          mode="bilinear", padding_mode="zeros", align_corners=False)
    np.testing.assert_allclose(ours, ref[0].permute(1, 2, 0).numpy(), atol=1e-5)
    # pixel centres sample exactly
    v, u = 3, 5
    centre = np.array([[(2 * u + 1) / 9 - 1, (2 * v + 1) / 7 - 1]], np.float32)
    np.testing.assert_allclose(sample_bilinear(img, centre)[0], img[v, u], atol=1e-6)
    # wrap_x: the seam between the last and first column blends both instead of zeros
    seam = np.array([[1.0, (2 * v + 1) / 7 - 1]])
    np.testing.assert_allclose(sample_bilinear(img, seam, wrap_x=True)[0], (img[v, 0] + img[v, 8]) / 2, atol=1e-6)
    assert np.all(sample_bilinear(img, np.full((2, 2), np.nan)) == 0)


def test_equirect_camera_covers_the_whole_cylinder():
    from xyzcyl.runtime.rig import Rig

    pano = ring_rig(1, ring_radius=0.0).cameras[0].replace(model="equirectangular", K=None, width=256, height=128)
    rig = Rig((pano,))
    spec = CylinderSpec.from_rig(rig, height=16, width=64)
    grids, valid = rig_sampling_grids(spec, rig)
    assert valid.all() and grids.shape == (1, 16, 64, 2)
    # camera at the cylinder centre looking forward: cylinder column j <-> pano column
    # pano u = (lon/2pi + 1/2) W - 1/2, lon = -theta (right of forward is + lon), theta = pi - 2 pi s
    s = (np.arange(64) + 0.5) / 64
    u_expected = (-(np.pi - 2 * np.pi * s) / (2 * np.pi) + 0.5) * 256 - 0.5
    u = ((grids[0, 8, :, 0] + 1) * 256 - 1) / 2
    np.testing.assert_allclose(u, u_expected, atol=2e-3)  # float32 grid storage


def test_frustum_annulus_round_trip_and_consistency():
    spec = _spec()
    rng = np.random.default_rng(4)
    coords = rng.uniform(-1, 1, (300, 3))
    pts = frustum_annulus_points(coords, spec, 2.0, 40.0)
    np.testing.assert_allclose(frustum_annulus_coords(pts, spec, 2.0, 40.0), coords, atol=1e-10)
    # on the cylinder surface (r = R_u) the (s, p) part equals the cylinder plane's normalised coordinates
    ii, jj = rng.uniform(0, spec.height - 1, 50), rng.uniform(0, spec.width - 1, 50)
    on = spec.pixel_to_point(ii, jj)
    c = frustum_annulus_coords(on, spec, 0.0, spec.radius)
    np.testing.assert_allclose(c[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(c[:, 1], (2 * jj + 1) / spec.width - 1, atol=1e-10)
    np.testing.assert_allclose(c[:, 2], (2 * ii + 1) / spec.height - 1, atol=1e-10)
    # eq. 28 written out: X_n = (2(r - r_min)/(r_max - r_min) - 1, -theta/pi, -2 z R_u / (Z_u r))
    d = pts - spec.centre
    r = np.hypot(d[:, 0], d[:, 1])
    eq28 = np.column_stack([2 * (r - 2) / 38 - 1, -np.arctan2(d[:, 1], d[:, 0]) / np.pi,
                            -2 * d[:, 2] * spec.radius / (spec.Z_u * r)])
    np.testing.assert_allclose(eq28, coords, atol=1e-10)


def test_ray_cylinder_far_root():
    spec = _spec()
    rng = np.random.default_rng(5)
    o = spec.centre + np.column_stack([rng.uniform(-5, 5, 400), rng.uniform(-5, 5, 400), rng.uniform(-2, 2, 400)])
    d = rng.normal(size=(400, 3))
    p, uv = ray_cylinder_intersection(o, d, spec)
    rel = p - spec.centre
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), spec.radius, rtol=1e-9)
    t = np.einsum("ij,ij->i", p - o, d) / np.einsum("ij,ij->i", d, d)
    assert np.all(t > 0)  # origins inside: the far root is the only forward hit
    np.testing.assert_allclose(o + t[:, None] * d, p, atol=1e-9)
    np.testing.assert_allclose(uv[:, 0], -np.arctan2(rel[:, 1], rel[:, 0]) / np.pi, atol=1e-12)
    np.testing.assert_allclose(uv[:, 1], -rel[:, 2] / spec.Z_u, atol=1e-12)
    _, uv2 = ray_cylinder_intersection(o, d, spec, paper_v=False)
    i, _ = spec.point_to_pixel(p)
    np.testing.assert_allclose(uv2[:, 1], (2 * i + 1) / spec.height - 1, atol=1e-9)
    # from outside, a ray through the cylinder hits twice: the far root is the one further along the ray
    o_out = spec.centre + [-50.0, 0.0, 0.0]
    p_out, _ = ray_cylinder_intersection(o_out, np.array([1.0, 0.0, 0.0]), spec)
    np.testing.assert_allclose(p_out, spec.centre + [spec.radius, 0, 0], atol=1e-9)
    # misses: looking away from outside, and vertical rays
    p_miss, uv_miss = ray_cylinder_intersection(np.stack([o_out, o[0]]), np.array([[-1.0, 0, 0], [0, 0, 1.0]]), spec)
    assert np.isnan(p_miss).all() and np.isnan(uv_miss).all()


def test_spec_dict_round_trip_and_validation():
    spec = _spec(rho=0.9, dh=0.4)
    again = CylinderSpec.from_dict(spec.to_dict())
    assert again.to_dict() == spec.to_dict()
    with pytest.raises(CylinderError, match="radius"):
        _spec(radius=-1.0)
    with pytest.raises(CylinderError, match="width"):
        _spec(width=0)
    with pytest.raises(CylinderError, match="centre"):
        _spec(centre=[0, float("nan"), 0])
