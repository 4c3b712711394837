"""runtime.detail (the detail layer: pixel-aligned Gaussians at each input camera's native resolution): the options'
validation; the grid camera and its colours; the LiDAR grid depth, the depth-edge rule and the two fusion passes
against their slow references; the edge-aware densification; the ground plane and the analytic far / ground
depths; the rotation -> quaternion; a flat textured wall rendered back from its cells; and one camera end to end
with a synthetic LiDAR (a near box in front of a wall): no flying pixels across the depth edge, the ego mask, and
the fusion with coarse Gaussians in front of, on and behind the detail surfaces."""

from __future__ import annotations

import dataclasses
import functools
import math
import re

import cv2
import numpy as np
import pytest
from xyzcyl.runtime.detail import (
    CameraDetail,
    DetailError,
    DetailOptions,
    camera_detail,
    carve_against,
    carve_against_reference,
    carve_details,
    carve_details_both,
    carve_details_reference,
    cell_gaussians,
    cell_gaussians_reference,
    concat_gaussians,
    concat_gaussians_reference,
    cull_covered,
    cull_covered_reference,
    densify,
    edge_keep,
    edge_keep_reference,
    edge_smoother,
    fit_ground,
    grid_camera,
    grid_colours,
    ground_depth,
    lidar_grid_depth,
    read_ego_mask,
    rotmat_to_quat,
    rotmats_to_quats,
    sphere_depth,
    support_mask,
)
from xyzcyl.runtime.lidar import lidar_depth_map_reference, occlusion_filter_reference
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.render.gaussians import SH_C0
from xyzcyl.runtime.rig import Camera, RigError, look_rotation, ring_rig
from xyzcyl.runtime.rotations import quat_to_rotmat
from xyzcyl.runtime.scene import rig_camera

LOW_PASS = 0.3   # px^2: the renderer's default 2D low-pass (RenderOptions.low_pass), added to every splat's variance


def _camera(width=96, height=64, f=60.0, pos=(1.0, 0.0, 1.5), yaw=0.0, pitch=0.0, name="front") -> Camera:
    T = np.eye(4)
    T[:3, :3] = look_rotation(yaw, pitch)
    T[:3, 3] = pos
    K = [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]
    return Camera(name=name, width=width, height=height, K=K, cam_to_ego=T)


def _discs(means, sigma, colour, opacity=0.99, thin=None) -> Gaussians:
    """Gaussians at ``means`` [N, 3]: isotropic (std ``sigma``) or, with ``thin``, flat along ego x; one colour."""
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = len(means)
    s = [thin, sigma, sigma] if thin is not None else [sigma] * 3
    return Gaussians(means, np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                     np.log(np.tile(s, (n, 1))).astype(np.float32),
                     np.full(n, math.log(opacity / (1 - opacity)), np.float32),
                     np.tile((np.asarray(colour, np.float32) - 0.5) / SH_C0, (n, 1, 1)).astype(np.float32))


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def _random_gaussians(rng, n: int, sh_degree: int) -> Gaussians:
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                     rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                     rng.normal(size=(n, (sh_degree + 1) ** 2, 3)).astype(np.float32))


def test_concat_gaussians_gives_its_references_bits():
    """concat_gaussians (a masked part's five fields copied in one parallel pass, straight into place) against its
    numpy definition: parts of SH degree 0 and 2 (the lower padded with zeros), masked and whole, an empty part, an
    all-False mask, a part whose fields are strided views (rows of a larger array: put_rows a field at a time)."""
    rng = np.random.default_rng(3)
    big = _random_gaussians(rng, 900, 0)
    strided = Gaussians.joined(**{f: getattr(big, f)[::3] for f in ("means", "quats", "log_scales",
                                                                  "opacity_logits", "sh")})
    parts = [_random_gaussians(rng, 500, 0), _random_gaussians(rng, 0, 0), _random_gaussians(rng, 300, 2),
             strided, _random_gaussians(rng, 40, 0)]
    masks = [rng.random(500) < 0.6, None, None, rng.random(300) < 0.5, np.zeros(40, bool)]
    for m in (masks, [masks[0], None, rng.random(300) < 0.7, None, None], None):
        got, want = concat_gaussians(parts, m), concat_gaussians_reference(parts, m)
        for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            a, b = getattr(got, f), getattr(want, f)
            assert a.dtype == b.dtype == np.float32 and a.shape == b.shape, f
            np.testing.assert_array_equal(a, b, err_msg=f)
    assert concat_gaussians(parts, m).sh.shape == (500 + 300 + 300 + 40, 9, 3)
    assert len(concat_gaussians([parts[1]])) == 0
    # whole parts put in a given order as they are joined (scatter_rows; the strided part a field at a time)
    to = rng.permutation(500 + 300 + 300 + 40)
    got, want = concat_gaussians(parts, to=to), concat_gaussians_reference(parts, to=to)
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f)
    np.testing.assert_array_equal(got.means[to[:500]], parts[0].means)
    for bad in (to[:-1], np.r_[to[:-1], to[0]], np.r_[to[:-1], len(to)]):     # short, a row twice, out of range
        with pytest.raises(ValueError, match="permutation"):
            concat_gaussians(parts, to=bad)
    with pytest.raises(ValueError, match="no masks"):
        concat_gaussians(parts, masks, to=to)


# -- options ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("field, value", [
    ("stride", 0), ("stride", 17), ("stride", 2.0), ("stride", True),
    ("model_depth", 1), ("ground", "yes"),
    ("footprint", 0.0), ("footprint", float("nan")), ("footprint", True), ("footprint", "1"),
    ("thickness", -0.1), ("smooth_lambda", 0), ("smooth_sigma", 0), ("support_deg", 0), ("occlusion_deg", -1),
    ("min_depth", 0), ("opacity", 0.0), ("opacity", 1.0), ("model_opacity", 1.5),
    ("edge_ratio", -0.01), ("cull_tolerance", -1), ("far_depth", -1), ("ground_max", -1), ("sharpen", -0.5),
    ("dedupe", -1), ("surface_stretch", -0.5), ("split", -0.01), ("split", float("nan")), ("max_depth", float("inf")), ("max_depth", 1.0), ("far_depth", 150.0), ("far_depth", 100.0),
])
def test_options_reject_bad_fields(field, value):
    with pytest.raises(DetailError, match=re.escape(f"detail.{field}:")):
        DetailOptions(**{field: value})


def test_options_defaults_and_edge_values_construct():
    o = DetailOptions()
    assert o.far_depth > o.max_depth > o.min_depth > 0 and 1 <= o.stride <= 16
    # the documented edge values: far_depth 0 (no far layer), stride 1 and 16, zero tolerances
    DetailOptions(far_depth=0.0, stride=1, edge_ratio=0.0, cull_tolerance=0.0, dedupe=0.0, sharpen=0.0)
    DetailOptions(stride=16, min_depth=0.5, max_depth=0.6, far_depth=0.7)


# -- grid camera and colours --------------------------------------------------------------------------------------

def test_grid_camera_stride_one_is_the_identity():
    cam = _camera().replace(distortion=(0.1, 0.01, 0.0, 0.0))
    grid = grid_camera(cam, 1)
    assert (grid.width, grid.height) == (cam.width, cam.height) and grid.distortion == cam.distortion  # lens kept
    np.testing.assert_array_equal(grid.K, cam.K)                 # resized to its own size: K unchanged, exactly
    np.testing.assert_array_equal(grid.cam_to_ego, cam.cam_to_ego)
    img = np.random.default_rng(0).random((cam.height, cam.width, 3)).astype(np.float32)
    np.testing.assert_array_equal(grid_colours(img, grid), img)


def test_grid_camera_stride_two_cells_are_the_block_centres_and_means():
    cam = _camera(width=96, height=64)
    grid = grid_camera(cam, 2)
    assert (grid.width, grid.height) == (48, 32)
    # a point seen at full-res (2i + 0.5, 2j + 0.5) -- the centre of block (i, j) -- projects to cell (i, j)
    rng = np.random.default_rng(1)
    i, j = rng.integers(0, 48, 20), rng.integers(0, 32, 20)
    uv_full = np.stack([2 * i + 0.5, 2 * j + 0.5], axis=-1)
    o, d = cam.pixel_rays(uv_full)
    uv, _, _ = grid.project(o + 7.0 * d)
    np.testing.assert_allclose(uv, np.stack([i, j], axis=-1), atol=1e-9)   # float64 round trip
    img = rng.random((64, 96, 3)).astype(np.float32)
    want = img.reshape(32, 2, 48, 2, 3).mean(axis=(1, 3))
    # float32 mean of four values: a few ulps apart from the float64-free reshape mean
    np.testing.assert_allclose(grid_colours(img, grid), want, atol=1e-6)
    # odd sizes round (W / s): 95 x 63 -> 48 x 32 (Python rounds half to even: 47.5 -> 48, 31.5 -> 32)
    odd = grid_camera(_camera(width=95, height=63), 2)
    assert (odd.width, odd.height) == (48, 32)


def test_grid_colours_sharpen_keeps_a_flat_image_and_raises_contrast():
    grid = grid_camera(_camera(width=64, height=48), 2)
    flat = np.full((48, 64, 3), [0.2, 0.5, 0.7], np.float32)
    # the unsharp mask adds sharpen (c - blur(c)); blur of a constant is that constant (reflected border): no change
    np.testing.assert_allclose(grid_colours(flat, grid, sharpen=1.0, footprint=0.7), flat[:24, :32], atol=1e-6)
    step = np.zeros((48, 64, 3), np.float32)
    step[:, 32:] = 0.6
    step += 0.2
    plain, sharp = grid_colours(step, grid), grid_colours(step, grid, sharpen=1.0, footprint=0.7)
    # beside the edge (cells 15 | 16) the dark side gets darker and the bright side brighter; far away no change
    assert sharp[10, 15, 0] < plain[10, 15, 0] - 0.05 and sharp[10, 16, 0] > plain[10, 16, 0] + 0.05
    np.testing.assert_allclose(sharp[:, :8], plain[:, :8], atol=1e-6)


# -- LiDAR depth and edges against the references -----------------------------------------------------------------

@pytest.mark.parametrize("occlusion_deg", [0.4, 3.0])
def test_lidar_grid_depth_matches_reference(occlusion_deg):
    cam = ring_rig(6, width=96, height=54).cameras[1]
    grid = grid_camera(cam, 2)
    rng = np.random.default_rng(2)
    # a near block (~5 m) in front of a far one (~25 m) in the camera's view, plus too-near / too-far returns
    n = 2500
    uv = rng.uniform([-2, -2], [grid.width + 1, grid.height + 1], (n, 2))
    near = (uv[:, 0] > 15) & (uv[:, 0] < 30) & (uv[:, 1] > 8) & (uv[:, 1] < 20)
    z = np.where(near, rng.uniform(4.5, 5.5, n), rng.uniform(20, 30, n))
    z[:40] = rng.uniform(0.2, 0.9, 40)
    z[40:80] = rng.uniform(160, 200, 40)
    o, d = grid.pixel_rays(uv)
    cos = d @ grid.rotation[:, 2]
    pts = o + (z / cos)[:, None] * d
    got = lidar_grid_depth(pts, grid, occlusion_deg, 1.0, 150.0)
    # the radius rule of the docstring: r = the angle in cells at the image centre (mean focal), at least 1
    r = max(1, round(0.5 * (grid.K[0, 0] + grid.K[1, 1]) * math.tan(math.radians(occlusion_deg))))
    ref = lidar_depth_map_reference(pts, grid, 1.0, 150.0)
    want = np.where(occlusion_filter_reference(ref, radius=r), ref, 0).astype(np.float32)
    np.testing.assert_array_equal(got, want)       # same projection, same float32 values: no tolerance
    dropped = (ref > 0) & (want == 0)
    assert got.dtype == np.float32 and (got > 0).sum() > 300 and dropped.sum() > 0   # the filter did something
    assert r == (1 if occlusion_deg < 1 else 2)


def test_edge_keep_matches_reference_and_by_hand():
    rng = np.random.default_rng(3)
    for ratio in (0.0, 0.1, 0.5):
        d = rng.lognormal(2.0, 0.6, (37, 41)).astype(np.float32)
        d[rng.random(d.shape) < 0.3] = 0
        d[0, :5] = 0                       # an all-empty corner window
        np.testing.assert_array_equal(edge_keep(d, ratio), edge_keep_reference(d, ratio))
    d = np.array([[5.0, 20.0, 0.0], [5.4, 10.0, 0.0]], np.float32)
    # 10 lies between the sides of the 5 | 20 jump (> 1.1 x 5 and < 20 / 1.1): a flying cell, dropped; 20 is the
    # far side (nothing in its window is farther), 5 and 5.4 the near side: kept; empty cells never kept
    assert edge_keep(d, 0.1).tolist() == [[True, True, False], [True, False, False]]
    ramp = np.array([[5.0, 8.75, 12.5, 16.25, 20.0, 20.0]], np.float32)
    # a smoothed jump: every cell between the two sides goes, both ends stay
    assert edge_keep(ramp, 0.1).tolist() == [[True, False, False, False, True, True]]


def _random_details(seed: int, n_cams: int = 4, size=(48, 27), colours: bool = False) -> list[CameraDetail]:
    """Detail layers of ring-rig cameras looking at one shared surface (a sphere of 12 m about the ego) with
    per-cell depth jitter in [0.75, 1.3]x and random keep / confidence: same-surface, in-front and behind cases all
    occur between overlapping cameras. ``colours``: each camera's image random, from four grey levels (so that
    a cell's colour is seen near its spot in another camera's image about half the time)."""
    rng = np.random.default_rng(seed)
    rig = ring_rig(n_cams, hfov_deg=110.0, width=size[0] * 2, height=size[1] * 2)
    out = []
    for cam in rig.cameras:
        grid = grid_camera(cam, 2)
        base = sphere_depth(grid, 12.0)
        jitter = np.where(rng.random(base.shape) < 0.5, 1.0, rng.uniform(0.75, 1.3, base.shape))
        depth = (base * jitter).astype(np.float32)
        keep = rng.random(base.shape) < 0.85
        measured = rng.random(base.shape) < 0.5
        g = cell_gaussians(grid, np.full((*base.shape, 3), 0.5, np.float32), depth, np.full(base.shape, 0.9),
                           keep, 0.5, 0.1)
        img = rng.choice([0.1, 0.35, 0.6, 0.9], base.shape)[..., None].repeat(3, 2) if colours else None
        out.append(CameraDetail.build(grid, depth, keep, measured, g.means, img))
    return out


def test_cull_covered_matches_reference():
    details = _random_details(4)
    rng = np.random.default_rng(5)
    n = 400
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[:, 2] = np.abs(dirs[:, 2]) * 0.3
    means = dirs * rng.uniform(3.0, 25.0, (n, 1)) + [0, 0, 1.5]
    # log scales from 5 cm to 3 m: every pyramid level from 0 to the cap at 64 cells
    coarse = Gaussians(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                       rng.uniform(math.log(0.05), math.log(3.0), (n, 3)).astype(np.float32),
                       np.zeros(n, np.float32), np.zeros((n, 1, 3), np.float32))
    for tol in (0.0, 0.15):
        got = cull_covered(coarse, details, tol)
        np.testing.assert_array_equal(got, cull_covered_reference(coarse, details, tol))
        assert 0.1 * n < got.sum() < 0.9 * n          # both outcomes occur (the comparison is not trivial)


def test_max_pyramid_is_each_windows_largest_depth():
    """CameraDetail.max_pyramid (each level a dilation of the one below) against the window's maximum taken
    directly: level L the largest kept depth within 2^L cells (0 outside the map), on a map with sparse cells and
    one cell at a corner (the window crossing the border at every level)."""
    d = _random_details(1, size=(40, 24))[0]
    depth = np.where(np.random.default_rng(2).random(d.depth.shape) < 0.02, d.depth, 0).astype(np.float32)
    depth[0, -1] = 50.0
    d = dataclasses.replace(d, depth=depth)
    h, w = depth.shape
    for L, got in enumerate(d.max_pyramid()):
        r = 2 ** L
        pad = np.pad(depth, r)
        want = np.zeros_like(depth)
        for dy in range(2 * r + 1):
            for dx in range(2 * r + 1):
                want = np.maximum(want, pad[dy:dy + h, dx:dx + w])
        np.testing.assert_array_equal(got, want, err_msg=f"level {L}")


@pytest.mark.parametrize("dedupe", [0.0, 0.7, 1.0])
def test_carve_details_matches_reference(dedupe):
    details = _random_details(6)
    got = carve_details(details, 0.15, dedupe)
    want = carve_details_reference(details, 0.15, dedupe)
    assert len(got) == len(want) == len(details)
    for g, w, d in zip(got, want, details):
        assert g.shape == (int(d.keep.sum()),)
        np.testing.assert_array_equal(g, w)
    dropped = sum(int((~g).sum()) for g in got)
    assert dropped > 20 and all(g.sum() > 0.5 * len(g) for g in got)
    keep, free = carve_details_both(details, 0.15, dedupe)
    for k, f, g, w in zip(keep, free, got, carve_details_reference(details, 0.15, 0.0)):
        np.testing.assert_array_equal(k, g)
        np.testing.assert_array_equal(f, w)


def test_carve_details_with_the_colour_test_matches_reference():
    """carve_details' free-space rule with the colour test (a keyframe without a sweep), one camera without an image
    among them (its cells have no colour to test, and it tests none: the depth alone decides there), against the
    cell-by-cell reference; the cameras come in one stack (CarveCameras), each carved by all but itself."""
    from dataclasses import replace

    details = _random_details(9, n_cams=5, colours=True)
    details[2] = replace(details[2], colours=None)
    photo = (12.0, 0.15)
    for dedupe in (0.0, 1.0):
        got = carve_details(details, 0.15, dedupe, photo)
        want = carve_details_reference(details, 0.15, dedupe, photo)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        by_depth = carve_details(details, 0.15, dedupe)
        assert all((b <= g).all() for b, g in zip(by_depth, got))      # the colour test only keeps more
        assert sum(int((~g).sum()) for g in got) < sum(int((~b).sum()) for b in by_depth)
        assert (~got[2]).sum() > 0
    # both rules and the free-space rule alone from one pass (a drive's fused cells and camera layers)
    both = carve_details_both(details, 0.15, 1.0, photo)
    for keep, free, wk, wf in zip(*both, carve_details_reference(details, 0.15, 1.0, photo),
                                  carve_details_reference(details, 0.15, 0.0, photo)):
        np.testing.assert_array_equal(keep, wk)
        np.testing.assert_array_equal(free, wf)
    assert sum(int((b & ~a).sum()) for a, b in zip(*both)) > 20         # the dedupe dropped what free keeps


@pytest.mark.parametrize("photo", [None, (12.0, 0.15)])
def test_carve_against_matches_reference(photo):
    """runtime.detail.carve_against (the see-through rule of a neighbouring keyframe's cameras, with or without the
    colour test) against its cell-by-cell reference; the colour test keeps cells the depth alone drops."""
    details = _random_details(8, colours=True)
    others = details[1:]
    got = np.ones(len(details[0].means), bool)
    carve_against(details[0], others, got, 0.15, photo)
    want = np.ones_like(got)
    carve_against_reference(details[0], others, want, 0.15, photo)
    np.testing.assert_array_equal(got, want)
    by_depth = np.ones_like(got)
    carve_against(details[0], others, by_depth, 0.15)
    assert (~by_depth).sum() > 20
    if photo is not None:     # a subset of the depth's drops: those whose colour no neighbour pixel shows
        assert (by_depth <= got).all() and 0 < (~got).sum() < (~by_depth).sum()


# -- densify --------------------------------------------------------------------------------------------------------

def test_densify_does_not_interpolate_across_a_colour_edge():
    h, w = 90, 160
    img = np.empty((h, w, 3), np.float32)
    img[:, :w // 2] = [0.8, 0.3, 0.2]
    img[:, w // 2:] = [0.2, 0.4, 0.9]
    img += np.random.default_rng(7).normal(0, 0.01, img.shape).astype(np.float32)   # a little sensor noise
    truth = np.where(np.arange(w)[None, :] < w // 2, 5.0, 20.0) * np.ones((h, 1))
    sparse = np.zeros((h, w), np.float32)
    sparse[3::8, 3::8] = truth[3::8, 3::8]            # samples 8 cells apart; the nearest to the edge (79 | 80): 75, 83
    assert not sparse[:, 79:81].any()
    d = densify(sparse, img, 200.0, 6.0)
    # within 3 % of its side's depth everywhere, the two columns beside the edge included: a blend across the
    # edge (log-average of 5 and 20 = 10 m) would be 100 % off
    np.testing.assert_array_less(np.abs(d / truth - 1), 0.03)
    np.testing.assert_array_equal(d[sparse > 0], sparse[sparse > 0])    # measured cells keep their value
    # the same samples with a flat guide do blend across the edge (what the test guards against)
    flat = densify(sparse, np.full_like(img, 0.5), 200.0, 6.0)
    assert np.abs(flat[:, 79:81] / truth[:, 79:81] - 1).max() > 0.2
    assert not densify(np.zeros((h, w), np.float32), img, 200.0, 6.0).any()


def test_densify_with_one_smoother_for_an_image_gives_each_call_its_own_bits():
    """camera_detail spreads the LiDAR and the model's depth over one camera's image with one edge_smoother: each
    result is the one a smoother made for that call gives, bit for bit (the smoother keeps nothing of a call)."""
    rng = np.random.default_rng(9)
    img = cv2.GaussianBlur(rng.random((270, 480, 3)).astype(np.float32), (0, 0), 2)
    a = np.where(rng.random((270, 480)) < 0.05, rng.uniform(2.0, 40.0, (270, 480)), 0).astype(np.float32)
    b = np.where(rng.random((270, 480)) < 0.6, rng.uniform(1.0, 90.0, (270, 480)), 0).astype(np.float32)
    shared = edge_smoother(img, 200.0, 6.0)
    got = [densify(s, img, 200.0, 6.0, shared) for s in (a, b, a)]
    for s, d in zip((a, b, a), got):
        np.testing.assert_array_equal(d, densify(s, img, 200.0, 6.0))
    assert not np.array_equal(got[0], got[1])        # two inputs, two results: the test compares something


def test_densify_gives_the_same_bits_from_threads_beside_other_opencv_work():
    """A keyframe's cameras are made two at a time and a drive's next keyframe beside its fusion's OpenCV work:
    OpenCV's fast global smoother gave another result when another thread's work held its thread pool (20 of 20
    calls differed beside a blur); densify runs OpenCV on one thread (one_thread_opencv), the same every time."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    rng = np.random.default_rng(8)
    img = cv2.GaussianBlur(rng.random((270, 480, 3)).astype(np.float32), (0, 0), 2)
    sparse = np.where(rng.random((270, 480)) < 0.05, rng.uniform(2.0, 40.0, (270, 480)), 0).astype(np.float32)
    ref = densify(sparse, img, 200.0, 6.0)
    big = rng.random((1080, 1920, 3)).astype(np.float32)
    stop = threading.Event()

    def blur():
        while not stop.is_set():
            cv2.GaussianBlur(big, (0, 0), 5)

    other = threading.Thread(target=blur)
    other.start()
    try:
        with ThreadPoolExecutor(2) as pool:
            got = list(pool.map(lambda _: densify(sparse, img, 200.0, 6.0), range(8)))
    finally:
        stop.set()
        other.join()
    for d in got:
        np.testing.assert_array_equal(d, ref)


def test_support_mask_marks_cells_near_samples():
    sparse = np.zeros((40, 60), np.float32)
    sparse[20, 10] = 5.0
    sparse[5, 50] = 7.0
    m = support_mask(sparse, 3.0)
    yy, xx = np.mgrid[0:40, 0:60]
    want = (np.hypot(yy - 20, xx - 10) <= 3.0) | (np.hypot(yy - 5, xx - 50) <= 3.0)
    np.testing.assert_array_equal(m, want)          # the precise Euclidean distance transform: exact
    assert not m[0, 0] and not m[39, 30] and not support_mask(np.zeros((4, 4), np.float32), 3.0).any()


# -- ground plane, far sphere -----------------------------------------------------------------------------------------

def _ground_sweep(tilt_deg: float, azimuth_deg: float, height: float = -1.8, n: int = 6000, seed: int = 0,
                  cars: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR returns on the plane z = height + gx x + gy y (tilted ``tilt_deg`` towards ``azimuth_deg``) with 3 cm
    noise, out to 35 m, and box "cars" (4 x 1.8 m, 0.3-1.6 m above the road). Returns (points, the true plane)."""
    rng = np.random.default_rng(seed)
    r, th = np.sqrt(rng.uniform(1, 35 ** 2, n)), rng.uniform(0, 2 * np.pi, n)
    x, y = r * np.cos(th), r * np.sin(th)
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    gx, gy = math.tan(t) * math.cos(a), math.tan(t) * math.sin(a)
    pts = [np.stack([x, y, height + gx * x + gy * y + rng.normal(0, 0.03, n)], axis=1)]
    for _ in range(cars):
        cx, cy = rng.uniform(-20, 20, 2)
        px, py = cx + rng.uniform(-2, 2, 400), cy + rng.uniform(-0.9, 0.9, 400)
        pts.append(np.stack([px, py, height + gx * px + gy * py + rng.uniform(0.3, 1.6, 400)], axis=1))
    nrm = np.array([-gx, -gy, 1.0]) / math.sqrt(1 + gx * gx + gy * gy)
    return np.concatenate(pts), np.array([*nrm, -nrm[2] * height])


def _plane_errors(plane: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(normal angle error, degrees; error of the height under the ego origin, metres)."""
    ang = math.degrees(math.acos(min(1.0, float(plane[:3] @ truth[:3]))))
    return ang, abs(-plane[3] / plane[2] + truth[3] / truth[2])


@pytest.mark.parametrize("tilt, azimuth", [(0.0, 0.0), (2.0, 30.0), (3.0, 200.0)])
def test_fit_ground_recovers_a_tilted_road_under_cars(tilt, azimuth):
    pts, truth = _ground_sweep(tilt, azimuth)
    plane = fit_ground(pts)
    assert plane is not None and plane[2] > 0 and abs(np.linalg.norm(plane[:3]) - 1) < 1e-12
    ang, dh = _plane_errors(plane, truth)
    # ~2000 returns with 3 cm noise in 3-25 m fix the slope to ~0.01 degrees; the bounds (0.25 degree, 5 cm)
    # leave room for the band's edges (a few road returns cut at +-0.3 m) yet fail a plane biased by the cars
    # (their returns start 0.3 m above the road) or left horizontal (3 degrees)
    assert ang < 0.25 and dh < 0.05


def test_fit_ground_refuses_few_returns_and_steep_planes():
    pts, _ = _ground_sweep(0.0, 0.0, n=300, cars=0)
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert 100 < ((r >= 3) & (r <= 25)).sum() < 200
    assert fit_ground(pts) is None                       # fewer returns in 3-25 m than min_points 200
    assert fit_ground(pts, min_points=50) is not None    # the same returns suffice when fewer are required
    assert fit_ground(_ground_sweep(20.0, 60.0)[0]) is None     # a 20 degree slope is not a road under the car
    assert fit_ground(np.zeros((0, 3))) is None


def test_fit_ground_recovers_a_six_degree_road():
    pts, truth = _ground_sweep(6.0, 200.0)
    plane = fit_ground(pts)
    assert plane is not None
    ang, dh = _plane_errors(plane, truth)
    assert ang < 0.5 and dh < 0.1


def test_ground_depth_of_a_pitched_camera_over_a_flat_road():
    h = 1.6
    cam = _camera(width=64, height=48, f=40.0, pos=(0.5, 0.3, h), yaw=0.4, pitch=-0.2)
    grid = grid_camera(cam, 2)
    got = ground_depth(grid, np.array([0.0, 0.0, 1.0, 0.0]))      # the plane z = 0
    # by hand: the cell's camera-frame ray (x, y, 1) reaches z = 0 at camera z s = -h / (R (x, y, 1))_z
    K = grid.K
    x = (np.arange(grid.width) - K[0, 2]) / K[0, 0]
    y = (np.arange(grid.height) - K[1, 2]) / K[1, 1]
    down = grid.rotation[2, 0] * x[None, :] + grid.rotation[2, 1] * y[:, None] + grid.rotation[2, 2]
    want = np.where(down < 0, -h / np.where(down < 0, down, -1.0), 0)
    assert (want > 0).any() and (want == 0).any()        # the horizon crosses the image
    np.testing.assert_allclose(got, want, rtol=1e-6)     # float32 output of a float64 computation
    # a plane 1 m lower (n . x + d = 0 with d = 1: z = -1) is hit (h + 1) / h times further along every ray
    lower = ground_depth(grid, np.array([0.0, 0.0, 1.0, 1.0]))
    np.testing.assert_allclose(lower, want * (h + 1) / h, rtol=1e-6)


def test_sphere_depth_inside_a_sphere():
    R = 300.0
    at_origin = grid_camera(_camera(width=64, height=48, f=40.0, pos=(0, 0, 0), yaw=1.0, pitch=0.3), 2)
    K = at_origin.K
    x = (np.arange(at_origin.width) - K[0, 2]) / K[0, 0]
    y = (np.arange(at_origin.height) - K[1, 2]) / K[1, 1]
    # from the centre every ray leaves at distance R: camera z = R cos(angle to the axis) = R / |(x, y, 1)|
    want = R / np.sqrt(1 + x[None, :] ** 2 + y[:, None] ** 2)
    np.testing.assert_allclose(sphere_depth(at_origin, R), want, rtol=1e-6)    # float32 output
    off = grid_camera(_camera(width=64, height=48, f=40.0, pos=(1.5, -0.7, 1.9), yaw=-2.0), 2)
    z = sphere_depth(off, R).astype(np.float64)
    # off centre: the point at camera z on each ray lies on the sphere (|p| = R) and in front of the camera
    K = off.K
    xo = (np.arange(off.width) - K[0, 2]) / K[0, 0]
    yo = (np.arange(off.height) - K[1, 2]) / K[1, 1]
    q = np.stack(np.broadcast_arrays(xo[None, :] * z, yo[:, None] * z, z), axis=-1)
    p = q @ off.rotation.T + off.position
    np.testing.assert_allclose(np.linalg.norm(p, axis=-1), R, rtol=1e-6)
    assert (z > 0).all()


# -- rotations ------------------------------------------------------------------------------------------------------

def test_rotmat_to_quat_round_trips():
    rng = np.random.default_rng(8)
    qs = rng.normal(size=(300, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    # the trace <= 0 branches: half turns about x, y, z (largest diagonal entry R00, R11, R22) and near-half turns
    # about random axes
    special = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1e-3, 1, 0.2, -0.1], [1e-3, 0.1, 1, 0.3],
               [1e-3, -0.2, 0.1, 1]]
    axes = rng.normal(size=(30, 3))
    angles = rng.uniform(2.2, math.pi, 30)         # > 120 degrees: trace = 1 + 2 cos(angle) < 0
    near_half = np.column_stack([np.cos(angles / 2), np.sin(angles / 2)[:, None] * axes /
                                 np.linalg.norm(axes, axis=1, keepdims=True)])
    qs = np.concatenate([qs, np.asarray(special, float) / np.linalg.norm(special, axis=1, keepdims=True),
                         near_half])
    branches = set()
    for q in qs:
        R = quat_to_rotmat(q)
        tr = np.trace(R)
        branches.add("tr" if tr > 0 else int(np.argmax(np.diag(R))))
        got = rotmat_to_quat(R)
        # float64 Shepperd: ~1e-15; up to the sign (q and -q are the same rotation)
        assert abs(np.linalg.norm(got) - 1) < 1e-12
        assert min(np.abs(got - q).max(), np.abs(got + q).max()) < 1e-9
        np.testing.assert_allclose(quat_to_rotmat(got), R, atol=1e-12)
    assert branches == {"tr", 0, 1, 2}


def test_rotmats_to_quats_matches_rotmat_to_quat():
    rng = np.random.default_rng(11)
    qs = rng.normal(size=(200, 4))
    qs[:4] = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]]     # each branch's extreme case
    qs[4:50, 0] *= 1e-3                                                   # near half turns: trace < 0 branches
    Rs = quat_to_rotmat(qs)
    got = rotmats_to_quats(Rs)
    for q, R in zip(got, Rs):
        one = rotmat_to_quat(R)
        # the same rotation, up to the sign; float64 (the batched version clamps its sqrt argument at 1e-12)
        assert min(np.abs(q - one).max(), np.abs(q + one).max()) < 1e-9
    np.testing.assert_allclose(quat_to_rotmat(got), Rs, atol=1e-12)


def _cov_ego(g: Gaussians) -> np.ndarray:
    R = quat_to_rotmat(g.quats)
    return R @ (np.exp(2.0 * g.log_scales.astype(np.float64))[:, :, None] * R.transpose(0, 2, 1))


def test_surface_discs_lie_on_a_tilted_road_and_look_round_from_their_camera():
    """surface_stretch > 0 on the road seen by a pitched camera: interior cells' discs have the road's normal as
    their thin axis and project back onto their cell as a circle of std ``footprint`` cells; on a frontal wall the
    surface disc is the image-plane disc."""
    cam = _camera(width=64, height=48, f=40.0, pos=(0.5, 0.0, 1.6), pitch=-0.35)
    grid = grid_camera(cam, 1)
    depth = ground_depth(grid, np.array([0.0, 0.0, 1.0, 0.0]))
    keep = (depth > 1.0) & (depth < 40.0)
    inner = cv2.erode(keep.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                      borderValue=0) > 0          # (the image's edge rows have one-sided tangents: left out)
    col = np.full((48, 64, 3), 0.5, np.float32)
    g = cell_gaussians(grid, col, depth, np.full(depth.shape, 0.9), keep, 0.5, 0.1, surface_stretch=10.0)
    # the kept cells with all four neighbours kept, up to 8 m: the road meets their rays at 11+ degrees, so its
    # tangents are < 1 / sin(11 deg) ~ 5 x the image-plane footprint, below the stretch limit 10
    sel = (inner & (depth < 8.0))[keep]
    assert sel.sum() > 500
    cov = _cov_ego(g)[sel]
    _, v = np.linalg.eigh(cov)
    normal = v[:, :, 0]                             # the thin axis (smallest variance)
    # float32 quats / scales: ~1e-6 -> the normal within ~1e-3 of ego z; thickness 0.1 x the disc: well separated
    assert (np.abs(normal[:, 2]) > 0.999).all()
    # projected into the camera (Jacobian at the centre), the disc is a circle of 0.5 px std. The central-difference
    # tangents are exact only where the depth is linear across the cell; up to 5 m the road's depth changes by
    # < 8 % per row and the projected variance comes out within 1.9 % (measured): 3 % bound. (To 12 m, 13 % per
    # row, it is 6.6 %; a disc of the wrong size, e.g. without the footprint factor, is 300 % off)
    near = (inner & (depth < 5.0))[keep]
    assert near.sum() > 500
    cov = _cov_ego(g)[near]
    q = (g.means.astype(np.float64)[near] - grid.position) @ grid.rotation
    X, Y, Z = q[:, 0], q[:, 1], q[:, 2]
    J = np.zeros((len(q), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = grid.K[0, 0] / Z, -grid.K[0, 0] * X / Z ** 2
    J[:, 1, 1], J[:, 1, 2] = grid.K[1, 1] / Z, -grid.K[1, 1] * Y / Z ** 2
    c2 = J @ grid.rotation.T @ cov @ grid.rotation @ J.transpose(0, 2, 1)
    np.testing.assert_allclose(c2, np.broadcast_to(0.25 * np.eye(2), c2.shape), atol=0.03 * 0.25)
    # the image-plane disc would look the same from the camera but stands across the road: its thin axis is the
    # optical axis, 70 degrees from ego z (the camera looks 20 degrees down): |cos| = sin(20 deg) = 0.34
    flat = cell_gaussians(grid, col, depth, np.full(depth.shape, 0.9), keep, 0.5, 0.1)
    np.testing.assert_allclose(np.abs(np.linalg.eigh(_cov_ego(flat)[sel])[1][:, 2, 0]), math.sin(0.35), atol=1e-3)
    # beyond 30 m the road meets the rays at < 3 degrees: tangents > 10 x the footprint, so those cells keep the
    # image-plane disc (the same covariance as without surface_stretch; float32)
    grazing = (depth > 30.0)[keep]
    assert grazing.sum() > 50
    np.testing.assert_allclose(_cov_ego(g)[grazing], _cov_ego(flat)[grazing], rtol=1e-5, atol=1e-9)
    # a frontal wall: the surface disc is the image-plane one (same covariance)
    wall = np.full(depth.shape, 10.0, np.float32)
    a = cell_gaussians(grid, col, wall, np.full(depth.shape, 0.9), np.ones_like(keep), 0.5, 0.1, surface_stretch=10.0)
    b = cell_gaussians(grid, col, wall, np.full(depth.shape, 0.9), np.ones_like(keep), 0.5, 0.1)
    np.testing.assert_allclose(_cov_ego(a), _cov_ego(b), atol=1e-8)     # ~(0.125 m)^2 entries, float32


# -- a flat textured wall from its cells ----------------------------------------------------------------------------

def _wall_cells(tex: np.ndarray, footprint: float = 0.6):
    cam = _camera(width=96, height=64, f=60.0)       # at x = 1 looking along ego x: the wall x = 11 is at z = 10
    grid = grid_camera(cam, 1)
    h, w = tex.shape[:2]
    depth = np.full((h, w), 10.0, np.float32)
    keep = np.ones((h, w), bool)
    g = cell_gaussians(grid, grid_colours(tex, grid), depth, np.full((h, w), 0.95), keep, footprint, 0.1)
    return cam, grid, g


@pytest.mark.parametrize("stretch", [0.0, 4.0, 30.0])
def test_cell_gaussians_matches_reference(stretch):
    """The numba pass against the numpy reference on a road-like depth (rows nearer towards the bottom, noise,
    holes): the same Gaussians in the same order. Both compute in float64 in the same order of operations and
    store float32, so 1e-6 relative bounds a last-bit difference of a libm function (atan2, sqrt) that can move
    a float32 by one ulp; a wrong branch moves a disc's axes or scales by O(1)."""
    rng = np.random.default_rng(3)
    cam = _camera(width=120, height=80, f=70.0, pitch=-10.0)
    h, w = cam.height, cam.width
    rows = np.arange(h, dtype=np.float64)[:, None] * np.ones((1, w))
    depth = (3.0 + 60.0 / (1.0 + np.maximum(rows - h / 3, 0.5)) + 0.05 * rng.random((h, w))).astype(np.float32)
    depth[20:30, 50:60] = 4.0                                     # a near box: a depth step around it
    keep = rng.random((h, w)) > 0.15
    colours = rng.random((h, w, 3)).astype(np.float32)
    opacity = np.full((h, w), 0.95)
    a = cell_gaussians(cam, colours, depth, opacity, keep, 0.5, 0.1, surface_stretch=stretch)
    b = cell_gaussians_reference(cam, colours, depth, opacity, keep, 0.5, 0.1, surface_stretch=stretch)
    assert len(a) == len(b) == keep.sum()
    np.testing.assert_allclose(a.means, b.means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a.log_scales, b.log_scales, rtol=1e-6, atol=1e-6)
    # q and -q are one rotation: compare the matrices
    np.testing.assert_allclose(quat_to_rotmat(a.quats), quat_to_rotmat(b.quats), atol=1e-6)
    np.testing.assert_array_equal(a.sh, b.sh)
    np.testing.assert_array_equal(a.opacity_logits, b.opacity_logits)
    if stretch > 0:                                               # the surface branch was taken for many cells
        cam_q = np.broadcast_to(rotmat_to_quat(cam.rotation).astype(np.float32), a.quats.shape)
        assert (np.abs(a.quats - cam_q).max(axis=1) > 1e-3).mean() > 0.3


def test_cell_gaussians_sit_on_their_pixel_rays_at_the_depth():
    tex = np.random.default_rng(9).random((64, 96, 3)).astype(np.float32)
    cam, grid, g = _wall_cells(tex)
    assert len(g) == 64 * 96 and g.sh_degree == 0
    ys, xs = np.nonzero(np.ones((64, 96), bool))
    uv, z, front = grid.project(g.means.astype(np.float64))
    assert front.all()
    # float32 means ~11 m from the origin: ~1e-6 m rounding -> ~1e-5 px at f = 60, z = 10
    np.testing.assert_allclose(uv, np.stack([xs, ys], axis=-1), atol=1e-4)
    np.testing.assert_allclose(z, 10.0, atol=1e-5)
    np.testing.assert_allclose(g.means[:, 0], 11.0, atol=1e-5)           # on the wall plane, ego frame
    # disc std = footprint x z / f = 0.6 x 10 / 60 = 0.1 m across, thickness 0.1 x that along the axis
    np.testing.assert_allclose(np.exp(g.log_scales), np.tile([0.1, 0.1, 0.01], (len(g), 1)), rtol=1e-6)
    np.testing.assert_allclose(quat_to_rotmat(g.quats), np.broadcast_to(cam.rotation, (len(g), 3, 3)), atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-g.opacity_logits)), 0.95, rtol=1e-6)
    np.testing.assert_allclose(g.sh[:, 0] * SH_C0 + 0.5, tex[ys, xs], atol=1e-6)    # the pixel's colour


def test_a_flat_wall_renders_back_its_colour_and_depth():
    # piecewise-constant blocks of 8 px: 2+ px inside a block, every splat that reaches the pixel has the block's
    # colour (screen std sqrt(0.6^2 + 0.3) = 0.81 px, cut at 3 sigma = 2.4 px)
    rng = np.random.default_rng(10)
    blocks = np.kron(rng.uniform(0.1, 0.9, (8, 12, 3)), np.ones((8, 8, 1))).astype(np.float32)
    cam, _, g = _wall_cells(blocks)
    r = render(g, rig_camera(cam))
    inner = (slice(4, -4), slice(4, -4))
    # alpha: the pixel's own disc gives 0.95, its 4 edge neighbours 0.95 exp(-1 / (2 x 0.66)) ~ 0.44 each, so the
    # transmittance left is below 0.05 x 0.56^4 < 0.005
    assert r.alpha[inner].min() > 0.995
    # every disc is at camera z 10: the expected depth is 10 up to float32 rounding
    np.testing.assert_allclose(r.depth[inner], 10.0, atol=1e-4)
    yy, xx = np.mgrid[0:64, 0:96]
    interior = (yy % 8 >= 2) & (yy % 8 < 6) & (xx % 8 >= 2) & (xx % 8 < 6)
    # rgb = sum w_i c_i with sum w_i = alpha: rgb / alpha is exactly the block colour (float32 accumulation)
    np.testing.assert_allclose((r.rgb / r.alpha[..., None])[interior], blocks[interior], atol=1e-4)

    # a smooth random texture: the render matches the texture blurred by the splats' screen std, closer than a
    # one-pixel misregistration of it would (coplanar discs composite in index order, which pulls each pixel
    # slightly towards earlier neighbours, but by much less than a pixel; cells misplaced by one pixel fail this)
    tex = cv2.GaussianBlur(rng.random((64, 96, 3)).astype(np.float32), (0, 0), 2.0)
    tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 0.8 + 0.1).astype(np.float32)
    cam, _, g = _wall_cells(tex)
    rgb = render(g, rig_camera(cam)).rgb
    blurred = cv2.GaussianBlur(tex, (0, 0), math.sqrt(0.6 ** 2 + LOW_PASS))
    one_px = max(_psnr(np.roll(blurred, 1, 1)[inner], blurred[inner]),
                 _psnr(np.roll(blurred, 1, 0)[inner], blurred[inner]))
    assert _psnr(rgb[inner], blurred[inner]) > one_px
    assert _psnr(rgb[inner], tex[inner]) > 28.0       # and in absolute terms (measured 31 dB; 3 dB margin)


# -- one camera end to end: a box in front of a wall ----------------------------------------------------------------

BOX_X, WALL_X = 6.0, 21.0                   # ego x of the box's front face and of the wall (camera at x = 1)
BOX_Y, BOX_Z = (-1.5, 1.5), (0.5, 2.5)      # the face's extent, metres
BOX_RGB, WALL_RGB = np.array([0.85, 0.25, 0.2], np.float32), np.array([0.2, 0.45, 0.85], np.float32)
LIDAR_AT = np.array([0.6, 0.0, 1.8])        # the sensor sits above and behind the camera


def _trace(origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(hit points [N, 3], hit the box [N]) of rays from ``origin`` (forward-looking: dirs x > 0)."""
    pb = origin + ((BOX_X - origin[0]) / dirs[:, 0])[:, None] * dirs
    on_box = (pb[:, 1] >= BOX_Y[0]) & (pb[:, 1] <= BOX_Y[1]) & (pb[:, 2] >= BOX_Z[0]) & (pb[:, 2] <= BOX_Z[1])
    pw = origin + ((WALL_X - origin[0]) / dirs[:, 0])[:, None] * dirs
    return np.where(on_box[:, None], pb, pw), on_box


@functools.lru_cache(maxsize=1)
def _box_scene():
    """(camera 160x90, its image [90, 160, 3] (4x supersampled: the box's edges mix colours in the cells they
    cross), a LiDAR sweep on a 1 degree grid from LIDAR_AT (~1 return per detail cell at stride 2), coarse wall
    Gaussians (the model))."""
    cam = _camera(width=160, height=90, f=110.0)
    ss = 4
    u = (np.arange(cam.width * ss) + 0.5) / ss - 0.5
    v = (np.arange(cam.height * ss) + 0.5) / ss - 0.5
    _, d = cam.pixel_rays(np.stack(np.meshgrid(u, v), axis=-1))
    _, box = _trace(cam.position, d.reshape(-1, 3))
    img = np.where(box.reshape(cam.height * ss, cam.width * ss, 1), BOX_RGB, WALL_RGB).astype(np.float32)
    img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    az, el = np.meshgrid(np.radians(np.arange(-40, 40, 1.0)), np.radians(np.arange(-25, 25, 1.0)))
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    lidar, _ = _trace(LIDAR_AT, dirs)
    ys, zs = np.meshgrid(np.linspace(-15, 15, 11), np.linspace(-8, 10, 7))
    wall = _discs(np.stack([np.full(ys.size, WALL_X), ys.ravel(), zs.ravel()], axis=1), 2.0, [0.5, 0.5, 0.5],
                  thin=0.05)
    return cam, img, lidar, wall


def test_camera_detail_leaves_no_flying_pixels_at_a_depth_edge():
    cam, img, lidar, coarse = _box_scene()
    opts = DetailOptions()
    g, det, counts = camera_detail(cam, img, coarse, opts, lidar)
    _, z, front = cam.project(g.means.astype(np.float64))
    assert front.all()
    lo, hi = 5.0 * (1 + opts.edge_ratio), 20.0 / (1 + opts.edge_ratio)
    assert not ((z > lo) & (z < hi)).any(), np.sort(z[(z > lo) & (z < hi)])
    # and the two surfaces are there at their depths (1 %: float32 means; densified values are the samples')
    near, far = np.abs(z / 5 - 1) < 0.01, np.abs(z / 20 - 1) < 0.01
    assert near.sum() > 500 and far.sum() > 2000 and (near | far).all()
    # colours follow the surfaces: 2+ cells inside the box's cells the Gaussians are box-coloured, inside the wall's
    # wall-coloured (the mixed cells at the box's edge stay on the near side, and the unsharp mask reaches ~1 cell:
    # those are left out; 1e-3: float32 SH round trip, the colours are flat)
    ys, xs = np.nonzero(det.keep)
    cmap = np.zeros((*det.keep.shape, 3), np.float32)
    cmap[ys, xs] = g.sh[:, 0] * SH_C0 + 0.5
    for depth, rgb in ((5.0, BOX_RGB), (20.0, WALL_RGB)):
        on = det.keep & (np.abs(det.depth / depth - 1) < 0.01)
        inner = cv2.erode(on.astype(np.uint8), np.ones((5, 5), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
        assert inner.sum() > 0.6 * on.sum()
        np.testing.assert_allclose(cmap[inner], np.broadcast_to(rgb, cmap[inner].shape), atol=1e-3)
    # the counts: every Gaussian is counted once (every kept cell here has a LiDAR return within support_deg: all
    # are "lidar"; no ground plane is given)
    assert counts["lidar"] + counts["ground"] + counts["model"] + counts["far"] == len(g)
    assert counts["lidar"] > 3000 and counts["edge"] > 0 and counts["lidar"] + counts["edge"] <= det.keep.size
    assert det.keep.sum() == len(g) and det.means.shape == (len(g), 3)
    np.testing.assert_array_equal(det.depth[~det.keep], 0)
    # the Gaussians are those of the kept cells in np.nonzero order, at the CameraDetail's depths
    ys, xs = np.nonzero(det.keep)
    np.testing.assert_allclose(z, det.depth[ys, xs], rtol=1e-5)     # float32 means


def test_camera_detail_ego_mask_removes_the_masked_cells():
    cam, img, lidar, coarse = _box_scene()
    opts = DetailOptions()
    g0, d0, _ = camera_detail(cam, img, coarse, opts, lidar)
    mask = np.zeros((cam.height, cam.width), bool)
    mask[70:, :] = True                          # the bottom rows: wall only (the box's lower edge is at row 66.5)
    g1, d1, c1 = camera_detail(cam, img, coarse, opts, lidar, ego_mask=mask)
    small = np.zeros_like(d0.keep)
    small[35:, :] = True                         # full-res rows 70-89 are cells 35-44 at stride 2
    np.testing.assert_array_equal(d1.keep, d0.keep & ~small)
    assert len(g1) == len(g0) - int((d0.keep & small).sum()) and len(g1) < len(g0) - 300
    assert sum(c1[k] for k in ("lidar", "ground", "model", "far")) == len(g1)


def test_fusion_culls_coarse_gaussians_in_front_of_detail_and_keeps_those_behind():
    """cull_covered's promise on the box scene: a coarse Gaussian is culled when it lies in front of (or within the
    tolerance of) some kept detail cell in its footprint, kept when it lies behind every detail surface of its
    footprint or where the camera has no detail cell (here: under an ego mask). Rendering the detail with the kept
    coarse Gaussians shows the detail surfaces unveiled, and the coarse surface where there is no detail."""
    cam, img, lidar, wall = _box_scene()
    opts = DetailOptions()
    mask = np.zeros((cam.height, cam.width), bool)
    mask[50:, :40] = True                        # no detail in the bottom-left corner (wall only there)
    probe_rgb = [0.9, 0.9, 0.1]

    def at(u, v, z):                             # the ego point at camera z on full-res pixel (u, v)'s ray
        o, d = cam.pixel_rays(np.array([[u, v]], float))
        return o[0] + d[0] * z / float(d[0] @ cam.rotation[:, 2])

    # sigma 0.1 m: 3 sigma = 0.3 m; at 3 m that is 5.5 cells of the stride-2 grid (f = 55): window 8 cells; at 12 m
    # 1.4 cells: window 2 cells
    probes = {
        "front of wall": (at(140, 20, 3.0), False),     # 3 m in front of the wall: veils it, culled
        "on wall": (at(140, 70, 20.8), False),          # within tolerance (20.8 < 1.15 x 20): culled
        "behind wall": (at(20, 20, 25.0), True),        # behind the wall: kept
        "behind box": (at(80, 44, 12.0), True),         # behind the box, window inside the box: kept
        "across edge": (at(47, 44, 12.0), False),       # behind the box but its window reaches the wall: culled
        "no detail": (at(18, 72, 3.0), True),           # in front, but under the mask: no detail cell, kept
        "behind camera": (cam.position - [5.0, 0, 0], True),
    }
    coarse = concat_gaussians([wall, _discs(np.stack([p for p, _ in probes.values()]), 0.1, probe_rgb)])
    n_wall = len(wall)
    g, det, _ = camera_detail(cam, img, coarse, opts, lidar, ego_mask=mask)
    keep = cull_covered(coarse, [det], opts.cull_tolerance)
    np.testing.assert_array_equal(keep, cull_covered_reference(coarse, [det], opts.cull_tolerance))
    got = dict(zip(probes, keep[n_wall:].tolist()))
    assert got == {k: want for k, (_, want) in probes.items()}
    # the model's wall discs on the image lie on the wall's detail cells (their windows reach past the mask): culled;
    # those outside the view stay
    uv, _, _ = det.grid.project(wall.means.astype(np.float64))
    px = np.rint(uv)
    seen = (px[:, 0] >= 0) & (px[:, 0] < det.grid.width) & (px[:, 1] >= 0) & (px[:, 1] < det.grid.height)
    assert 0 < seen.sum() < n_wall
    np.testing.assert_array_equal(keep[:n_wall], ~seen)

    scene = concat_gaussians([g, coarse], [None, keep])
    r, alone = render(scene, rig_camera(cam)), render(g, rig_camera(cam))
    for (v, u), rgb in (((20, 140), WALL_RGB), ((44, 80), BOX_RGB)):
        # the detail surface alone has its colour (rgb / alpha: the one colour of every disc there; 0.01 allows
        # the sharpened colours of cells a few cells from the box's edge)
        np.testing.assert_allclose(alone.rgb[v, u] / alone.alpha[v, u], rgb, atol=0.01)
        # unveiled: whatever kept coarse Gaussian shows there lies behind the detail, so it adds at most the
        # detail's leftover transmittance (1 - alpha, ~0.06 at the default footprint) x a colour <= 1; 1e-4: float32
        assert np.abs(r.rgb[v, u] - alone.rgb[v, u]).max() <= 1 - alone.alpha[v, u] + 1e-4
    # where there is no detail, the nearer coarse surface shows in front (0.01: the probe's alpha is ~0.99 and the
    # wall discs behind it are culled: nothing else is there)
    assert alone.alpha[72, 18] == 0
    np.testing.assert_allclose(r.rgb[72, 18] / r.alpha[72, 18], probe_rgb, atol=0.01)
    # without the cull the probe in front of the wall veils it: the bound above fails there (the test can tell)
    veiled = render(concat_gaussians([g, coarse]), rig_camera(cam)).rgb[20, 140]
    assert np.abs(veiled - alone.rgb[20, 140]).max() > 0.3


def test_camera_detail_counts_partition_the_gaussians_beyond_max_depth():
    cam = _camera(width=64, height=48, f=40.0)
    # the model sees a wall 200 m away (beyond max_depth 150): its cells go to the far sphere
    ys, zs = np.meshgrid(np.linspace(-300, 300, 13), np.linspace(-300, 300, 13))
    coarse = _discs(np.stack([np.full(ys.size, 201.0), ys.ravel(), zs.ravel()], axis=1), 40.0, [0.5] * 3, thin=0.5)
    g, _, counts = camera_detail(cam, np.full((48, 64, 3), 0.5, np.float32), coarse, DetailOptions(), None)
    assert len(g) == 32 * 24
    assert counts["lidar"] + counts["ground"] + counts["model"] + counts["far"] == len(g)


def test_read_ego_mask(tmp_path):
    cam = _camera(width=64, height=48)
    a = np.zeros((48, 64), np.uint8)
    a[40:, 10:20] = 255
    cv2.imwrite(str(tmp_path / "m.png"), a)
    np.testing.assert_array_equal(read_ego_mask(tmp_path / "m.png", cam), a > 0)
    cv2.imwrite(str(tmp_path / "small.png"), a[:20])
    with pytest.raises(RigError, match="'front': ego_mask: has shape"):
        read_ego_mask(tmp_path / "small.png", cam)
