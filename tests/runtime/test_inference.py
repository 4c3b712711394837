"""runtime.inference.Reconstructor: model-folder checks, input checks, resizing, the lifting cache, threads."""

from __future__ import annotations

import dataclasses
import json
import shutil
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from xyzcyl.runtime import inference
from xyzcyl.runtime.inference import (
    ModelError,
    Reconstructor,
    calibration_key,
    read_model_info,
    resize_area,
    resize_nearest,
    verify_model,
)
from xyzcyl.runtime.lifting import LiftingParams
from xyzcyl.runtime.numba_cache import threadsafe
from xyzcyl.runtime.rig import RigError
from xyzcyl.testing.model import overlap_rig

pytestmark = pytest.mark.slow   # the session's ONNX export (tests/conftest.py)


@pytest.fixture(scope="module")
def rec(tiny_export):
    return Reconstructor.load(tiny_export.dir, threads=1)


def _images(rig, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random((c.height, c.width, 3), dtype=np.float32) for c in rig.cameras]


def test_model_json_describes_the_folder(tiny_export):
    info = verify_model(tiny_export.dir)
    m = info.meta
    assert m["opset"] == 20 and m["name"] == "tiny-test" and m["version"] == "0.0.1"
    assert set(m["graphs"]) == {"encode", "encode_image", "encode_depth", "volume", "background"}
    assert set(m["files"]) == {"encode.onnx", "encode_image.onnx", "encode_depth.onnx", "volume.onnx",
                               "background.onnx", "MODEL_CARD.md"}
    enc = {i["name"]: i["shape"] for i in m["graphs"]["encode"]["inputs"]}
    assert enc["images"] == ["N", 3, 64, 128] and enc["grid_occ"][0] == "N" and enc["depth_mask"] == ["N"]
    vol = {i["name"]: i["shape"] for i in m["graphs"]["volume"]["inputs"]}
    assert vol["voxel_idx"] == ["M"]
    lp = LiftingParams.from_config_dict(tiny_export.model.cfg.to_dict())
    assert m["lifting"] == json.loads(json.dumps(dataclasses.asdict(lp))) and info.lifting == lp
    assert m["config"] == tiny_export.model.cfg.to_dict()
    assert m["checkpoint"]["step"] == 0 and m["checkpoint"]["train"]["stage"] == "render"
    card = (tiny_export.dir / "MODEL_CARD.md").read_text()
    assert "tiny-test 0.0.1" in card and "Apache-2.0" in card


@pytest.mark.parametrize("damage", ["alter", "remove"])
@pytest.mark.parametrize("name", ["volume.onnx", "MODEL_CARD.md"])
def test_missing_or_altered_model_file_is_named(tiny_export, tmp_path, damage, name):
    d = tmp_path / "m"
    shutil.copytree(tiny_export.dir, d)
    if damage == "alter":
        data = bytearray((d / name).read_bytes())
        data[len(data) // 2] ^= 0x01
        (d / name).write_bytes(bytes(data))
    else:
        (d / name).unlink()
    with pytest.raises(ModelError, match=name.replace(".", r"\.")) as e:
        Reconstructor.load(d)
    assert ("altered" if damage == "alter" else "missing") in str(e.value)


def test_not_a_model_folder(tmp_path):
    with pytest.raises(ModelError, match="model.json"):
        read_model_info(tmp_path)
    with pytest.raises(ModelError, match="not a folder"):
        read_model_info(tmp_path / "nope")


def test_lifting_cache_per_calibration(tiny_export):
    rec = Reconstructor.load(tiny_export.dir, threads=1, cache_size=2)
    rig5, rig6, rig8 = overlap_rig(5), overlap_rig(6), overlap_rig(8)
    a = rec.reconstruct(rig6, _images(rig6), detail=None)
    b = rec.reconstruct(overlap_rig(6), _images(rig6), detail=None)     # the same calibration in another Rig object
    assert not a.lifting_cached and b.lifting_cached
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    assert not rec.reconstruct(rig5, _images(rig5), detail=None).lifting_cached
    assert not rec.reconstruct(overlap_rig(6, ring_radius=0.6), _images(rig6), detail=None).lifting_cached   # moved cameras
    rec.reconstruct(rig8, _images(rig8), detail=None)
    assert len(rec._cache) == 2 and calibration_key(rig6) not in rec._cache   # least recently used dropped


def test_counts_and_metadata(rec):
    rig = overlap_rig(6)
    s = rec.reconstruct(rig, _images(rig), detail=None)
    c = s.counts
    assert c["volume"] == 2 * c["voxels"] and c["pixel"] == 16 * 128   # G_v = 2; G_p = 1 on the k = 2 lattice of 8 x 64
    assert c["total"] == len(s.gaussians) == c["volume"] + c["pixel"] - c["pruned"]
    assert s.model["name"] == "tiny-test" and s.model["version"] == "0.0.1"
    for k in ("decode", "resize", "lifting", "encode", "select", "volume", "gaussians", "background", "total"):
        assert s.timings[k] >= 0
    assert s.background is not None and s.background.image.shape[1] == 4 * 64
    # the default adds the detail layer (runtime.detail): its counts partition the scene's Gaussians
    ds = rec.reconstruct(rig, _images(rig))
    d = ds.counts
    # the cells the fusion drops stay in the scene, hidden, for their camera's own view (runtime.detail.OwnViews)
    assert d["total"] == len(ds.gaussians) == d["coarse"] + d["detail"] + d["carved"] + 3 * d["split"]
    assert d["coarse"] + d["culled"] == c["total"] and len(ds.own_views.index) == d["carved"]
    assert d["detail"] + d["carved"] == sum(d[f"detail_{k}"] for k in ("lidar", "ground", "model", "far")) > 0


def test_resizes_any_image_size_with_inter_area(rec):
    """A rig at 2x the model's input: its images are area-resized, its calibration is used as is (the lifting grids
    are normalised image coordinates, the same at any resolution)."""
    big = overlap_rig(6, width=256, height=128)
    imgs = _images(big, seed=3)
    a = rec.reconstruct(big, imgs, detail=None)
    small = overlap_rig(6)
    b = rec.reconstruct(small, [resize_area(i, 64, 128) for i in imgs], detail=None)
    np.testing.assert_allclose(a.gaussians.means, b.gaussians.means, atol=1e-4)
    uint8 = rec.reconstruct(big, [np.round(i * 255).astype(np.uint8) for i in imgs], detail=None)
    assert len(uint8.gaussians) > 0


def test_depth_resize_is_torchs_nearest():
    import torch
    import torch.nn.functional as F

    d = np.random.default_rng(0).random((450, 800)).astype(np.float32)
    for h, w in ((28, 50), (8, 16), (56, 100), (900, 1600)):
        ref = F.interpolate(torch.from_numpy(d)[None, None], size=(h, w), mode="nearest")[0, 0].numpy()
        np.testing.assert_array_equal(resize_nearest(d, h, w), ref)


@pytest.mark.parametrize("case", ["size", "nan_image", "nan_depth", "neg_depth", "depth_size", "count"])
def test_bad_input_names_the_camera(rec, case):
    rig = overlap_rig(5)
    imgs = _images(rig)
    depths = None
    if case == "size":
        imgs[2] = imgs[2][:, :100]
    elif case == "nan_image":
        imgs[2][3, 4, 1] = np.nan
    elif case == "count":
        imgs = imgs[:4]
    else:
        depths = [None] * 5
        depths[2] = np.full((64, 128), 5.0, np.float32)
        if case == "nan_depth":
            depths[2][10, 10] = np.nan
        elif case == "neg_depth":
            depths[2][10, 10] = -1.0
        else:
            depths[2] = depths[2][:32]
    with pytest.raises(RigError) as e:
        rec.reconstruct(rig, imgs, depths, detail=None)
    assert ("'cam2'" in str(e.value)) if case != "count" else "rig" in str(e.value)


def test_concurrent_reconstructions_agree(rec):
    """Several threads on one Reconstructor (shared sessions, locked cache, the detail layer's numba kernels) give the
    sequential results."""
    rigs = [overlap_rig(5), overlap_rig(6), overlap_rig(8)]
    imgs = [_images(r, seed=i) for i, r in enumerate(rigs)]
    ref = [rec.reconstruct(r, i).gaussians.means for r, i in zip(rigs, imgs)]
    with ThreadPoolExecutor(4) as pool:
        futs = [pool.submit(rec.reconstruct, rigs[k % 3], imgs[k % 3]) for k in range(6)]
        got = [f.result().gaussians.means for f in futs]
    for k, g in enumerate(got):
        np.testing.assert_array_equal(g, ref[k % 3])


def test_lidar_becomes_the_depth_input(rec):
    """reconstruct(lidar=...): every camera without a depth map gets one from the sweep at the depth size (each
    cell with a point holds that point's camera z, the others the model's own depth rescaled), a camera with a
    supplied map keeps it, and the scene is rebuilt from the second encode pass."""
    from xyzcyl.runtime.inference import InferenceError
    from xyzcyl.runtime.lidar import lidar_depth_map

    rig = overlap_rig(6)
    imgs = _images(rig, seed=3)
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-1.0, 4.0, 40))
    wall = np.stack([15 * np.cos(az).ravel(), 15 * np.sin(az).ravel(), z.ravel()], axis=1)   # a 15 m round wall
    scene0 = rec.reconstruct(rig, imgs, depths=[None] * 6, detail=None)
    given = np.full((rig.cameras[2].height, rig.cameras[2].width), 9.0, np.float32)
    _, depth_g, mask_g = rec.prepare(rig, imgs, [None, None, given, None, None, None])
    d, m, scales = rec.lidar_depths(rig, scene0.gaussians, wall, depth_g, mask_g)
    assert m.tolist() == [1.0] * 6 and scales[2] is None and np.all(d[2] == 9.0)
    h, w = rec.info.depth_size
    for n in (0, 1, 3):
        lid = lidar_depth_map(wall, rig.cameras[n].replace(distortion=None).resized(w, h))
        has = lid > 0
        assert has.mean() > 0.3                       # the wall fills the view's lower and middle rows
        np.testing.assert_array_equal(d[n, 0][has], lid[has])
        assert scales[n] > 0
    scene = rec.reconstruct(rig, imgs, depths=[None] * 6, lidar=wall, detail=None)
    assert scene.counts["lidar_cameras"] == 6 and "encode_lidar" in scene.timings
    assert not np.array_equal(scene.gaussians.means, scene0.gaussians.means)
    assert not depth_g[0].any() and mask_g[0] == 0       # the caller's inputs were not changed in place
    with pytest.raises(InferenceError, match=r"lidar: need finite points of shape \[P, 3\]"):
        rec.reconstruct(rig, imgs, depths=[None] * 6, lidar=wall[:, :2], detail=None)
    bad = wall.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InferenceError, match="lidar"):
        rec.reconstruct(rig, imgs, depths=[None] * 6, lidar=bad, detail=None)


def _unsplit(src, dst):
    """A copy of model folder ``src`` at ``dst`` without the split encode graph (a folder exported before it)."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "model.json").read_text())
    for g in inference.ENCODE_SPLIT:
        name = meta["graphs"].pop(g)["file"]
        del meta["files"][name]
        (dst / name).unlink()
    (dst / "model.json").write_text(json.dumps(meta, indent=1))
    return dst


def test_the_split_encode_graph_reconstructs_as_the_whole_one(rec, tiny_export, tmp_path):
    """With encode_image + encode_depth in the folder the reconstructor holds no session of "encode" and runs the
    halves (the second pass with LiDAR only the depth half, given the first pass's image half): the same bits as a
    folder without them, which runs "encode" twice."""
    whole = Reconstructor.load(_unsplit(tiny_export.dir, tmp_path / "whole"), threads=1)
    assert "encode" in whole.sessions and not set(inference.ENCODE_SPLIT) & set(whole.sessions)
    assert "encode" not in rec.sessions and set(inference.ENCODE_SPLIT) <= set(rec.sessions)
    rig = overlap_rig(6)
    imgs = _images(rig, seed=5)
    az, z = np.meshgrid(np.linspace(-np.pi, np.pi, 720, endpoint=False), np.linspace(-1.0, 4.0, 40))
    wall = np.stack([12 * np.cos(az).ravel(), 12 * np.sin(az).ravel(), z.ravel()], axis=1)
    for lidar in (None, wall):
        a = rec.reconstruct(rig, imgs, lidar=lidar, detail=None)
        b = whole.reconstruct(rig, imgs, lidar=lidar, detail=None)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(a.gaussians, name), getattr(b.gaussians, name))
        np.testing.assert_array_equal(a.background.image, b.background.image)
    # the image half reused with another depth = both halves run again = the encode graph
    x, depth, mask = rec.prepare(rig, imgs)
    lift, _ = rec.lifting(rig)
    feed = {"images": x, "depth": depth, "depth_mask": mask, **lift}
    _, early = rec.encode(feed)
    d2 = {**feed, "depth": np.random.default_rng(1).uniform(2, 30, depth.shape).astype(np.float32),
          "depth_mask": np.ones_like(mask)}
    reused, again = rec.encode(d2, early)[0], rec.encode(d2)[0]
    ref, none = whole.encode(d2)
    assert none is None and set(reused) == set(ref) == {o["name"] for o in rec.info.meta["graphs"]["encode"]["outputs"]}
    for k in ref:
        np.testing.assert_array_equal(reused[k], ref[k])
        np.testing.assert_array_equal(again[k], ref[k])
    np.testing.assert_array_equal(rec._run("encode", d2)["pixel_means"], ref["pixel_means"])


def test_cameras_made_in_threads_give_the_one_thread_details(rec):
    """camera_details with two threads (reconstruct's default) gives each camera the Gaussians, cell maps and counts
    that one thread gives, in rig order; the fused scene is the same bit for bit."""
    if not threadsafe():
        pytest.skip("numba's threading layer here runs the cameras one at a time")
    rig = overlap_rig(6)
    imgs = _images(rig, seed=4)
    one = rec.keyframe(rig, imgs, detail=inference.DEFAULT_DETAIL, detail_threads=1)
    two = rec.keyframe(rig, imgs, detail=inference.DEFAULT_DETAIL, detail_threads=2)
    assert one.owners == two.owners == list(range(6))
    assert one.counts == two.counts
    for a, b, da, db in zip(one.parts, two.parts, one.details, two.details):
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(da.depth, db.depth)
        np.testing.assert_array_equal(da.keep, db.keep)
    s1 = rec.reconstruct(rig, imgs)
    was = inference.DETAIL_THREADS
    try:
        inference.DETAIL_THREADS = 1
        s0 = rec.reconstruct(rig, imgs)
    finally:
        inference.DETAIL_THREADS = was
    np.testing.assert_array_equal(s0.gaussians.means, s1.gaussians.means)
    np.testing.assert_array_equal(s0.gaussians.sh, s1.gaussians.sh)
