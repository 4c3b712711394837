"""The renderer takes several Gaussian sets and draws them as their concatenation without copying them, and draws a
set behind an earlier result (``behind``): what a drive's layered view (runtime.scene.Scene._layers) is made of."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import pinhole, random_gaussians
from xyzcyl.runtime.detail import concat_gaussians as concat
from xyzcyl.runtime.render import Gaussians, render, render_backward
from xyzcyl.runtime.render import kernels as K
from xyzcyl.runtime.render.core import _prepare
from xyzcyl.runtime.render.projection import RenderOptions
from xyzcyl.runtime.scene import composite_layers

# render(behind=a) against composite_layers(a, render alone): the layered raster stops a pixel once a's and b's
# transmittance together would fall to T_STOP, the composite once b's own would; a pixel stops before the Gaussian
# that would take it there, so each stop leaves at most T_STOP / (1 - A_MAX) of its light undrawn (the renderer's own
# bound, as in one pass), and a pixel with at most T_RESUME left is not drawn behind at all; times colours below ~2
# here (SH DC of sigma 0.5); typically far less (the mean's bound)
LAYERED_ATOL = 2 * 2 * max(float(K.T_STOP) / (1 - float(K.A_MAX)), float(K.T_RESUME))


def test_several_sets_draw_as_their_concatenation():
    rng = np.random.default_rng(11)
    # sizes across projection chunks (PROJ_CHUNK), one empty part, SH degrees 0 and 1 mixed
    parts = [random_gaussians(rng, 2 * K.PROJ_CHUNK + 17), random_gaussians(rng, 0),
             random_gaussians(rng, 300, degree=1), random_gaussians(rng, K.PROJ_CHUNK)]
    cam = pinhole(width=97, height=70)
    whole = render(concat(parts), cam, background=(0.1, 0.2, 0.3))
    split = render(parts, cam, background=(0.1, 0.2, 0.3))
    # the same slots in the same order, the same blends: only the SH padding of the degree-0 parts differs (adding
    # exact zeros), so equal to float32 rounding of the colour
    np.testing.assert_allclose(split.rgb, whole.rgb, atol=1e-6)
    np.testing.assert_array_equal(split.alpha, whole.alpha)
    np.testing.assert_array_equal(split.depth, whole.depth)
    # slot -> Gaussian index is the index in the concatenation
    opts = RenderOptions()
    a, b = _prepare(concat(parts), cam, opts), _prepare(parts, cam, opts)
    np.testing.assert_array_equal(a[1], b[1])               # instances per tile
    np.testing.assert_array_equal(a[4][a[2]], b[4][b[2]])   # the Gaussians they are, in order (slots differ)
    assert b[4][b[2]].max() >= len(parts[0]) + 300       # the last part's indices are offset


def test_a_set_drawn_behind_an_earlier_result():
    rng = np.random.default_rng(12)
    front = random_gaussians(rng, 400, lo=(-2, -1.5, 2), hi=(2, 1.5, 4), opacity=(0.0, 6.0))
    back = random_gaussians(rng, 400, lo=(-3, -2, 6), hi=(3, 2, 10))
    cam = pinhole()
    a = render(front, cam)
    b = render(back, cam, background=(0.2, 0.5, 0.9))
    e_rgb, e_depth, e_alpha = composite_layers(a, b)
    got = render(back, cam, background=(0.2, 0.5, 0.9), behind=a)
    np.testing.assert_allclose(got.rgb, e_rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.alpha, e_alpha, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.depth, e_depth, atol=LAYERED_ATOL * 10)   # metres: the light dropped x <= 10 m
    assert np.abs(got.rgb - e_rgb).mean() < 1e-4
    # the pixels the front covers stop early: less raster work than drawing the back set alone
    assert got.state.row_evals.sum() < b.state.row_evals.sum()
    # the earlier result is not changed, and its light is kept where nothing lies behind it
    np.testing.assert_array_equal(a.rgb, render(front, cam).rgb)
    # behind a result drawn over a background: refused (its pixels hold that background already)
    with pytest.raises(ValueError, match="behind"):
        render(back, cam, behind=b)
    with pytest.raises(ValueError, match="behind"):
        render(back, pinhole(width=40, height=30), behind=a)


def test_the_backward_pass_of_a_result_drawn_behind_is_the_sets_own():
    rng = np.random.default_rng(13)
    front, back = random_gaussians(rng, 50, lo=(-2, -1.5, 2), hi=(2, 1.5, 4)), random_gaussians(rng, 60)
    cam = pinhole(width=40, height=30)
    d_rgb = rng.normal(size=(30, 40, 3)).astype(np.float32)
    behind = render(back, cam, behind=render(front, cam))
    own = render(back, cam)
    g1 = render_backward(back, cam, behind, d_rgb)
    g2 = render_backward(back, cam, own, d_rgb)
    for name in ("means", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(g1, name), getattr(g2, name))
    assert np.abs(g1.means).max() > 0


def test_rows_that_stopped_are_skipped_and_the_rest_drawn_exactly():
    """The raster skips a tile's rows whose pixels all stopped (kernels._blend_one's live rows) and draws the others
    as before: behind an opaque wall over the image's upper part, whose edge crosses tiles, the pixels the wall never
    touched equal the back set drawn alone exactly, the rest its composite; fewer rows are evaluated than when the
    same tiles are drawn without the wall."""
    ys, xs = np.meshgrid(np.arange(-1.6, 0.21, 0.05), np.arange(-2.2, 2.21, 0.05), indexing="ij")
    means = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1).astype(np.float32)
    n = len(means)
    wall = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), np.log(0.06), np.float32),
                     np.full(n, 8.0, np.float32), np.full((n, 1, 3), 0.3, np.float32))
    back = random_gaussians(np.random.default_rng(4), 600, lo=(-3, -2, 6), hi=(3, 2, 10))
    cam = pinhole()
    a = render(wall, cam)
    stopped_rows = (1.0 - a.alpha <= K.T_RESUME).all(axis=1)             # rows drawn behind it start stopped
    tile_rows = stopped_rows.reshape(-1)[: (cam.height // K.TILE) * K.TILE].reshape(-1, K.TILE)
    assert (tile_rows.any(axis=1) & ~tile_rows.all(axis=1)).any()       # a tile with stopped and live rows
    alone = render(back, cam, background=(0.2, 0.5, 0.9))
    got = render(back, cam, background=(0.2, 0.5, 0.9), behind=a)
    free = a.alpha == 0
    assert free.mean() > 0.3
    np.testing.assert_array_equal(got.rgb[free], alone.rgb[free])
    np.testing.assert_array_equal(got.depth[free], alone.depth[free])
    e_rgb, _, e_alpha = composite_layers(a, alone)
    np.testing.assert_allclose(got.rgb, e_rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.alpha, e_alpha, atol=LAYERED_ATOL)
    # in the tiles the wall's edge crosses, the stopped rows are not evaluated (without the skip: as many rows as
    # when drawn alone, the tile's other rows still blending)
    ntx = -(-cam.width // K.TILE)
    mixed = [r * ntx + c for r in np.flatnonzero(tile_rows.any(axis=1) & ~tile_rows.all(axis=1)) for c in range(ntx)]
    assert (got.state.row_evals[mixed] <= alone.state.row_evals[mixed]).all()
    assert got.state.row_evals[mixed].sum() < 0.9 * alone.state.row_evals[mixed].sum()
    assert got.state.row_evals.sum() < alone.state.row_evals.sum()
