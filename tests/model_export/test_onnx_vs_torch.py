"""The exported graphs run by onnxruntime (xyzcyl.runtime.inference) against XYZCylinder.forward in torch on the
same inputs: tiny config, 5, 6 and 8 cameras (the graphs were exported with 6: the camera axis is dynamic).

Tolerances (float32 everywhere; both sides run the same operations in another order / with other kernels), as a
fraction of max(1, max |torch output|):
- outputs upstream of the pixel-projection scatter (occupancy logits, pixel Gaussians): float32 round-off of a few
  ulps per operation accumulated through ~100 layers; measured <= 2.5e-6; bound TIGHT = 2e-5.
- outputs downstream of it (appearance plane, volume CPFGs and Gaussians, background): eq. 41 bins each pixel
  Gaussian's mean with floor(), so a mean within ~1e-6 m of a bin edge may land in the neighbouring bin on one side
  only; its feature then moves by one column/row of the volume cylinder, which changes the planes by about that
  feature times proj_conv's last layer (std 1e-3 at initialisation) -- a few 1e-4 at most. Measured 1.1e-5 with
  0 bin flips (the planes' own round-off); bound LOOSE = 2e-4, and the assertion message reports the flips.
Selection runs once, on the onnxruntime logits, and both sides decode the same voxels (forward's voxel_idx).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from xyzcyl.model_export.lifting import frustum_coords_torch, to_torch
from xyzcyl.model_export.model import GAUSSIAN_KEYS
from xyzcyl.runtime.inference import Reconstructor, select_voxels
from xyzcyl.runtime.lifting import background_grid
from xyzcyl.testing.model import overlap_rig

TIGHT, LOOSE = 2e-5, 2e-4


def _check(name, got, ref, rel, note=""):
    got, ref = np.asarray(got), np.asarray(ref)
    assert got.shape == ref.shape, f"{name}: shape {got.shape} != torch {ref.shape}"
    err = float(np.abs(got - ref).max()) if got.size else 0.0
    bound = rel * max(1.0, float(np.abs(ref).max()) if ref.size else 0.0)
    assert err <= bound, f"{name}: max |onnx - torch| = {err:.3g} > {bound:.3g} {note}"


@pytest.fixture(scope="module")
def rec(tiny_export):
    return Reconstructor.load(tiny_export.dir, threads=2)


def _inputs(n, seed=0):
    rig = overlap_rig(n)
    rng = np.random.default_rng(seed)
    images = [rng.random((rig.cameras[0].height, rig.cameras[0].width, 3), dtype=np.float32) for _ in range(n)]
    return rig, images


def _bin_flips(model, means_a, means_b, spec_vol) -> int:
    """How many pixel-Gaussian anchors fall into another eq. 41 bin (plane, row or column) on the two sides."""
    cfg = model.cfg
    out = []
    for m in (means_a, means_b):
        c = frustum_coords_torch(torch.tensor(m), torch.tensor(spec_vol), cfg.grid.r_min, cfg.grid.r_max)
        t, s, p = (c[:, 0] + 1) / 2, (c[:, 1] + 1) / 2, (c[:, 2] + 1) / 2
        out.append(torch.stack([torch.floor(t * cfg.volume.k), torch.floor(s * cfg.cylinder.width),
                                torch.floor(p * cfg.cylinder.height)], 1))
    return int((out[0] != out[1]).any(1).sum())


@pytest.mark.parametrize("n", [5, 6, 8])
def test_reconstruct_matches_torch(tiny_export, rec, n):
    model = tiny_export.model
    rig, images = _inputs(n, seed=n)
    depths = None
    if n == 6:   # a supplied depth map for two cameras: the graph's depth/depth_mask path
        depths = [None] * n
        depths[1] = np.full((64, 128), 7.5, np.float32)
        depths[4] = np.linspace(2.0, 30.0, 64 * 128, dtype=np.float32).reshape(64, 128)
    scene = rec.reconstruct(rig, images, depths, detail=None)
    imgs, depth, mask = rec.prepare(rig, images, depths)
    lift, _ = rec.lifting(rig)
    idx = select_voxels(rec._run("encode", {"images": imgs, "depth": depth, "depth_mask": mask, **lift})["occ_logits"],
                        rec.info.max_voxels)
    assert scene.counts["voxels"] == idx.size > 0
    with torch.no_grad():
        out = model(torch.from_numpy(imgs), to_torch(lift), depth=torch.from_numpy(depth),
                    depth_mask=torch.from_numpy(mask), voxel_idx=torch.from_numpy(idx))
    ref = {k: out["gaussians"][k].numpy() for k in GAUSSIAN_KEYS}
    # the scene prunes invisible Gaussians; compare the graphs' raw outputs (volume first, then pixel: forward's order)
    enc = rec._run("encode", {"images": imgs, "depth": depth, "depth_mask": mask, **lift})
    vol = rec._run("volume", {"geo_cpfg": enc["geo_cpfg"], "app_cpfg": enc["app_cpfg"], "voxel_idx": idx,
                              "vol_coords": lift["vol_coords"], "voxel_centres": lift["voxel_centres"]})
    nv = out["n_volume"]
    assert nv == vol["volume_means"].shape[0] == 2 * idx.size and out["n_pixel"] == enc["pixel_means"].shape[0]
    flips = _bin_flips(model, enc["pixel_means"], ref["means"][nv:], lift["spec_vol"])
    note = f"({flips} eq. 41 bin flips)"
    _check("occ_logits", enc["occ_logits"], out["occ_logits"].numpy(), TIGHT)
    _check("app_plane", enc["app_plane"], out["app_plane"].numpy(), LOOSE, note)
    for k in GAUSSIAN_KEYS:
        _check(f"pixel {k}", enc[f"pixel_{k}"], ref[k][nv:], TIGHT)
        _check(f"volume {k}", vol[f"volume_{k}"], ref[k][:nv], LOOSE, note)
    # the scene's Gaussians are these, minus the invisible ones
    keep = 1 / (1 + np.exp(-np.concatenate([vol["volume_opacity_logits"], enc["pixel_opacity_logits"]]))) >= 0.99 / 255
    assert len(scene.gaussians) == int(keep.sum()) == scene.counts["total"]
    np.testing.assert_array_equal(scene.gaussians.means,
                                  np.concatenate([vol["volume_means"], enc["pixel_means"]])[keep])
    # background network per view: graph vs torch (ray grids of two input cameras)
    spec = rec.background_spec(rig)
    grids = np.stack([background_grid(spec, c.K, c.cam_to_ego, 40, 20) for c in rig.cameras[:2]])
    bg = rec._run("background", {"app_plane": enc["app_plane"], "grids": grids})["background"]
    with torch.no_grad():
        bref = model.background(out["app_plane"], torch.from_numpy(grids)).numpy()
    _check("background", bg, bref, LOOSE, note)


def test_selection_matches_torch(tiny_export):
    """numpy select_voxels == XYZCylinder.select_voxels on the same logits, top-k branch included."""
    model = tiny_export.model
    rng = np.random.default_rng(1)
    logits = rng.normal(size=(2, *model.cfg.grid.shape)).astype(np.float32)
    ref = model.select_voxels(torch.from_numpy(logits), source="predicted").numpy()
    got = select_voxels(logits, model.cfg.volume.max_voxels)
    assert ref.size == model.cfg.volume.max_voxels   # ~half of 1600 voxels positive: top-k ran
    np.testing.assert_array_equal(got, ref)
    few = logits.copy()
    few[1] = few[0] - 1.0
    few[1].reshape(-1)[[3, 77]] = few[0].reshape(-1)[[3, 77]] + 0.5
    np.testing.assert_array_equal(select_voxels(few, 300), model.select_voxels(torch.from_numpy(few)).numpy())
    assert select_voxels(np.zeros_like(logits), 300).size == 0


def test_volume_graph_takes_zero_voxels(tiny_export, rec):
    rig, images = _inputs(6)
    imgs, depth, mask = rec.prepare(rig, images)
    lift, _ = rec.lifting(rig)
    enc = rec._run("encode", {"images": imgs, "depth": depth, "depth_mask": mask, **lift})
    vol = rec._run("volume", {"geo_cpfg": enc["geo_cpfg"], "app_cpfg": enc["app_cpfg"],
                              "voxel_idx": np.zeros(0, np.int64), "vol_coords": lift["vol_coords"],
                              "voxel_centres": lift["voxel_centres"]})
    assert vol["volume_means"].shape == (0, 3) and vol["volume_sh"].shape == (0, 1, 3)


def test_same_result_for_any_thread_count(tiny_export, rec):
    """ScatterElements (scatter_add) is deterministic in onnxruntime (ScatterND with add, what index_add exports to,
    loses updates with several threads): 1 and 2 threads give bit-identical planes and Gaussians, run to run."""
    rig, images = _inputs(6, seed=11)
    one = Reconstructor.load(tiny_export.dir, threads=1)
    a = one.reconstruct(rig, images, detail=None)
    for _ in range(2):
        b = rec.reconstruct(rig, images, detail=None)
        np.testing.assert_array_equal(a.app_plane, b.app_plane)
        for k in GAUSSIAN_KEYS:
            np.testing.assert_array_equal(getattr(a.gaussians, k), getattr(b.gaussians, k))
        np.testing.assert_array_equal(a.background.image, b.background.image)
