"""runtime/lifting.py: the numpy half of the network's UCCM lifting (the torch half is tested in
tests/model_export/test_lifting.py)."""

import numpy as np
from xyzcyl.runtime.cylinder import CylinderSpec, overlay
from xyzcyl.runtime.lifting import (
    LiftingParams,
    background_grid,
    build_lifting_inputs,
    overlay_selection,
    overlay_selection_reference,
    voxel_centres,
)
from xyzcyl.runtime.rig import ring_rig


def test_overlay_selection_matches_gamma_fold():
    rng = np.random.default_rng(0)
    valid = rng.random((5, 7, 9)) < 0.4
    cw, ccw = overlay_selection(valid)
    rcw, rccw = overlay_selection_reference(valid)
    np.testing.assert_array_equal(cw, rcw)
    np.testing.assert_array_equal(ccw, rccw)
    # and with runtime.cylinder.overlay on one-hot camera indicators (channel axis last)
    onehot = np.broadcast_to(np.eye(5)[:, None, None, :], (5, 7, 9, 5)) * valid[..., None]
    np.testing.assert_array_equal(np.moveaxis(overlay(onehot, "cw"), -1, 0), cw)
    np.testing.assert_array_equal(np.moveaxis(overlay(onehot, "ccw"), -1, 0), ccw)
    assert np.all(cw.sum(0) == valid.any(0)) and np.all(ccw.sum(0) == valid.any(0))


def test_background_grid_forward_camera():
    rig = ring_rig(6, hfov_deg=78.0, width=128, height=64)
    spec = CylinderSpec(centre=rig.cameras[0].position, radius=20.0, z_min=-3, z_max=13, height=8, width=64)
    cam = rig.cameras[0]
    g = background_grid(spec, cam.K, cam.cam_to_ego, cam.width, cam.height)
    assert g.shape == (cam.height, cam.width, 2)
    # principal ray: horizontal, from the centre -> theta = yaw 0 (u = 0), dz = 0 (v = 0)
    cx, cy = cam.K[0, 2], cam.K[1, 2]
    u = (g[int(cy), int(cx)] + g[int(cy) + 1, int(cx) + 1]) / 2
    np.testing.assert_allclose(u, [0.0, 0.0], atol=0.05)
    assert np.all(np.diff(g[:, int(cx), 1]) > 0)  # rows go down the cylinder


def test_voxel_centres_layout():
    c = voxel_centres((-40, -40, -3, 40, 40, 13), 4.0)
    assert c.shape == (4, 20, 20, 3)
    np.testing.assert_allclose(c[0, 0, 0], [-38, -38, -1])
    np.testing.assert_allclose(c[1, 2, 3], [-40 + 14, -40 + 10, -3 + 6])



def test_build_lifting_inputs_shapes_and_selection():
    rig = ring_rig(5, hfov_deg=95.0, width=64, height=32)
    cfg = {"cylinder": {"height": 8, "width": 32, "z_range": [-3.0, 13.0], "rho_occ": 0.9, "rho_vol": 0.98,
                        "rho_pix": 0.98, "dh_occ": 0.0, "dh_vol": 0.4, "dh_pix": 0.4},
           "grid": {"pc_range": [-40, -40, -3, 40, 40, 13], "voxel_size": 8.0, "r_min": 0.5, "r_max": 57.0},
           "pixel": {"k_in": 1, "k_out": 2}}
    params = LiftingParams.from_config_dict(cfg)
    inp = build_lifting_inputs(rig, params)
    for m in ("occ", "vol", "pix"):
        assert inp[f"grid_{m}"].shape == (5, 8, 32, 2) and inp[f"sel_cw_{m}"].shape == (5, 8, 32)
        assert inp[f"grid_{m}"].dtype == np.float32
    assert inp["pix_rays"].shape == (5, 8, 32, 3) and inp["pix_offsets"].shape == (5, 3)
    assert inp["pix_dirs"].shape == (16, 64, 3)
    assert inp["grid_pixc"].shape == (5, 16, 64, 2) and inp["sel_pixc"].shape == (5, 16, 64)
    assert set(np.unique(inp["sel_pixc"].sum(0))) <= {0.0, 1.0}                       # one-hot or unseen
    # the fine lattice's cylinder points are pix_dirs' rays at radius R_u: every seen fine pixel's grid value
    # lies inside its camera's image
    assert (np.abs(inp["grid_pixc"][inp["sel_pixc"] > 0]) <= 1.0 + 1e-6).all()
    np.testing.assert_allclose(np.hypot(inp["pix_dirs"][..., 0], inp["pix_dirs"][..., 1]), 1.0, atol=1e-6)
    assert inp["occ_coords"].shape == (2, 10, 10, 3) and np.isfinite(inp["occ_coords"]).all()
    # the volume cylinder is higher (dh 0.4) and wider (rho 0.98 -> smaller radius) than the occupancy one
    assert inp["spec_vol"][2] == np.float32(inp["spec_occ"][2] + 0.4)
    assert inp["spec_vol"][3] < inp["spec_occ"][3]


def test_depth_rays_back_project_cylinder_pixels():
    """A camera depth equal to the cylinder pixel's own camera z must back-project onto that pixel's surface
    point: X = c_n + z_n(P) * rays[n] = P."""
    rig = ring_rig(6, hfov_deg=80.0, width=64, height=32, ring_radius=0.7)
    spec = CylinderSpec.from_rig(rig, rho=0.9, height=8, width=32)
    from xyzcyl.runtime.lifting import depth_rays
    rays, offs = depth_rays(rig, spec)
    P = spec.points()
    for n, cam in enumerate(rig.cameras):
        _, z, front = cam.project(P)
        X = spec.centre + offs[n] + z[..., None] * rays[n]
        np.testing.assert_allclose(X[front], P[front], atol=1e-4)  # float32 storage of rays at ~25 m


def test_focal_n_hand_values():
    import math

    from xyzcyl.runtime.lifting import focal_n
    from xyzcyl.runtime.rig import Camera, Rig

    rig = ring_rig(4, hfov_deg=90.0, width=64, height=32)       # square pixels: fx = fy = 32 / tan(45 deg) = 32
    f = focal_n(rig)
    assert f.shape == (4,) and f.dtype == np.float32
    np.testing.assert_allclose(f, math.sqrt(32 / 64 * 32 / 32), rtol=1e-6)
    # resizing an image (any aspect) leaves it unchanged: fx / W and fy / H are both kept
    small = Rig([c.resized(40, 24) for c in rig.cameras])
    np.testing.assert_allclose(focal_n(small), f, rtol=1e-6)
    # a narrower lens has the longer focal: 50 deg against 90 deg across the same image, tan(45) / tan(25)
    np.testing.assert_allclose(focal_n(ring_rig(4, hfov_deg=50.0, width=64, height=32)) / f,
                               1 / math.tan(math.radians(25)), rtol=1e-6)
    # equirectangular: W / (2 pi) and H / pi pixels per radian
    pano = Rig([Camera(name="pano", width=512, height=256, K=None, cam_to_ego=np.eye(4), model="equirectangular")])
    np.testing.assert_allclose(focal_n(pano), 1 / (math.pi * math.sqrt(2)), rtol=1e-6)
    cfg = {"cylinder": {"height": 8, "width": 32, "z_range": [-3.0, 13.0], "rho_occ": 0.9, "rho_vol": 0.98,
                        "rho_pix": 0.98, "dh_occ": 0.0, "dh_vol": 0.4, "dh_pix": 0.4},
           "grid": {"pc_range": [-40, -40, -3, 40, 40, 13], "voxel_size": 8.0, "r_min": 0.5, "r_max": 57.0},
           "pixel": {"k_in": 1, "k_out": 2}}
    np.testing.assert_array_equal(build_lifting_inputs(rig, LiftingParams.from_config_dict(cfg))["focal_n"], f)
