"""Split cells (runtime.detail.split_cells, expand_split): at stride 2 a detail cell is one colour for 2x2 input
pixels, so a render at the input camera keeps ~2/3 of the image's gradient energy (PandaSet's own views: sharpness
0.67). A cell with a quarter (at stride 2 a pixel) whose luma strays from the four's mean by more than
DetailOptions.split becomes one Gaussian per quarter on the cell's disc. Checked here: which cells split, where
their quarters sit (on their rays and on the disc's plane), their colours and shapes, the render that resolves a
pixel texture the cells blur, the kernels against their references, the fusion's positions (the own views of two
cameras with split cells), a drive's transform and the exposure gain."""

from __future__ import annotations

import math

import numpy as np
import pytest
from xyzcyl.runtime.detail import (
    CameraDetail,
    DetailOptions,
    _quarters_kernel,
    _split_positions,
    _stray_kernel,
    cell_gaussians,
    expand_split,
    fuse_details,
    grid_camera,
    grid_colours,
    quarters_reference,
    split_cells,
    stray_reference,
)
from xyzcyl.runtime.drive import transform_detail, transform_gaussians
from xyzcyl.runtime.exposure import Harmoniser
from xyzcyl.runtime.imageio import LUMA_BT601
from xyzcyl.runtime.realeval import sharpness_ratio
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.render.gaussians import SH_C0
from xyzcyl.runtime.rig import Camera, Rig
from xyzcyl.runtime.scene import Scene, render_view, rig_camera

WALL_X = 10.0        # ego x of the wall the cameras see


def _camera(name: str = "A", x: float = 0.0, y: float = 0.0, f: float = 60.0, yaw: float = 0.0) -> Camera:
    """An OpenCV camera at (x, y, 1.5) ego looking along ego +x turned by ``yaw`` degrees about ego z, 96x64 px."""
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = (x, y, 1.5)
    K = np.array([[f, 0, 47.5], [0, f, 31.5], [0, 0, 1.0]])
    return Camera(K=K, cam_to_ego=T, width=96, height=64, name=name)


def _checker(colour, amplitude: float, blocks: np.ndarray | None = None, size: int = 1) -> np.ndarray:
    """[64, 96, 3] ``colour`` with a checker of +-amplitude in squares of ``size`` pixels where ``blocks`` (bool, one
    per 2 x size pixel block; None: everywhere)."""
    yy, xx = np.mgrid[0:64, 0:96]
    sign = np.where((yy // size + xx // size) % 2 == 0, 1.0, -1.0)
    if blocks is not None:
        sign = sign * np.kron(blocks, np.ones((2 * size, 2 * size)))
    return np.clip(np.asarray(colour, np.float32) + amplitude * sign[..., None], 0, 1).astype(np.float32)


def _wall(cam: Camera, image: np.ndarray, opts: DetailOptions) -> tuple[Gaussians, CameraDetail]:
    """``cam``'s detail layer of the wall x = WALL_X (every cell kept, its depth the wall's along the cell's ray)
    with its split cells."""
    grid = grid_camera(cam, opts.stride)
    origin, d = grid.pixel_rays()
    t = (WALL_X - origin[..., 0]) / d[..., 0]                       # distance to the wall along each cell's ray
    depth = (t * (d @ grid.rotation)[..., 2]).astype(np.float32)    # camera z
    keep = np.ones(depth.shape, bool)
    colours = grid_colours(image, grid, opts.sharpen, opts.footprint)
    g = cell_gaussians(grid, colours, depth, np.full(depth.shape, opts.opacity), keep, opts.footprint,
                       opts.thickness, surface_stretch=opts.surface_stretch)
    split = split_cells(cam, image, grid, g, keep, opts.split, opts.sharpen, opts.footprint)
    return g, CameraDetail.build(grid, depth, keep, keep, g.means, colours, split)


@pytest.mark.parametrize("stride", [2, 4])
def test_the_cells_whose_quarters_stray_split_and_their_quarters_sit_on_their_rays_on_the_wall(stride):
    rng = np.random.default_rng(4)
    half = stride // 2
    blocks = rng.random((64 // stride, 96 // stride)) < 0.3
    image = _checker([0.4, 0.5, 0.6], 0.1, blocks, size=half)     # each quarter one colour, +-0.1 off the cell's
    cam = _camera(yaw=20.0)                                 # the wall seen obliquely: its discs are not frontal
    opts = DetailOptions(stride=stride, sharpen=0.0, split=0.05)
    g, d = _wall(cam, image, opts)
    sp = d.split
    # the checker's cells stray by 0.1 > 0.05 from their mean, the flat ones by 0: exactly those split
    np.testing.assert_array_equal(sp.index, np.flatnonzero(blocks.ravel()))
    assert sp.means.shape == (blocks.sum(), 4, 3) and sp.colours.shape == (blocks.sum(), 4, 3)
    ys, xs = np.nonzero(blocks)
    qy = ys[:, None] * 2 + np.array([0, 0, 1, 1])[None, :]          # the quarters, rows first within the cell
    qx = xs[:, None] * 2 + np.array([0, 1, 0, 1])[None, :]
    uv, _, front = cam.project(sp.means.astype(np.float64))
    assert front.all()
    # a quarter's centre in the image: pixel (q + 1/2) half - 1/2; float32 means ~12 m from the origin: ~1e-6 m
    # rounding -> ~1e-5 px at f = 60
    np.testing.assert_allclose(uv, np.stack([(qx + 0.5) * half - 0.5, (qy + 0.5) * half - 0.5], axis=-1), atol=1e-3)
    # on the wall's plane (the surface discs lie in it): within float32 rounding of the means
    np.testing.assert_allclose(sp.means[..., 0], WALL_X, atol=1e-4)
    py, px = qy * half, qx * half                           # a pixel of each quarter (one colour in a quarter)
    np.testing.assert_allclose(sp.colours, image[py, px], atol=1e-6)    # sharpen 0: the pixels' own colours
    assert split_cells(cam, image, d.grid, g, d.keep, 0.0, 0.0, 0.5) is None            # 0: never
    assert split_cells(cam, image, d.grid, g, d.keep, 0.2, 0.0, 0.5) is None            # none strays that far


def test_expand_split_draws_each_split_cell_as_its_pixels():
    image = _checker([0.4, 0.5, 0.6], 0.1, np.random.default_rng(5).random((32, 48)) < 0.25)
    opts = DetailOptions(sharpen=0.0, split=0.05)
    g, d = _wall(_camera(), image, opts)
    sp = d.split
    keep = np.random.default_rng(6).random(len(g)) < 0.7
    e = expand_split(g, d, keep)
    is_split = np.zeros(len(g), bool)
    is_split[sp.index] = True
    plain = keep & ~is_split
    kept_split = keep[sp.index]
    assert len(e) == plain.sum() + 4 * kept_split.sum()
    n = int(plain.sum())
    np.testing.assert_array_equal(e.means[:n], g.means[plain])             # the plain cells first, unchanged
    np.testing.assert_array_equal(e.sh[:n], g.sh[plain])
    pix = e.subset(np.arange(n, len(e)))
    parent = np.repeat(sp.index[kept_split], 4)
    np.testing.assert_array_equal(pix.means, sp.means[kept_split].reshape(-1, 3))
    np.testing.assert_array_equal(pix.quats, g.quats[parent])
    np.testing.assert_allclose(pix.log_scales, g.log_scales[parent] - math.log(2), atol=1e-6)   # float32 log
    np.testing.assert_array_equal(pix.opacity_logits, g.opacity_logits[parent])
    np.testing.assert_allclose(pix.sh[:, 0] * SH_C0 + 0.5, sp.colours[kept_split].reshape(-1, 3), atol=1e-6)
    assert len(expand_split(g, d, np.zeros(len(g), bool))) == 0
    assert len(expand_split(g, CameraDetail.build(d.grid, d.depth, d.keep, d.keep, d.means))) == len(g)


def test_split_cells_resolve_a_pixel_texture_the_cells_blur():
    # +-0.15 per pixel at random (a checker's central differences, which sharpness_ratio takes, are 0)
    sign = np.where(np.random.default_rng(9).random((64, 96, 1)) < 0.5, -1.0, 1.0)
    image = (np.array([0.45, 0.5, 0.55]) + 0.15 * sign).astype(np.float32)
    cam = _camera()
    g, d = _wall(cam, image, DetailOptions())
    cells = render(g, rig_camera(cam)).rgb
    split = render(expand_split(g, d), rig_camera(cam)).rgb
    inner = (slice(4, -4), slice(4, -4))
    # one colour per 2x2 block keeps a quarter of the texture's variance; a Gaussian per pixel (std 0.25 px at
    # footprint 0.5, widened by the renderer's 0.3 px^2 low-pass to 0.6 px) keeps more: measured sharpness 0.29 ->
    # 0.53 and mean error 0.130 -> 0.104 (margins: 1.5x and 0.9x)
    sharp_cells, sharp_split = (sharpness_ratio(x[inner], image[inner]) for x in (cells, split))
    assert sharp_split > 1.5 * sharp_cells
    assert np.abs(split[inner] - image[inner]).mean() < 0.9 * np.abs(cells[inner] - image[inner]).mean()


def test_split_positions_follow_each_cell():
    rng = np.random.default_rng(7)
    first = 5
    split = [rng.random(n) < 0.3 for n in (7, 0, 11)]
    # the layout fuse_details makes, labelled: (camera, cell, quarter) for every Gaussian after the first
    layout = [(-1, i, 0) for i in range(first)]
    for j, m in enumerate(split):
        layout += [(j, i, 0) for i in np.flatnonzero(~m)]
    for j, m in enumerate(split):
        layout += [(j, i, q) for i in np.flatnonzero(m) for q in range(4)]
    at = {lab: k for k, lab in enumerate(layout)}
    old = [(-1, i) for i in range(first)] + [(j, i) for j, m in enumerate(split) for i in range(len(m))]
    where = _split_positions(first, split)
    for pos in (rng.permutation(len(old))[:15], np.sort(rng.permutation(len(old))[:15])):
        got = where(pos)
        want = []
        for p in pos:
            j, i = old[p]
            moved = j >= 0 and split[j][i]
            want += [at[(j, i, q)] for q in range(4)] if moved else [at[(j, i, 0)]]
        np.testing.assert_array_equal(np.sort(got), np.sort(want))
        if np.all(np.diff(pos) > 0):        # ascending positions come out ascending (fuse_details sorts none)
            np.testing.assert_array_equal(got, np.sort(want))


RED, BLUE = (0.9, 0.2, 0.2), (0.2, 0.3, 0.9)


def _share(rgb: np.ndarray, alpha: np.ndarray, colour, tol: float) -> float:
    """The fraction of the covered pixels within ``tol`` per channel of ``colour``."""
    covered = alpha > 0.5
    close = np.all(np.abs(rgb / np.maximum(alpha[..., None], 1e-6) - np.asarray(colour)) < tol, axis=-1)
    return float((close & covered).sum() / max(covered.sum(), 1))


def test_fused_cameras_with_split_cells_each_see_their_own_at_their_pose():
    """Two cameras see one wall, each in its own colour with a pixel checker (so most cells split); B is nearer and
    wins the shared part. Each camera's own view must show its own Gaussians alone, pixels included: the fusion's
    own-view positions follow the split cells to their pixels."""
    opts = DetailOptions()
    a, b = _camera("A", 0.0, 0.0), _camera("B", 4.0, 2.5)
    rng = np.random.default_rng(8)
    (ga, da), (gb, db) = (_wall(c, _checker(col, 0.08, rng.random((32, 48)) < 0.6), opts)
                          for c, col in ((a, RED), (b, BLUE)))
    g, own, counts = fuse_details(Gaussians.empty(), [ga, gb], [da, db], [0, 1], ("A", "B"), opts)
    assert counts["carved"] > 100
    shown_split = sum(int(np.isin(d.split.index, np.flatnonzero(k)).sum()) for d, k in
                      zip((da, db), (np.ones(len(ga), bool), np.ones(len(gb), bool))))
    assert len(g) > len(ga) + len(gb) and shown_split > 1000
    scene = Scene(gaussians=g, background=None, rig=Rig(cameras=(a, b)), own_views=own)
    for cam, col in ((a, RED), (b, BLUE)):
        rgb, _, alpha = render_view(scene, cam)
        # the checker's +-0.08 and the discs' blending stay within 0.15 of the colour; the other camera's is
        # 0.6 away in some channel
        assert _share(rgb, alpha, col, 0.15) > 0.99
    rgb, _, alpha = render_view(Scene(g, None, scene.rig), a)        # without own views: B's cells in A's image
    assert _share(rgb, alpha, BLUE, 0.15) > 0.05


def test_a_drives_transform_and_the_exposure_gain_reach_the_split_pixels():
    image = _checker([0.4, 0.5, 0.6], 0.1)
    g, d = _wall(_camera(), image, DetailOptions())
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = (3.0, -2.0, 0.5)
    moved = expand_split(transform_gaussians(g, T), transform_detail(d, T))
    want = transform_gaussians(expand_split(g, d), T)
    np.testing.assert_allclose(moved.means, want.means, atol=1e-5)      # float32 metres ~10 m
    np.testing.assert_allclose(moved.sh, want.sh, atol=1e-6)
    h = Harmoniser(1)
    gain = np.array([1.25, 1.0, 0.8])
    h.gains.append(gain[None, :])            # as ``add`` leaves them: the last keyframe's [C, 3]
    (dh,) = h.details([d], [0])
    np.testing.assert_allclose(dh.split.colours, d.split.colours / gain, rtol=1e-6)
    assert dh.split.means is d.split.means


@pytest.mark.parametrize("width, height", [(97, 64), (96, 65)])
def test_a_grid_that_does_not_tile_the_image_splits_nothing(width, height):
    cam = _camera().replace(width=width, height=height)
    image = np.zeros((height, width, 3), np.float32)
    image[::2, ::2] = 1.0
    grid = grid_camera(cam, 2)
    keep = np.ones((grid.height, grid.width), bool)
    g = cell_gaussians(grid, grid_colours(image, grid), np.full(keep.shape, 5.0, np.float32), np.full(keep.shape, 0.9),
                       keep, 0.5, 0.1)
    assert split_cells(cam, image, grid, g, keep, 0.03, 0.5, 0.5) is None


def test_the_kernels_match_their_references():
    """_stray_kernel and _quarters_kernel against their numpy definitions on random data: rays of any length, some
    grazing a disc (the fallback), some NaN (no ray)."""
    rng = np.random.default_rng(11)
    quarters = rng.random((40, 60, 3)).astype(np.float32) * 0.2 + 0.4
    keep = rng.random((20, 30)) < 0.8
    # exact: the same float32 mean and comparisons (sums in another order move the mean by an ulp, far below the
    # 1e-3 steps between the random values and the threshold)
    np.testing.assert_array_equal(_stray_kernel(quarters, keep, np.float32(0.03), LUMA_BT601),
                                  stray_reference(quarters, keep, 0.03))
    n = 500
    centre = rng.normal(0, 10, (n, 3))
    quats = rng.normal(0, 1, (n, 4))
    rays = rng.normal(0, 1, (n, 4, 3)) * rng.uniform(0.2, 3.0, (n, 4, 1))
    rays[:50, :, :] = centre[:50, None, :] / 7.0 + rng.normal(0, 0.01, (50, 4, 3))   # near the centre's direction
    rays[5, 2] = np.nan
    origin = np.array([1.0, -2.0, 0.5])
    got = np.empty((n, 4, 3), np.float32)
    _quarters_kernel(centre, quats, rays, origin, got)
    want = quarters_reference(centre, quats, rays, origin)
    # float64 in both, stored as float32: the same up to a last bit (~1e-6 relative of ~10 m)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(got[5, 2], centre[5].astype(np.float32))
