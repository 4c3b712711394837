"""Surface (visibility-carved) occupancy labels and the per-camera input augmentation of dataset.py."""

import numpy as np
import pytest
import torch
from xyzcyl.model_export.config import ConfigError
from xyzcyl.model_export.dataset import (
    CAMERA_AUG_PRESET,
    OCC_UNKNOWN,
    CameraAug,
    DatasetConfig,
    SceneDataset,
    apply_camera_aug,
    camera_aug_fields,
    simulate_lidar,
    surface_labels,
)
from xyzcyl.runtime.rig import Camera

# ------------------------------------------------------------------------------------------ surface labels

# grid x 0..10, y -2..2, z -2..2 at 1 m: [L_z, L_y, L_x] = [4, 4, 10]; a wall at x in [5, 8) (3 voxels thick)
RANGE = (0.0, -2.0, -2.0, 10.0, 2.0, 2.0)
CAM_FORWARD = np.array([[0.0, 0.0, 1.0, 0.5],    # OpenCV camera at (0.5, 0, 0) looking down ego +x:
                        [-1.0, 0.0, 0.0, 0.0],   # camera x (right) = ego -y, camera y (down) = ego -z
                        [0.0, -1.0, 0.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]])


def _wall_scene(distortion=None):
    occ = np.zeros((4, 4, 10), bool)
    occ[:, :, 5:8] = True
    w = h = 64
    f = w / 2 / np.tan(np.radians(50))                  # 100 deg FoV: the wall face (+-24 deg) is well inside
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    cam = Camera(name="front", width=w, height=h, K=K, cam_to_ego=CAM_FORWARD, distortion=distortion)
    depth = np.full((1, h, w), 4.5, np.float32)        # plane x = 5 seen from x = 0.5, depth along the axis
    valid = np.ones((1, h, w), bool)
    return occ, cam, depth, valid


def test_surface_labels_keep_the_front_layer_of_a_wall():
    occ, cam, depth, valid = _wall_scene()
    lab = surface_labels(occ, RANGE, 1.0, [cam], depth, valid)
    assert lab.dtype == np.uint8 and lab.shape == occ.shape
    assert (lab[:, :, 5] == 1).all()                   # the face the camera sees (a hit on x = 5 lands behind it)
    assert (lab[:, :, 6:8] == OCC_UNKNOWN).all()        # inside the wall: unknown, ignored by the losses
    assert (lab[:, :, :5] == 0).all() and (lab[:, :, 8:] == 0).all()   # free in front and behind stays free
    # pixels not valid (sky / too deep) mark nothing: the hidden wall is all unknown
    assert (surface_labels(occ, RANGE, 1.0, [cam], depth, ~valid)[occ] == OCC_UNKNOWN).all()
    # dilation 1: occupied 26-neighbours of seen voxels join the surface, free voxels stay free
    dil = surface_labels(occ, RANGE, 1.0, [cam], depth, valid, dilation=1)
    assert (dil[:, :, 5:7] == 1).all() and (dil[:, :, 7] == OCC_UNKNOWN).all() and (dil[~occ] == 0).all()
    # seen from behind (camera at x = 9.5 looking down -x): the face x = 8 lies on a voxel boundary, and its hits
    # must land in the wall voxel (x index 7), not in the free one behind it
    pose = np.diag([-1.0, -1.0, 1.0, 1.0]) @ CAM_FORWARD     # turned 180 deg about z: at (-0.5, 0, 0) ...
    pose[0, 3] += 10.0                                       # ... moved to (9.5, 0, 0)
    back = Camera(name="back", width=cam.width, height=cam.height, K=cam.K, cam_to_ego=pose)
    assert np.allclose(back.position, [9.5, 0, 0]) and np.allclose(back.rotation[:, 2], [-1, 0, 0])
    lab_b = surface_labels(occ, RANGE, 1.0, [back], np.full_like(depth, 1.5), valid)
    assert (lab_b[:, :, 7] == 1).all() and (lab_b[:, :, 5:7] == OCC_UNKNOWN).all() and (lab_b[~occ] == 0).all()
    both = surface_labels(occ, RANGE, 1.0, [cam, back], np.concatenate([depth, np.full_like(depth, 1.5)]),
                          np.concatenate([valid, valid]))
    assert (both[:, :, [5, 7]] == 1).all() and (both[:, :, 6] == OCC_UNKNOWN).all()
    # the general (distorted-camera) path agrees with the pinhole fast path
    occ2, cam2, depth2, valid2 = _wall_scene(distortion=(1e-9, 0.0, 0.0, 0.0))
    assert cam2.distortion is not None
    assert np.array_equal(surface_labels(occ2, RANGE, 1.0, [cam2], depth2, valid2), lab)
    # keep: hidden occupied voxels (the ego car) become 1; kept free voxels stay free
    keep = np.zeros_like(occ)
    keep[:, :, 7:9] = True
    kept = surface_labels(occ, RANGE, 1.0, [cam], depth, valid, keep=keep)
    assert (kept[:, :, 7] == 1).all() and (kept[:, :, 8] == 0).all() and (kept[:, :, 6] == OCC_UNKNOWN).all()
    assert np.array_equal(kept[:, :, :7], lab[:, :, :7])


@pytest.fixture
def tiny_data(tiny_synth_data):
    return tiny_synth_data


def test_surface_labels_in_items_and_flip(tiny_data):
    solid = SceneDataset(tiny_data, DatasetConfig())[0]
    cfg = DatasetConfig(occupancy_labels="surface")
    surf = SceneDataset(tiny_data, cfg)[0]
    occ, lab = solid["occupancy"].numpy(), surf["occupancy"].numpy()
    assert set(np.unique(lab)) == {0, 1, OCC_UNKNOWN}
    assert np.array_equal(lab == 0, occ == 0)           # only occupied voxels are relabelled
    assert 0 < (lab == 1).sum() < 0.5 * occ.sum()
    assert torch.equal(surf["bev"], solid["bev"])       # the BEV obstacle map is unchanged
    # the flipped item's labels are the flipped labels ...
    flip = SceneDataset(tiny_data, cfg.replace(flip_prob=1.0))[0]
    assert flip["flipped"] and torch.equal(flip["occupancy"], surf["occupancy"].flip(1))
    # ... and what the mirrored cameras see in the flipped depths (the mirror maps voxels onto voxels)
    again = surface_labels(occ[:, ::-1] > 0, (-40.0, -40.0, -3.0, 40.0, 40.0, 13.0), 0.8,
                           list(flip["rig"].cameras), flip["depth"][:, 0].numpy(),
                           (flip["depth_valid"] & (flip["sky"] < 0.5))[:, 0].numpy())
    assert (again == flip["occupancy"].numpy()).mean() > 0.9999


def test_surface_ego_labels_mark_the_hidden_ego_car(tiny_data):
    from xyzcyl.model_export.data.classes import EGO
    surf = SceneDataset(tiny_data, DatasetConfig(occupancy_labels="surface"))
    ego = SceneDataset(tiny_data, DatasetConfig(occupancy_labels="surface+ego"))
    sem = np.load(surf.scenes[0] / "occupancy.npz")["semantic_0p8"].transpose(2, 1, 0)   # [L_z, L_y, L_x]
    car = sem == EGO
    assert car.sum() >= 10                               # the generator's ego car spans many 0.8 m voxels
    a, b = surf[0]["occupancy"].numpy(), ego[0]["occupancy"].numpy()
    assert (a[car] != 1).mean() > 0.9                   # no input camera sees the ego car: (nearly) all hidden
    assert (b[car] == 1).all()                           # surface+ego: every ego voxel occupied
    assert np.array_equal(a[~car], b[~car])              # nothing else changes


def test_surface_config_validation():
    with pytest.raises(ConfigError, match="occupancy_labels"):
        DatasetConfig(occupancy_labels="visible")
    for bad in (-1, 1.5, True):
        with pytest.raises(ConfigError, match="surface_dilation"):
            DatasetConfig(surface_dilation=bad)
    assert DatasetConfig(occupancy_labels="surface", surface_dilation=2).surface_dilation == 2


# --------------------------------------------------------------------------------------- camera augmentation

STRONG = {"camera_exposure": 0.5, "camera_white_balance": 0.3, "vignetting": 1.0, "blur": 1.0, "jpeg": 1.0,
          "noise": 0.05}


def _base(**kw):
    return DatasetConfig(setting="both", num_targets=3, brightness=0.2, contrast=0.2, saturation=0.2, flip_prob=0.5,
                         **kw)


def test_each_camera_aug_changes_inputs_only(tiny_data):
    ds0 = SceneDataset(tiny_data, _base())
    for index in (0, 1):
        off = ds0[index]
        for field, value in STRONG.items():
            on = SceneDataset(tiny_data, _base(**{field: value}))[index]
            x = on["images"]
            assert not torch.equal(x, off["images"]), field
            assert 0 <= float(x.min()) and float(x.max()) <= 1 and x.dtype == torch.float32, field
            # targets (colour-jittered as before), flip, geometry: untouched, the rng stream included
            assert on["flipped"] == off["flipped"] and on["targets"]["names"] == off["targets"]["names"], field
            for a, b in ((on["targets"]["images"], off["targets"]["images"]), (on["depth"], off["depth"]),
                         (on["sky"], off["sky"]), (on["occupancy"], off["occupancy"])):
                assert torch.equal(a, b), field


def test_camera_aug_is_reproducible_and_per_camera(tiny_data):
    cfg = _base(**STRONG)
    ds = SceneDataset(tiny_data, cfg)
    a, b = ds.item(1, 3), SceneDataset(tiny_data, cfg).item(1, 3)
    assert torch.equal(a["images"], b["images"])
    assert not torch.equal(ds.item(1, 4)["images"], a["images"])
    # exposure alone: each camera gets its own gain (ratio to the un-augmented input differs per camera)
    off = SceneDataset(tiny_data, DatasetConfig())[0]["images"]
    exp = SceneDataset(tiny_data, DatasetConfig(camera_exposure=0.5))[0]["images"]
    m = (off > 0.05) & (off < 0.6)                     # no clipping at 1.5 x
    ratios = [float((exp[k][m[k]] / off[k][m[k]]).median()) for k in range(len(off))]
    assert len({round(r, 3) for r in ratios}) == len(ratios)
    assert all(0.5 - 1e-3 <= r <= 1.5 + 1e-3 for r in ratios)


def test_camera_aug_off_is_the_raw_input(tiny_data):
    from xyzcyl.runtime.rig import load_rig

    it = SceneDataset(tiny_data, DatasetConfig(**{k: 0.0 for k in CAMERA_AUG_PRESET}))[0]
    raw = np.stack(load_rig(tiny_data / "scene_000000" / "rig.json").load_images())
    assert np.array_equal(it["images"].numpy(), raw.transpose(0, 3, 1, 2))
    assert not DatasetConfig().camera_aug and DatasetConfig(noise=0.01).camera_aug


def test_apply_camera_aug_operations():
    img = np.full((30, 40, 3), 0.5, np.float32)
    v = apply_camera_aug(img, CameraAug(vignetting=0.4))
    assert v[15, 20, 0] == pytest.approx(0.5, abs=2e-3) and v[0, 0, 0] == pytest.approx(0.5 * 0.6, abs=1e-6)
    g = apply_camera_aug(img, CameraAug(gain=(1.2, 1.0, 0.8)))
    np.testing.assert_allclose(g[0, 0], [0.6, 0.5, 0.4], atol=1e-6)
    rng = np.random.default_rng(0)
    tex = rng.random((30, 40, 3)).astype(np.float32)
    b = apply_camera_aug(tex, CameraAug(blur_sigma=1.2))
    assert b.std() < 0.7 * tex.std()
    n = apply_camera_aug(img, CameraAug(noise_sigma=0.05), np.random.default_rng(1))
    assert 0.04 < float((n - img).std()) < 0.06
    j = apply_camera_aug(tex, CameraAug(jpeg_quality=40))
    assert 0.01 < float(np.abs(j - tex).mean()) and (j * 255 == np.round(j * 255)).all()   # 8-bit decode
    s = apply_camera_aug(img, CameraAug(gain=(3.0, 3.0, 3.0), noise_sigma=0.5), np.random.default_rng(2))
    assert s.min() >= 0 and s.max() <= 1 and s.dtype == np.float32
    assert np.array_equal(apply_camera_aug(tex, CameraAug()), tex)


def test_camera_aug_config_and_preset():
    for field in CAMERA_AUG_PRESET:
        for bad in (-0.1, 1.5, True):
            with pytest.raises(ConfigError, match=field):
                DatasetConfig(**{field: bad})
    with pytest.raises(ConfigError, match="camera_exposure"):
        DatasetConfig(camera_exposure=1.0)             # a gain of 0
    assert DatasetConfig(blur=1.0, jpeg=1.0, vignetting=1.0, noise=1.0).camera_aug
    assert camera_aug_fields(0.0) == {k: 0.0 for k in CAMERA_AUG_PRESET}
    full = camera_aug_fields(1.0)
    assert full == CAMERA_AUG_PRESET and DatasetConfig(**full).camera_aug
    assert camera_aug_fields(0.5)["jpeg"] == pytest.approx(0.25)
    with pytest.raises(ConfigError, match="camera_aug"):
        camera_aug_fields(1.5)
    plain = DatasetConfig(flip_prob=0.5, brightness=0.1, num_targets=2, **full).without_augmentation()
    assert plain == DatasetConfig(num_targets=2)


def test_train_cli_camera_aug(tiny_data, tmp_path, capsys):
    import argparse

    from xyzcyl.model_export.commands import train as cmd

    parser = argparse.ArgumentParser()
    cmd.add_arguments(parser)
    args = parser.parse_args(["--data", str(tiny_data), "--stage", "occ", "--out", str(tmp_path / "r"),
                              "--camera-aug", "1.5"])
    assert cmd.run(args) == 2 and "camera_aug" in capsys.readouterr().err
    assert parser.parse_args(["--data", "d", "--stage", "occ", "--out", "o"]).camera_aug == 0.0


# ---------------------------------------------------------------------------------------------- camera drop


def _ring(yaws_deg):
    """Cameras at the origin looking along the given azimuths (deg, ego frame), in the given (rig) order."""
    cams = []
    for k, yaw in enumerate(yaws_deg):
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        pose = np.eye(4)
        pose[:3, :3] = np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])   # columns: cam x, y, z in ego
        cams.append(Camera(name=f"c{k}", width=8, height=6, K=np.array([[4.0, 0, 3.5], [0, 4.0, 2.5], [0, 0, 1]]),
                           cam_to_ego=pose))
    return cams


def test_camera_azimuth_of_a_known_ring():
    from xyzcyl.model_export.dataset import camera_azimuth

    yaws = [0, 55, 110, 180, -110, -55]
    assert [round(np.degrees(camera_azimuth(c))) for c in _ring(yaws)] == yaws
    # the nuScenes-like rig of the generator: CAM_FRONT looks forward, CAM_FRONT_LEFT to the left (+y)
    assert camera_azimuth(_ring([90])[0]) == pytest.approx(np.pi / 2)


def test_draw_camera_drop_removes_an_adjacent_sector():
    from xyzcyl.model_export.dataset import draw_camera_drop

    yaws = [0, -55, -110, 180, 110, 55]              # rig order is not azimuth order (clockwise here)
    cams = _ring(yaws)
    assert draw_camera_drop(cams, np.random.default_rng(0), 0.0, 2) == list(range(6))
    sizes = set()
    for seed in range(200):
        keep = draw_camera_drop(cams, np.random.default_rng(seed), 1.0, 2)
        dropped = sorted(set(range(6)) - set(keep))
        sizes.add(len(dropped))
        assert keep == sorted(keep) and 1 <= len(dropped) <= 2
        if len(dropped) == 2:                          # the two are neighbours on the ring (55 deg apart)
            a, b = (yaws[i] for i in dropped)
            assert abs((a - b + 180) % 360 - 180) in (55, 70)   # 70: the 180 / 110 (or -110) pair
    assert sizes == {1, 2}
    # at least 3 cameras stay: a 4-camera rig loses at most 1, a 3-camera rig none
    assert all(len(draw_camera_drop(_ring([0, 90, 180, 270]), np.random.default_rng(s), 1.0, 3)) == 3
               for s in range(20))
    assert draw_camera_drop(_ring([0, 120, 240]), np.random.default_rng(0), 1.0, 2) == [0, 1, 2]


def test_camera_drop_in_items_keeps_targets_and_pairs_images_with_cameras(tiny_data):
    base = DatasetConfig(setting="both", num_targets=3, flip_prob=0.0)
    off = SceneDataset(tiny_data, base)
    on = SceneDataset(tiny_data, base.replace(camera_drop=1.0))
    names = [c.name for c in off[0]["rig"].cameras]
    for index in (0, 1):
        a, b = off.item(index, 2), on.item(index, 2)
        kept = [c.name for c in b["rig"].cameras]
        assert 4 <= len(kept) <= 5 and len(b["images"]) == len(b["depth"]) == len(b["sky"]) == len(kept)
        idx = [names.index(n) for n in kept]
        for key in ("images", "depth", "depth_valid", "sky"):   # each kept camera keeps its own arrays
            assert torch.equal(b[key], a[key][idx]), key
        assert b["targets"]["names"] == a["targets"]["names"]
        assert torch.equal(b["targets"]["images"], a["targets"]["images"])
    # reproducible per (seed, epoch, index), and validation turns it off
    assert [c.name for c in on.item(1, 2)["rig"].cameras] == [c.name for c in on.item(1, 2)["rig"].cameras]
    assert base.replace(camera_drop=1.0).without_augmentation().camera_drop == 0.0
    # with the flip, the dropped rig is mirrored like a whole one (images flipped, cameras mirrored)
    both = SceneDataset(tiny_data, base.replace(camera_drop=1.0, flip_prob=1.0)).item(0, 2)
    assert both["flipped"] and len(both["rig"].cameras) == len(both["images"]) < len(names)


def test_camera_drop_config_validation():
    for bad in (-0.1, 1.5, True, "0.5"):
        with pytest.raises(ConfigError, match="camera_drop"):
            DatasetConfig(camera_drop=bad)
    for bad in (0, 1.5, True):
        with pytest.raises(ConfigError, match="camera_drop_max"):
            DatasetConfig(camera_drop_max=bad)


def test_several_data_folders_are_one_set(tiny_data, tmp_path):
    import shutil

    from xyzcyl.model_export.dataset import DataError

    one = SceneDataset(tiny_data, DatasetConfig())
    two = SceneDataset([tiny_data, tiny_data], DatasetConfig())
    assert len(two) == 2 * len(one) and two.scenes == one.scenes + one.scenes
    # index 2 is the second folder's first scene: the same files (no augmentation here, so the same inputs)
    assert two.item(2, 0)["scene"] == one.item(0, 0)["scene"]
    assert torch.equal(two.item(2, 0)["images"], one.item(0, 0)["images"])
    # a second folder without the needed grid fails at construction, naming its own file
    bad = tmp_path / "bad"
    shutil.copytree(tiny_data / "scene_000000", bad / "scene_000000")
    z = dict(np.load(bad / "scene_000000" / "occupancy.npz"))
    np.savez(bad / "scene_000000" / "occupancy.npz", **{k: v for k, v in z.items() if k != "semantic_1p6"})
    with pytest.raises(DataError, match=r"bad/scene_000000/occupancy.npz: voxel_size"):
        SceneDataset([tiny_data, bad], DatasetConfig(voxel_size=1.6))
    with pytest.raises(DataError, match="no data set folder"):
        SceneDataset([], DatasetConfig())


# ------------------------------------------------------------------------------------------ lens zoom


def test_zoom_camera_maps_pixels_like_the_resampling():
    from xyzcyl.model_export.dataset import zoom_camera

    cam = Camera(name="c", width=64, height=32, K=np.array([[40.0, 0, 31.5], [0, 38.0, 15.2], [0, 0, 1]]), cam_to_ego=CAM_FORWARD)
    z, x0, y0 = 1.3, 7.25, 3.5
    new, inv = zoom_camera(cam, z, x0, y0)
    assert new.width == cam.width and new.height == cam.height
    np.testing.assert_array_equal(new.cam_to_ego, cam.cam_to_ego)
    # any ego point: its pixel in the new camera, mapped through the resampling's inverse map, is its old pixel
    pts = np.array([[10.0, 1.0, 0.3], [6.0, -0.8, -0.5], [25.0, 2.0, 1.0]])
    uv_old, _, _ = cam.project(pts)
    uv_new, _, _ = new.project(pts)
    back = np.c_[uv_new, np.ones(len(pts))] @ inv.T
    # float64 pinhole projection both ways: rounding only
    np.testing.assert_allclose(back, uv_old, atol=1e-9)
    # the window's left edge (pixel-edge x0) lands on the new image's left edge (pixel-edge 0, centre -1/2)
    np.testing.assert_allclose(inv @ [-0.5, -0.5, 1.0], [x0 - 0.5, y0 - 0.5], atol=1e-12)


def test_lens_zoom_in_items_keeps_geometry_and_targets(tiny_data):
    from xyzcyl.model_export import metrics as M

    base = DatasetConfig(setting="both", num_targets=3, flip_prob=0.0, max_depth=1e12)
    off = SceneDataset(tiny_data, base)
    on = SceneDataset(tiny_data, base.replace(lens_zoom=1.0))
    a, b = off.item(0, 1), on.item(0, 1)
    ca, cb = a["rig"].cameras, b["rig"].cameras
    assert [c.name for c in ca] == [c.name for c in cb]
    f_ratio = [c2.K[0, 0] / c1.K[0, 0] for c1, c2 in zip(ca, cb)]
    assert all(1.0 < r <= 1.4 for r in f_ratio) and len(set(np.round(f_ratio, 6))) == len(f_ratio)  # per camera
    for c1, c2 in zip(ca, cb):
        np.testing.assert_array_equal(c1.cam_to_ego, c2.cam_to_ego)
        np.testing.assert_allclose(c2.K[1, 1] / c1.K[1, 1], c2.K[0, 0] / c1.K[0, 0], rtol=1e-12)
    assert not torch.equal(a["images"], b["images"])
    assert b["targets"]["names"] == a["targets"]["names"]
    assert torch.equal(b["targets"]["images"], a["targets"]["images"])
    # each zoomed view's surface is its own camera's: back-projected with the new K, the zoomed depth lands on
    # the surface the original camera saw (seen_by_inputs against the original view alone). Nearest resampling
    # can pick the other side of a depth edge for pixels on it, so a few may miss.
    for k in range(len(ca)):
        d = b["depth"][k, 0].numpy()
        seen = M.seen_by_inputs(d, cb[k].K, cb[k].cam_to_ego, a["depth"][k:k + 1, 0].numpy(), [ca[k]])
        has = d > 0
        assert has.sum() > 0.3 * d.size and seen[has].mean() > 0.97, (k, seen[has].mean())
        # the sky follows the pixels: where the zoomed view has sky it has no depth
        assert not (b["sky"][k, 0].numpy() > 0.5)[has].any()
    # reproducible, off in validation, and the probability applies per camera
    assert torch.equal(on.item(0, 1)["images"], b["images"])
    assert base.replace(lens_zoom=1.0).without_augmentation().lens_zoom == 0.0
    assert torch.equal(SceneDataset(tiny_data, base.replace(lens_zoom=0.0)).item(0, 1)["images"], a["images"])


def test_lens_zoom_config_validation():
    for bad in (-0.1, 1.5, True, "0.5"):
        with pytest.raises(ConfigError, match="lens_zoom"):
            DatasetConfig(lens_zoom=bad)
    for bad in (0.9, 5, True):
        with pytest.raises(ConfigError, match="lens_zoom_max"):
            DatasetConfig(lens_zoom_max=bad)


# ------------------------------------------------------------------------------------------ simulated LiDAR input

def test_simulate_lidar_by_hand():
    """Points only at valid, non-sky cells of 1-80 m below the top-beam row, each the nearest-sampled true depth;
    probability 0 gives none; a seed gives the same sweep."""
    from xyzcyl.runtime.inference import resize_nearest

    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 100.0, (3, 64, 128)).astype(np.float32)
    depth[:, :5] = 0
    sky = np.zeros((3, 64, 128), bool)
    sky[:, :20] = True
    lid, surf = simulate_lidar(depth, sky, (8, 16), np.random.default_rng(1), 1.0)
    assert lid.shape == surf.shape == (3, 8, 16) and lid.dtype == np.float32
    for k in range(3):
        d = resize_nearest(depth[k], 8, 16)
        has = lid[k] > 0
        np.testing.assert_array_equal(lid[k][has], d[has])
        assert has.any() and not has[:2].any()            # the top beam sits at >= 0.25 h: rows 0-1 stay empty
        assert np.all((lid[k][has] >= 1) & (lid[k][has] <= 80)) and surf[k][has].all()
        assert not surf[k][:2].any() and surf[k][3:].all()   # sky rows 0..19 of 64 -> rows 0..2 of 8
    again = simulate_lidar(depth, sky, (8, 16), np.random.default_rng(1), 1.0)
    assert np.array_equal(again[0], lid)
    assert simulate_lidar(depth, sky, (8, 16), np.random.default_rng(1), 0.0) is None


def test_lidar_input_in_items(tiny_data):
    from xyzcyl.testing.model import synth_test_config

    cfg = synth_test_config()
    h, w = cfg.backbone.input_height // cfg.backbone.feature_stride, cfg.backbone.input_width // cfg.backbone.feature_stride
    base = DatasetConfig(setting="both", num_targets=2, voxel_size=1.6, flip_prob=0.0)
    on = SceneDataset(tiny_data, base.replace(lidar_input=1.0), model_cfg=cfg).item(0, 1)
    off = SceneDataset(tiny_data, base, model_cfg=cfg).item(0, 1)
    n = on["images"].shape[0]
    assert on["lidar_depth"].shape == on["lidar_surface"].shape == (n, h, w) and (on["lidar_depth"] > 0).any()
    assert "lidar_depth" not in off and torch.equal(on["images"], off["images"])      # its own child stream
    assert torch.equal(on["targets"]["images"], off["targets"]["images"])
    assert base.replace(lidar_input=1.0).without_augmentation().lidar_input == 0.0
    with pytest.raises(ConfigError, match="lidar_input"):
        SceneDataset(tiny_data, base.replace(lidar_input=0.5))          # no model config: no depth size
    for bad in (-0.1, 1.5, True, "0.5"):
        with pytest.raises(ConfigError, match="lidar_input"):
            DatasetConfig(lidar_input=bad)
