"""Dataset over a tiny generated data set: shapes, seeding, grid orientation, flip consistency, jitter."""

import json

import numpy as np
import pytest
import torch
from xyzcyl.model_export.config import ConfigError, preset
from xyzcyl.model_export.dataset import (
    DataError,
    DatasetConfig,
    SceneDataset,
    collate_scenes,
    load_rig_folder,
    mirror_order,
)

PC = (-40.0, -40.0, -3.0, 40.0, 40.0, 13.0)


@pytest.fixture
def tiny_data(tiny_synth_data):
    return tiny_synth_data


def _points(cam, depth, uv):
    """Back-project pixels uv [M, 2] with optical-axis depth [M] to ego points [M, 3]."""
    K = cam.K
    x = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], -1)
    pc = x * depth[:, None]
    return pc @ cam.cam_to_ego[:3, :3].T + cam.cam_to_ego[:3, 3]


def _voxel_index(p, voxel=0.8):
    lo = np.array(PC[:3])
    ijk = np.floor((p - lo) / voxel).astype(int)          # (x, y, z) indices
    return ijk[:, 2], ijk[:, 1], ijk[:, 0]                # -> [L_z, L_y, L_x] order


def test_item_shapes_and_seeding(tiny_data):
    ds = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=3))
    it = ds[0]
    assert it["images"].shape == (6, 3, 32, 56) and it["images"].dtype == torch.float32
    assert 0 <= float(it["images"].min()) and float(it["images"].max()) <= 1
    assert it["depth"].shape == (6, 1, 32, 56) and it["sky"].shape == (6, 1, 32, 56)
    assert not bool((it["depth"][it["depth_valid"]] <= 0).any())
    assert float(it["depth"].max()) <= 80.0 and float(it["targets"]["depth"].max()) <= 80.0   # max_depth
    t = it["targets"]
    assert t["images"].shape == (3, 3, 32, 56) and t["depth"].shape == (3, 32, 56) and t["K"].shape == (3, 3, 3)
    assert it["occupancy"].shape == (20, 100, 100) and it["bev"].shape == (100, 100)
    assert set(np.unique(it["occupancy"].numpy())) <= {0, 1}
    # sky pixels carry no depth
    assert not bool((t["depth_valid"] & (t["sky"] > 0.5)).any())
    # same seed/epoch -> same subset; other epochs draw other subsets (12 forward targets, 3 drawn)
    assert ds[0]["targets"]["names"] == t["names"]
    names = set()
    for e in range(6):
        ds.set_epoch(e)
        names.add(tuple(ds[0]["targets"]["names"]))
    assert len(names) > 1
    assert collate_scenes([it, it])[1] is it


def test_occupancy_orientation_matches_depth(tiny_data):
    """Surface points seen by the input cameras lie in (or next to) occupied voxels of the loaded grid."""
    it = SceneDataset(tiny_data, DatasetConfig())[0]
    occ = it["occupancy"].numpy()
    hits = []
    for n, cam in enumerate(it["rig"].cameras):
        d = it["depth"][n, 0].numpy()
        v, u = np.nonzero(it["depth_valid"][n, 0].numpy() & (d < 30))
        p = _points(cam, d[v, u], np.stack([u, v], -1).astype(float))
        z, y, x = _voxel_index(p)
        near = np.zeros(len(p), bool)
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    zz, yy, xx = z + dz, y + dy, x + dx
                    ok = (zz >= 0) & (zz < 20) & (yy >= 0) & (yy < 100) & (xx >= 0) & (xx < 100)
                    near[ok] |= occ[zz[ok], yy[ok], xx[ok]] > 0
        hits.append(near)
    hits = np.concatenate(hits)
    assert hits.size > 100
    # a swapped axis would put most surface points into free voxels; a few thin objects may fall between voxels
    assert hits.mean() > 0.95


def test_flip_keeps_calibration_consistent(tiny_data):
    base = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=12))[0]
    flip = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=12, flip_prob=1.0))[0]
    assert flip["flipped"] and not base["flipped"]
    order = mirror_order(6)
    assert [c.name for c in flip["rig"].cameras] == [base["rig"].cameras[k].name for k in order]
    M = np.diag([1.0, -1.0, 1.0])
    for n, k in enumerate(order):
        cam_f, cam_b = flip["rig"].cameras[n], base["rig"].cameras[k]
        assert torch.equal(flip["images"][n], base["images"][k].flip(-1))
        d = base["depth"][k, 0].numpy()
        v, u = np.nonzero(base["depth_valid"][k, 0].numpy())
        p = _points(cam_b, d[v, u], np.stack([u, v], -1).astype(float))
        # the mirrored camera sees the mirrored point at the flipped pixel, with the same depth
        uv, z, front = cam_f.project(p @ M.T)
        assert front.all()
        np.testing.assert_allclose(uv[:, 0], 55 - u, atol=1e-6)  # float64 projection round trip
        np.testing.assert_allclose(uv[:, 1], v, atol=1e-6)
        np.testing.assert_allclose(z, d[v, u], rtol=1e-6)
    assert torch.equal(flip["occupancy"], base["occupancy"].flip(1))
    assert torch.equal(flip["bev"], base["bev"].flip(0))
    tb, tf = base["targets"], flip["targets"]
    assert tb["names"] == tf["names"]
    assert torch.equal(tf["images"], tb["images"].flip(-1))
    np.testing.assert_allclose(tf["cam_to_ego"][:, 1, 3], -tb["cam_to_ego"][:, 1, 3])


def test_colour_jitter_only_touches_colours(tiny_data):
    base = SceneDataset(tiny_data, DatasetConfig())[0]
    jit = SceneDataset(tiny_data, DatasetConfig(brightness=0.3, contrast=0.3, saturation=0.3))[0]
    assert not torch.equal(base["images"], jit["images"])
    assert 0 <= float(jit["images"].min()) and float(jit["images"].max()) <= 1
    for a, b in zip(base["rig"].cameras, jit["rig"].cameras):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.cam_to_ego, b.cam_to_ego)
    assert torch.equal(base["depth"], jit["depth"]) and torch.equal(base["sky"], jit["sky"])
    assert base["targets"]["names"] == jit["targets"]["names"]


def test_lifting_inputs_and_errors(tiny_data, tmp_path):
    cfg = preset("cpu")
    it = SceneDataset(tiny_data, DatasetConfig(setting="ego-inward", num_targets=2), model_cfg=cfg)[0]
    assert it["lifting"]["grid_occ"].shape[0] == 6
    assert it["targets"]["background_grid"].shape == (len(it["targets"]["names"]), 32, 56, 2)
    with pytest.raises(ConfigError, match="setting"):
        DatasetConfig(setting="sideways")
    with pytest.raises(ConfigError, match="voxel_size"):
        SceneDataset(tiny_data, DatasetConfig(voxel_size=0.4), model_cfg=cfg)
    with pytest.raises(DataError, match="voxel_size"):
        SceneDataset(tiny_data, DatasetConfig(voxel_size=0.4))
    scene = tiny_data / "scene_000000"
    broken = tmp_path / "broken"
    (broken / "scene_000000").mkdir(parents=True)
    for f in ("rig.json", "occupancy.npz"):
        (broken / "scene_000000" / f).write_bytes((scene / f).read_bytes())
    (broken / "scene_000000" / "targets.json").write_text(json.dumps({"settings": {}}))
    with pytest.raises(DataError, match="setting"):
        SceneDataset(broken, DatasetConfig(setting="ego-inward"))
    with pytest.raises(DataError, match="no complete scene"):
        SceneDataset(tiny_data / "scene_000000" / "inputs")


def test_real_rig_folder(real_data):
    it = load_rig_folder(real_data / "nuscenes_ca9a282c")
    assert it["images"].shape == (6, 3, 900, 1600) and it["depth"] is None
    assert float(it["images"].max()) <= 1.0


def test_both_settings_draw_from_the_union(tiny_data):
    fwd = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=100))[0]["targets"]["names"]
    inw = SceneDataset(tiny_data, DatasetConfig(setting="ego-inward", num_targets=100))[0]["targets"]["names"]
    both = SceneDataset(tiny_data, DatasetConfig(setting="both", num_targets=100))[0]["targets"]
    assert len(both["names"]) == len(fwd) + len(inw) and both["images"].shape[0] == len(fwd) + len(inw)
    assert sorted(both["names"]) == sorted(fwd + inw)
    # a small T mixes: over a few epochs both settings' cameras are drawn
    ds = SceneDataset(tiny_data, DatasetConfig(setting="both", num_targets=2))
    seen = set()
    for e in range(8):
        seen.update(ds.item(0, e)["targets"]["names"])
    assert seen & set(fwd) and seen & set(inw)


def test_target_scale_keeps_targets_consistent(tiny_data):
    full = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=2))[0]["targets"]
    half = SceneDataset(tiny_data, DatasetConfig(setting="ego-forward", num_targets=2, target_scale=0.5))[0]
    t = half["targets"]
    assert t["names"] == full["names"] and (t["width"], t["height"]) == (28, 16)
    assert t["images"].shape == (2, 3, 16, 28) and t["depth"].shape == (2, 16, 28) and t["sky"].shape == (2, 16, 28)
    # 2x2 area means of the full-size arrays
    img = full["images"].numpy().reshape(2, 3, 16, 2, 28, 2).mean(axis=(3, 5))
    np.testing.assert_allclose(t["images"].numpy(), img, atol=1e-5)       # float32 area weights
    np.testing.assert_allclose(t["sky"].numpy(), full["sky"].numpy().reshape(2, 16, 2, 28, 2).mean(axis=(2, 4)),
                               atol=1e-6)
    # depth only where all four input pixels had depth, then their mean; no depth across the horizon
    v4 = full["depth_valid"].numpy().reshape(2, 16, 2, 28, 2).all(axis=(2, 4))
    d4 = full["depth"].numpy().reshape(2, 16, 2, 28, 2).mean(axis=(2, 4))
    assert np.array_equal(t["depth_valid"].numpy(), v4) and v4.any() and not v4.all()
    np.testing.assert_allclose(t["depth"].numpy()[v4], d4[v4], rtol=1e-5)
    assert not t["depth"].numpy()[~v4].any()
    # calibration: K follows u -> (u + 1/2) / 2 - 1/2
    K, K2 = full["K"][0], t["K"][0]
    assert K2[0, 0] == pytest.approx(K[0, 0] / 2) and K2[0, 2] == pytest.approx((K[0, 2] + 0.5) / 2 - 0.5)
    with pytest.raises(ConfigError, match="target_scale"):
        DatasetConfig(target_scale=0.0)
    with pytest.raises(DataError, match="target_scale"):          # 56 x 0.3 is not whole
        SceneDataset(tiny_data, DatasetConfig(target_scale=0.3))[0]
