import math
import warnings

import numpy as np
import pytest
import torch
from xyzcyl.model_export.lifting import (
    frustum_coords_torch,
    lift,
    rig_inputs,
    sample_cpfg,
    sample_plane_wrapped,
    to_torch,
)
from xyzcyl.runtime.cylinder import CylinderSpec, frustum_annulus_coords, overlay, project_rig
from xyzcyl.runtime.rig import ring_rig
from xyzcyl.testing.model import tiny_config


@pytest.mark.parametrize("n", [5, 6])
def test_flat_colours_give_expected_columns(n):
    """Cameras at the cylinder centre (ring radius 0) with flat, distinct colours: every cylinder column at
    angle theta must show the last (F+) / first (F-) camera whose FoV contains theta; and the torch path must
    agree with runtime.cylinder's numpy sampling + overlay."""
    hfov = 1.3 * 360.0 / n
    rig = ring_rig(n, hfov_deg=hfov, width=96, height=48, ring_radius=0.0)
    cfg = tiny_config()
    inp = rig_inputs(rig, cfg)
    colours = np.array([[0.1 + 0.15 * k, 1.0 - 0.1 * k, 0.3 + 0.05 * k] for k in range(n)], dtype=np.float32)
    images = torch.from_numpy(np.broadcast_to(colours[:, :, None, None], (n, 3, 48, 96)).copy())
    fp, fm = lift(images, inp["grid_occ"], inp["sel_cw_occ"], inp["sel_ccw_occ"])
    fp, fm = fp[0].permute(1, 2, 0).numpy(), fm[0].permute(1, 2, 0).numpy()  # [H, W, 3]

    H, W = cfg.cylinder.height, cfg.cylinder.width
    row = H // 2
    yaws = np.array([-360.0 * k / n for k in range(n)])  # ring_rig: clockwise order
    checked = 0
    for j in range(W):
        theta = math.degrees(math.pi - 2 * math.pi * (j + 0.5) / W)
        d = (theta - yaws + 180.0) % 360.0 - 180.0
        # margin: 1.5 columns (bilinear footprint at the image edge) + a little for the half-pixel border
        margin = 1.5 * 360.0 / W
        inside = np.abs(d) < hfov / 2 - margin
        if np.any(np.abs(np.abs(d) - hfov / 2) <= margin):
            continue  # near a camera edge: skip
        seen = np.flatnonzero(inside)
        assert seen.size, "the rig covers all directions"
        np.testing.assert_allclose(fp[row, j], colours[seen.max()], atol=1e-6)  # float32 sums of one term
        np.testing.assert_allclose(fm[row, j], colours[seen.min()], atol=1e-6)
        checked += 1
    assert checked > W // 3

    # torch path == numpy sampling + gamma overlay (same bilinear semantics; float32 rounding only)
    from xyzcyl.runtime.lifting import LiftingParams
    spec = LiftingParams.from_config_dict(cfg.to_dict()).spec(rig, "occupancy")
    maps, valid = project_rig(spec, rig, [np.broadcast_to(c, (48, 96, 3)).astype(np.float32) for c in colours])
    np.testing.assert_allclose(fp, overlay(maps, "cw", valid=valid), atol=1e-5)
    np.testing.assert_allclose(fm, overlay(maps, "ccw", valid=valid), atol=1e-5)


def test_frustum_coords_torch_matches_numpy():
    spec = CylinderSpec(centre=[0.3, -0.2, 1.7], radius=25.0, z_min=-3.0, z_max=13.0, height=8, width=64)
    rng = np.random.default_rng(1)
    pts = rng.uniform([-40, -40, -3], [40, 40, 13], size=(500, 3))
    ref = frustum_annulus_coords(pts, spec, 0.5, 57.0)
    st = torch.tensor([*spec.centre, spec.radius, spec.z_min, spec.z_max], dtype=torch.float64)
    got = frustum_coords_torch(torch.from_numpy(pts), st, 0.5, 57.0).numpy()
    # column coordinate: theta = +-pi is the same column (2s-1 = -1 or 1), compare modulo 2
    got[:, 1] = np.where(np.abs(got[:, 1] - ref[:, 1]) > 1, got[:, 1] - 2 * np.sign(got[:, 1]), got[:, 1])
    np.testing.assert_allclose(got, ref, atol=1e-9)  # float64 both sides


def test_sample_cpfg_planes_and_wrap():
    K, H, W = 6, 4, 16
    # value = plane index k: trilinear sampling at t gives t*K - 1/2 between the first and last plane centres
    g = torch.arange(K, dtype=torch.float64).view(1, 1, K, 1, 1).expand(1, 1, K, H, W).contiguous()
    t = torch.linspace(0.5 / K, 1 - 0.5 / K, 11, dtype=torch.float64)
    coords = torch.stack([2 * t - 1, torch.full_like(t, 0.1), torch.zeros_like(t)], dim=1)
    np.testing.assert_allclose(sample_cpfg(g, coords)[:, 0].numpy(), (t * K - 0.5).numpy(), atol=1e-12)
    # value = column index: across the theta seam (s = 0 == s = 1) the sample blends column W-1 and column 0
    g = torch.arange(W, dtype=torch.float64).view(1, 1, 1, 1, W).expand(1, 1, K, H, W).contiguous()
    for s, expect in ((0.0, (W - 1) / 2), (0.25 / W, (W - 1) * 0.25), (1 - 0.25 / W, (W - 1) * 0.75)):
        c = torch.tensor([[0.0, 2 * s - 1, 0.0]], dtype=torch.float64)
        assert sample_cpfg(g, c)[0, 0].item() == pytest.approx(expect, abs=1e-9)
    plane = g[:, :, 0]
    grid = torch.tensor([[[[-1.0, 0.0]]]], dtype=torch.float64)
    assert sample_plane_wrapped(plane, grid).item() == pytest.approx((W - 1) / 2, abs=1e-9)

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/model_export/conftest.py


def test_to_torch_copies_read_only_arrays_and_shares_writable_ones():
    ro = np.arange(6, dtype=np.float32).reshape(2, 3)
    ro.flags.writeable = False   # as the runtime's lifting cache hands them out
    rw = np.zeros((2, 3), np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # torch warns when it would share a read-only buffer
        out = to_torch({"ro": ro, "rw": rw})
    out["ro"] += 1
    out["rw"] += 1
    assert ro[0, 0] == 0 and out["ro"][0, 0] == 1   # the cache is untouched
    assert rw[0, 0] == 1                            # a writable float32 array is not copied
