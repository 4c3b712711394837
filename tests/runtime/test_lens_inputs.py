"""Input cameras with lenses (issue 28 step 2): the lifting grids, depth rays and focal of fisheye and f-theta rigs,
LiDAR depth maps and the model's depth along true rays (runtime.raydepth), and `xyzcyl cylinder` on a fisheye rig."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from xyzcyl.cli import main
from xyzcyl.runtime.cylinder import CylinderSpec, camera_sampling_grid, overlay, project_rig
from xyzcyl.runtime.lidar import camera_depths, lidar_depth_map, lidar_depth_map_reference, summarise
from xyzcyl.runtime.lifting import depth_rays, focal_n
from xyzcyl.runtime.raydepth import render_ray_depth
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.rig import Rig, ring_rig
from xyzcyl.runtime.scene import Scene
from xyzcyl.testing import EXAMPLE_RIG, REPO

FISHEYE = {"model": "opencv_fisheye", "k1": -0.03, "k2": 0.004, "k3": -2e-4, "k4": 0.0, "max_angle_deg": 100.0}
FTHETA = {"model": "ftheta", "reference_poly": "angle_to_pixeldist", "angle_to_pixeldist_poly": [0.0, 21.0, 0.0, -1.5],
          "max_angle_deg": 95.0, "linear_cde": [1.01, 0.002, -0.001]}


def lens_rig(lens: dict, n: int = 4, width: int = 96, height: int = 64, f: float = 24.0) -> Rig:
    """A ring of n outward cameras with ``lens`` (a fisheye of 200 degrees across at f = 24 px sees 84 px)."""
    base = ring_rig(n, hfov_deg=90.0, width=width, height=height, ring_radius=0.6)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Rig(cameras=tuple(c.replace(K=K, distortion=lens) for c in base.cameras))


@pytest.mark.parametrize("lens", [FISHEYE, FTHETA], ids=["fisheye", "ftheta"])
def test_sampling_grids_land_where_the_lens_projects(lens):
    rig = lens_rig(lens)
    spec = CylinderSpec.from_rig(rig, rho=0.9, height=16, width=64)
    P = spec.points()
    for cam in rig.cameras:
        grid, valid = camera_sampling_grid(spec, cam)
        q = (P - cam.position) @ cam.rotation
        uv, ok = cam.distortion.project(cam.K, q)
        want = ok & cam.inside(uv)
        assert np.array_equal(valid, want) and valid.any()
        u = ((grid[..., 0] + 1) * cam.width - 1) / 2
        v = ((grid[..., 1] + 1) * cam.height - 1) / 2
        np.testing.assert_allclose(np.stack([u, v], -1)[valid], uv[valid], atol=2e-4)   # float32 grid
        # the lens images beyond 90 degrees: some cylinder pixels behind the image plane are sampled
        assert (valid & (q[..., 2] < 0)).any()


@pytest.mark.parametrize("lens", [FISHEYE, FTHETA], ids=["fisheye", "ftheta"])
def test_depth_rays_use_the_distance_beyond_90_degrees(lens):
    rig = lens_rig(lens)
    spec = CylinderSpec.from_rig(rig, rho=0.9, height=16, width=64)
    rays, offs = depth_rays(rig, spec)
    P = spec.points()
    for n, cam in enumerate(rig.cameras):
        assert cam.depth_is_distance
        _, d, front = cam.project_depth(P)
        np.testing.assert_allclose(d, np.linalg.norm(P - cam.position, axis=-1))
        X = spec.centre + offs[n] + d[..., None] * rays[n]
        np.testing.assert_allclose(X[front], P[front], atol=1e-4)
        behind = front & (((P - cam.position) @ cam.rotation)[..., 2] < 0)
        assert behind.any() and np.isfinite(rays[n][behind]).all()


def test_focal_n_is_the_paraxial_focal():
    fish, ft = lens_rig(FISHEYE), lens_rig(FTHETA)
    np.testing.assert_allclose(focal_n(fish), math.sqrt(24 / 96 * 24 / 64), rtol=1e-6)   # K's fx, fy
    # f-theta: K is not used by the lens; the polynomial's slope at the axis (x: times c)
    np.testing.assert_allclose(focal_n(ft), math.sqrt(21 * 1.01 / 96 * 21 / 64), rtol=1e-6)
    assert fish.cameras[0].paraxial_focal == (24.0, 24.0)
    # a pinhole matched to the lens at its centre has the same focal_n
    pin = Rig(cameras=tuple(c.replace(distortion=None) for c in fish.cameras))
    np.testing.assert_allclose(focal_n(pin), focal_n(fish))


def test_cylinder_of_a_wide_fisheye_rig_counts_its_fov_as_pi():
    rig = lens_rig(FISHEYE, f=16.0, height=96)           # the image circle fits: the vertical FoV is 200 degrees
    assert rig.cameras[0].vertical_fov > math.pi
    spec = CylinderSpec.from_rig(rig, rho=0.9, height=8, width=32)
    assert spec.radius == pytest.approx(8.0 / math.tan(0.9 * math.pi / 2))


@pytest.mark.parametrize("lens", [FISHEYE, FTHETA, [-0.2, 0.05, 0.001, -0.002]], ids=["fisheye", "ftheta", "opencv"])
def test_lidar_depth_lands_on_the_lens_pixel(lens):
    cam = lens_rig(lens).cameras[0]
    rng = np.random.default_rng(2)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = cam.position + d * rng.uniform(2.0, 30.0, (4000, 1))
    m = lidar_depth_map(pts, cam)
    np.testing.assert_array_equal(m, lidar_depth_map_reference(pts, cam))
    q = (pts - cam.position) @ cam.rotation
    uv, ok = cam.distortion.project(cam.K, q) if cam.distortion is not None else (None, None)
    want = np.linalg.norm(q, axis=1) if cam.depth_is_distance else q[:, 2]
    px = np.rint(uv).astype(int)
    ok &= (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    assert ok.sum() > 200
    # every landed pixel holds the nearest of the points Lens.project puts there
    for i in np.flatnonzero(ok)[:300]:
        same = ok & (px[:, 0] == px[i, 0]) & (px[:, 1] == px[i, 1])
        assert m[px[i, 1], px[i, 0]] == pytest.approx(want[same].min(), rel=1e-6)
    if cam.depth_is_distance:
        assert (ok & (q[:, 2] < 0)).any()                 # points behind the image plane reach the map


def _sphere(radius: float, centre, n: int = 120) -> Gaussians:
    """Opaque Gaussians tiling a sphere about ``centre``: every ray from it meets the surface at ``radius``."""
    k = np.arange(n * n) + 0.5
    z = 1 - 2 * k / (n * n)
    a = math.pi * (3 - math.sqrt(5)) * k
    d = np.stack([np.sqrt(1 - z * z) * np.cos(a), np.sqrt(1 - z * z) * np.sin(a), z], 1)
    means = (np.asarray(centre) + radius * d).astype(np.float32)
    step = radius * math.sqrt(4 * math.pi / (n * n))
    # flat discs tangent to the sphere: the normal (local z) along d
    zax = np.array([0, 0, 1.0])
    axis = np.cross(zax, d)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.arctan2(s[:, 0], d[:, 2])
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), [1.0, 0, 0])
    quats = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], 1).astype(np.float32)
    log_scales = np.log(np.tile([[step, step, 0.005]], (len(means), 1))).astype(np.float32)
    return Gaussians(means, quats, log_scales, np.full(len(means), 8.0, np.float32),
                     np.full((len(means), 1, 3), 0.5, np.float32))


@pytest.mark.parametrize("lens", [FISHEYE, FTHETA, [-0.2, 0.05, 0.001, -0.002]], ids=["fisheye", "ftheta", "opencv"])
def test_model_depth_along_true_rays(lens):
    """Gaussians on a 10 m sphere about the camera: every pixel with a ray reads 10 m (its camera z for an opencv
    lens), fisheye pixels beyond 90 degrees included."""
    cam = lens_rig(lens).cameras[0]
    depth, alpha = render_ray_depth(_sphere(10.0, cam.position), cam)
    d = cam.depth_rays()
    has = np.all(np.isfinite(d), axis=-1)
    assert has.sum() > 1000 and (alpha[has] > 0.99).mean() > 0.99
    want = 10.0 / np.linalg.norm(d, axis=-1)              # point = depth * ray at 10 m from the centre
    np.testing.assert_allclose(depth[has & (alpha > 0.99)], want[has & (alpha > 0.99)], rtol=2e-3)
    assert (depth[~has] == 0).all() and (alpha[~has] == 0).all()


def test_lidar_eval_on_a_fisheye_camera():
    """The whole depth check on a fisheye camera: LiDAR points on the sphere give ratio 1, 10 % further 1/1.1."""
    cam = lens_rig(FISHEYE).cameras[0].replace(name="fish")
    scene = Scene(gaussians=_sphere(10.0, cam.position), background=None, rig=Rig(cameras=(cam,)))
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = summarise(camera_depths(scene, cam.position + 10.0 * d, width=96))
    assert s["all"]["points"] > 500 and s["all"]["median_ratio"] == pytest.approx(1.0, abs=3e-3)
    s2 = summarise(camera_depths(scene, cam.position + 11.0 * d, width=96))
    assert s2["all"]["median_ratio"] == pytest.approx(1 / 1.1, abs=3e-3)


def test_cylinder_cli_on_a_fisheye_rig(tmp_path, capsys):
    rig = lens_rig(FISHEYE)
    cams = []
    for i, cam in enumerate(rig.cameras):
        img = np.zeros((cam.height, cam.width, 3), np.uint8)
        img[...] = (60 * (i + 1), 100, 200 - 40 * i)
        cv2.imwrite(str(tmp_path / f"c{i}.png"), img)
        cams.append({**cam.to_dict(), "image": f"c{i}.png"})
    (tmp_path / "rig.json").write_text(json.dumps({"cameras": cams}))
    out = tmp_path / "pano.png"
    assert main(["cylinder", str(tmp_path / "rig.json"), "--out", str(out), "--height", "16", "--width", "64"]) == 0
    text = capsys.readouterr().out
    assert "covered: 100.00%" in text
    pano = cv2.imread(str(out))[..., ::-1].astype(np.float32) / 255
    # the panorama is the cameras' images sampled through their lenses (cw overlay: the last valid camera wins)
    spec = CylinderSpec.from_rig(rig, rho=0.9, height=16, width=64)
    maps, valid = project_rig(spec, rig, [cv2.imread(str(tmp_path / f"c{i}.png"))[..., ::-1].astype(np.float32)
                                          / 255 for i in range(4)])
    assert valid.any(axis=0).all()
    np.testing.assert_allclose(pano, overlay(maps, "cw", valid=valid), atol=1 / 255 + 1e-6)



@pytest.mark.skipif(not (REPO / "models" / "xyzcyl-cpu-v1" / "model.json").is_file(), reason="no shipped model")
def test_reconstruct_a_fisheye_rig_with_lidar_and_detail():
    """The whole input path on lens cameras (the example rig's cameras given a fisheye lens): LiDAR depth for every
    camera, detail cells on the lens cameras, every Gaussian finite."""
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.rig import load_rig

    rig = load_rig(EXAMPLE_RIG)
    lens = {**FISHEYE, "max_angle_deg": 80.0}
    fish = Rig(cameras=tuple(c.replace(distortion=lens) for c in rig.cameras))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))
    d[:, 2] = -np.abs(d[:, 2]) * 0.2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lidar = d * rng.uniform(3.0, 40.0, (len(d), 1)) + [0.0, 0.0, 1.8]
    rec = Reconstructor.load(REPO / "models" / "xyzcyl-cpu-v1", threads=2)
    scene = rec.reconstruct(fish, rig.load_images(), lidar=lidar)
    c = scene.counts
    assert c["lidar_cameras"] == len(rig.cameras) and c["detail"] > 10000 and c["detail_lidar"] > 0
    g = scene.gaussians
    assert np.isfinite(g.means).all() and np.isfinite(g.log_scales).all() and np.isfinite(g.quats).all()


@pytest.mark.skipif(not (REPO / "models" / "xyzcyl-cpu-v1" / "model.json").is_file(), reason="no shipped model")
def test_depth_files_of_lens_cameras_are_taken_as_the_cameras_depth():
    """A fisheye camera's supplied depth map (distances along its pixels' rays) goes to the network as it is,
    resized like a pinhole's (the depth rays are in the same convention)."""
    from xyzcyl.runtime.inference import Reconstructor, resize_nearest

    rig = lens_rig(FISHEYE, n=2)
    rec = Reconstructor.load(REPO / "models" / "xyzcyl-cpu-v1", threads=1)
    imgs = [np.zeros((c.height, c.width, 3), np.float32) for c in rig.cameras]
    dist = np.full((64, 96), 7.5, np.float32)
    _, depth, mask = rec.prepare(rig, imgs, [dist, None])
    assert mask.tolist() == [1.0, 0.0]
    np.testing.assert_array_equal(depth[0, 0], resize_nearest(dist, *rec.info.depth_size))
