"""runtime.lidarsim: the LiDAR models and their checks, a sweep inside a cylinder of Gaussians (every ray's range is
known), the spin's motion (points in the end-of-spin frame), returns dropped by alpha and range, the file
encodings, and beams estimated from a recorded sweep."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from xyzcyl.common.wire import ViewError
from xyzcyl.runtime.lidarsim import (
    LIDAR_MODELS,
    MAX_RAYS,
    LidarModel,
    beams_from_sweep,
    elevations_of,
    gaussians_drawer,
    interpolate_pose,
    lidar_model,
    peakiness,
    render_lidar,
    sector_count,
    sweep_bytes,
)
from xyzcyl.runtime.rotations import quat_to_rotmat, rotmat_to_quat
from xyzcyl.testing.lidarscene import GREY_LUMA, cylinder_gaussians

# a small spinner for fast tests: 9 beams -20..+20 degrees, 2-degree columns
SMALL = LidarModel("small", tuple(float(v) for v in np.linspace(-20, 20, 9)), 2.0, 360.0, 180.0, 200.0)
# tolerance on a range inside the cylinder: the renderer's depth is the front-to-back blend of the Gaussians'
# centre depths (3DGS's expected depth); the cylinder's plates overlap (sigma = their spacing, 0.087 m around), and
# off a sector camera's axis the nearer side of that blend wins: the range reads short by up to 0.045 m at 22 degrees
# off-axis (measured; 0.003 m on the axis)
RANGE_TOL = 0.06


def _pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat([math.cos(math.radians(yaw_deg) / 2), 0, 0, math.sin(math.radians(yaw_deg) / 2)])
    T[:3, 3] = (x, y, z)
    return T


@pytest.fixture(scope="module")
def cylinder():
    return gaussians_drawer(cylinder_gaussians(10.0))


def test_nominal_models():
    p, a, p64 = LIDAR_MODELS["pandar128"], LIDAR_MODELS["at128"], LIDAR_MODELS["pandar64"]
    assert (p.beams, p.columns, p.azimuth_fov_deg) == (128, 1800, 360.0)
    assert min(p.elevations_deg) == -25.0 and max(p.elevations_deg) == 15.0
    assert np.all(np.diff(p.elevations_deg) > 0)
    assert np.count_nonzero(np.diff(p.elevations_deg) < 0.2) == 63          # the fine centre band
    assert (a.beams, a.columns, a.azimuth_fov_deg) == (128, 1200, 120.0)
    assert a.azimuths_deg()[0] == 60.0 and a.azimuths_deg()[-1] == pytest.approx(-59.9)   # left to right
    assert (p64.beams, min(p64.elevations_deg), max(p64.elevations_deg)) == (64, -25.0, 15.0)
    d = p.directions()
    assert d.shape == (128, 1800, 3) and np.allclose(np.linalg.norm(d, axis=-1), 1.0)


@pytest.mark.parametrize("kw, field", [
    ({"name": "velodyne"}, "model"),
    ({"azimuth_step_deg": 0.0}, "azimuth_step_deg"),
    ({"azimuth_step_deg": float("nan")}, "azimuth_step_deg"),
    ({"azimuth_step_deg": 0.05}, "azimuth_step_deg"),                      # 128 x 7200 rays > MAX_RAYS
    ({"max_range_m": -1.0}, "max_range_m"),
    ({"elevations_deg": [0.0, 75.0]}, "elevations_deg[1]"),
    ({"elevations_deg": []}, "elevations_deg"),
    ({"elevations_deg": [0.0, float("inf")]}, "elevations_deg[1]"),
])
def test_model_checks_name_the_field(kw, field):
    name = kw.pop("name", "pandar128")
    with pytest.raises(ViewError) as e:
        lidar_model(name, **kw)
    assert e.value.field == field, e.value
    assert 128 * 7200 > MAX_RAYS


def test_interpolate_pose_ends_and_middle():
    a, b = _pose(1, 2, 3, 10), _pose(3, 2, 1, 50)
    got = interpolate_pose(a, b, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(got[0], a, atol=1e-12)
    np.testing.assert_allclose(got[2], b, atol=1e-12)
    np.testing.assert_allclose(got[1], _pose(2, 2, 2, 30), atol=1e-12)     # half the yaw, half the way
    q = rotmat_to_quat(got[1][:3, :3])
    assert np.linalg.norm(q) == pytest.approx(1.0)


def test_a_still_sweep_inside_a_cylinder(cylinder):
    """From the cylinder's axis every ray returns at horizontal distance 10 m, at its beam's elevation; intensity is
    the grey's luminance; the sensor 1.5 m up sees the same rings shifted."""
    s = render_lidar(cylinder, SMALL, _pose(z=1.5))
    assert s.stats["rays"] == 9 * 180 and s.stats["returns"] == 9 * 180 and s.stats["sectors"] == 8
    p = s.points.astype(np.float64)
    r = np.hypot(p[:, 0], p[:, 1])
    assert np.abs(r - 10.0).max() < RANGE_TOL
    elev = np.degrees(np.arctan2(p[:, 2], r))
    np.testing.assert_allclose(elev, np.asarray(SMALL.elevations_deg)[s.beam], atol=0.8)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    want = (SMALL.azimuths_deg()[s.column] + 180.0) % 360.0 - 180.0
    assert np.abs((az - want + 180.0) % 360.0 - 180.0).max() < 0.1
    np.testing.assert_allclose(s.range_m, np.linalg.norm(p, axis=1), rtol=1e-5)
    np.testing.assert_allclose(s.intensity, GREY_LUMA, atol=2e-3)
    img = s.range_image()
    assert img.shape == (9, 180) and np.all(img > 0)


def test_the_spin_moves_the_sensor_and_points_are_in_the_end_frame(cylinder):
    """A sensor moving 1 m forward and turning 20 degrees during the spin: its points, taken back from the
    end-of-spin frame into the scene, lie on the cylinder; read as if in the start frame they do not."""
    start, end = _pose(x=-0.5, yaw_deg=-10.0), _pose(x=0.5, yaw_deg=10.0)
    assert sector_count(SMALL, start, end) == 20                  # 1 m / 0.05 m
    s = render_lidar(cylinder, SMALL, start, end)
    assert s.stats["returns"] == s.stats["rays"] and s.stats["origin_error_m"] == pytest.approx(0.025)
    p = s.points.astype(np.float64)
    scene = p @ end[:3, :3].T + end[:3, 3]
    assert np.abs(np.hypot(scene[:, 0], scene[:, 1]) - 10.0).max() < RANGE_TOL
    wrong = p @ start[:3, :3].T + start[:3, 3]
    assert np.abs(np.hypot(wrong[:, 0], wrong[:, 1]) - 10.0).max() > 0.5
    # the first column fires from the start pose: its direction from there is its own azimuth in the start frame
    first = s.column == 0
    d0 = scene[first] - start[:3, 3]
    az0 = np.degrees(np.arctan2(d0[:, 1], d0[:, 0])) - (-10.0)
    assert np.abs((az0 - SMALL.azimuths_deg()[0] + 180.0) % 360.0 - 180.0).max() < 1.0


def test_at128_sees_forward_only(cylinder):
    m = lidar_model("at128", azimuth_step_deg=1.0)
    s = render_lidar(cylinder, m, np.eye(4))
    assert s.stats["rays"] == 128 * 120 and s.stats["returns"] == 128 * 120 and s.stats["sectors"] == 3
    az = np.degrees(np.arctan2(s.points[:, 1], s.points[:, 0]))
    assert az.min() > -60.0 and az.max() <= 60.0 + 1e-3


def test_no_return_from_nothing_thin_air_or_beyond_range():
    """Faint Gaussians (alpha < ALPHA_MIN) and a wall beyond max_range return nothing, each counted."""
    faint = cylinder_gaussians(10.0)
    faint.opacity_logits[:] = -3.0                                # opacity 0.05
    s = render_lidar(gaussians_drawer(faint), SMALL, np.eye(4))
    assert len(s) == 0 and s.stats["no_return"] == s.stats["rays"]
    near = lidar_model("pandar64", azimuth_step_deg=5.0, max_range_m=8.0)
    s = render_lidar(gaussians_drawer(cylinder_gaussians(10.0)), near, np.eye(4))
    assert len(s) == 0 and s.stats["out_of_range"] == s.stats["rays"]
    assert s.points.shape == (0, 3) and s.range_image().max() == 0.0


def test_encodings(cylinder):
    from plyfile import PlyData

    s = render_lidar(cylinder, SMALL, np.eye(4))
    ply = PlyData.read(io.BytesIO(sweep_bytes(s, "ply")))
    v = ply["vertex"]
    assert v.count == len(s)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), s.points)
    np.testing.assert_array_equal(v["intensity"], s.intensity)
    np.testing.assert_array_equal(v["ring"], s.beam)
    a = np.load(io.BytesIO(sweep_bytes(s, "npy")))
    assert a.shape == (len(s), 4) and a.dtype == np.float32
    with pytest.raises(ViewError):
        sweep_bytes(s, "las")


def test_beams_from_a_sweep_and_the_origin_that_sharpens_them():
    """Points on 5 known rings seen from (0.3, 0, 1.8): the rings are found from there to 0.02 degrees; seen from
    the frame's origin they smear (lower peakiness)."""
    rng = np.random.default_rng(3)
    rings = np.array([-15.0, -8.0, -2.0, 0.5, 6.0])
    o = np.array([0.3, 0.0, 1.8])
    e = np.radians(np.repeat(rings, 4000))
    a = rng.uniform(-np.pi, np.pi, e.size)
    d = rng.uniform(4.0, 60.0, e.size)
    pts = o + np.stack([d * np.cos(e) * np.cos(a), d * np.cos(e) * np.sin(a), d * np.sin(e)], 1)
    got = beams_from_sweep(pts, o, max_beams=8)
    np.testing.assert_allclose(got, rings, atol=0.02)
    assert peakiness(elevations_of(pts, o)) > 3 * peakiness(elevations_of(pts, (0.0, 0.0, 0.0)))
    with pytest.raises(ViewError):
        beams_from_sweep(np.zeros((5, 3)))


def test_the_sensors_height_from_its_nearest_ground_ring():
    """A spinner 2.1 m above a flat road whose ego origin sits 0.3 m above it (PandaSet's case), its lowest beam at
    -25 degrees, a wall 12 m ahead: the height above the ground and the ground under the origin come back from the
    sweep alone, to within the ring's sampling (0.2-degree columns; the 0.5 % quantile of the ring radius)."""
    from xyzcyl.runtime.lidarsim import sensor_height_from_sweep

    h, ground = 2.1, -0.3
    elev = np.radians(np.linspace(-25.0, -2.0, 24))[:, None]
    az = np.radians(np.arange(0.0, 360.0, 0.2))[None, :]
    r = h / np.tan(-elev) + 0.0 * az                                   # where each beam meets the road
    road = np.stack([r * np.cos(az), r * np.sin(az), np.full(r.shape, ground)], -1).reshape(-1, 3)
    wall = np.stack(np.meshgrid([12.0], np.linspace(-5, 5, 50), np.linspace(0, 3, 30), indexing="ij"), -1)
    g, height = sensor_height_from_sweep(np.concatenate([road, wall.reshape(-1, 3)]), -25.0)
    assert g == pytest.approx(ground, abs=0.02) and height == pytest.approx(h, abs=0.02)
    with pytest.raises(ViewError) as e:
        sensor_height_from_sweep(wall.reshape(-1, 3), -25.0)           # no ground in it
    assert e.value.field == "points"
    with pytest.raises(ViewError):
        sensor_height_from_sweep(road, 5.0)
