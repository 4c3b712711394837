"""The renderer takes several Gaussian sets and draws them as their concatenation without copying them, and draws a
set behind an earlier result (``behind``): what a drive's layered view (runtime.scene.Scene._layers) is made of."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from render_scenes import pinhole, random_gaussians
from xyzcyl.runtime.detail import concat_gaussians as concat
from xyzcyl.runtime.render import Gaussians, render, render_backward
from xyzcyl.runtime.render import kernels as K
from xyzcyl.runtime.render.core import _prepare
from xyzcyl.runtime.render.projection import RenderOptions
from xyzcyl.runtime.render.result import RenderResult
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


def test_tiles_the_layers_in_front_cover_are_finished_as_they_drew_them():
    """render(..., behind=a, cover=c): a tile where a left no pixel more than c of its light is a's alone, its colour
    and depth divided by its alpha (alpha 1), and none of the set behind is drawn there; every other tile is the
    composite as before. Checked against composite_layers(..., cover=c), the reference, for two layers behind a
    half-transparent wall (each pixel of it keeps ~4 % of its light, as a drive's detail cells do) whose edge
    crosses tiles."""
    ys, xs = np.meshgrid(np.arange(-1.6, 0.21, 0.05), np.arange(-2.2, 2.21, 0.05), indexing="ij")
    means = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1).astype(np.float32)
    n = len(means)
    rng = np.random.default_rng(5)
    wall = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), np.log(0.03), np.float32),
                     np.full(n, 1.2, np.float32), rng.uniform(-0.5, 0.5, (n, 1, 3)).astype(np.float32))
    mid = random_gaussians(rng, 500, lo=(-3, -2, 5), hi=(3, 2, 7))
    back = random_gaussians(rng, 500, lo=(-3, -2, 8), hi=(3, 2, 12))
    cam = pinhole()
    a = render(wall, cam)
    left = 1.0 - a.alpha
    assert 0.01 < np.median(left[left < 0.5]) < 0.1        # the wall: a few % of the light left, not opaque
    cover = 0.1
    b = render(mid, cam, behind=render(wall, cam), cover=cover)
    got = render(back, cam, background=(0.2, 0.5, 0.9), behind=b, cover=cover)
    e_rgb, e_depth, e_alpha = composite_layers(a, render(mid, cam), render(back, cam, background=(0.2, 0.5, 0.9)),
                                               cover=cover)
    np.testing.assert_allclose(got.rgb, e_rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.alpha, e_alpha, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.depth, e_depth, atol=LAYERED_ATOL * 10)    # metres, as above
    # the covered tiles: a's pixels renormalised exactly (float32 division), nothing behind drawn there
    th, tw = cam.height // K.TILE, cam.width // K.TILE
    covered = (left[: th * K.TILE, : tw * K.TILE].reshape(th, K.TILE, tw, K.TILE).max(axis=(1, 3)) <= cover)
    assert 0.1 < covered.mean() < 0.9                       # some tiles covered, some not
    px = np.repeat(np.repeat(covered, K.TILE, 0), K.TILE, 1)
    H, W = px.shape
    np.testing.assert_allclose(got.rgb[:H, :W][px], a.rgb[:H, :W][px] / a.alpha[:H, :W][px][:, None], rtol=1e-6)
    assert (got.alpha[:H, :W][px] == 1).all()
    np.testing.assert_array_equal(got.depth[:H, :W][px], a.depth[:H, :W][px])
    assert (got.state.row_evals.reshape(-1)[: th * tw].reshape(th, -1)[:, :tw][covered] == 0).all()
    # the tiles the layer in front finished (its state's finished: alpha 1 throughout) are left as they are, not
    # finished again: the same pixels as behind a copy of b that does not say so, and still finished after
    assert b.state.finished is not None and b.state.finished.any() and not b.state.finished.all()
    plain = RenderResult(b.rgb, b.alpha, b.depth, dataclasses.replace(b.state, finished=None))
    again = render(back, cam, background=(0.2, 0.5, 0.9), behind=plain, cover=cover)
    for x, y in ((got.rgb, again.rgb), (got.alpha, again.alpha), (got.depth, again.depth)):
        np.testing.assert_array_equal(x, y)
    assert (got.state.finished >= b.state.finished).all()
    # elsewhere (one layer behind the wall) what the exact composite gives: the light the wall leaves shows what
    # lies behind
    one = render(back, cam, background=(0.2, 0.5, 0.9), behind=render(wall, cam), cover=cover)
    exact = render(back, cam, background=(0.2, 0.5, 0.9), behind=render(wall, cam))
    np.testing.assert_array_equal(one.rgb[:H, :W][~px], exact.rgb[:H, :W][~px])
    np.testing.assert_array_equal(one.rgb[:H, :W][px], got.rgb[:H, :W][px])
    assert np.abs(exact.rgb[:H, :W][px] - one.rgb[:H, :W][px]).max() > 1e-3     # the rule changed those pixels
    with pytest.raises(ValueError, match="cover"):
        render(back, cam, behind=a, cover=1.0)
    # the Gaussians that touch only covered tiles are not sorted or binned (kernels.open_slots): every open tile
    # lists the same Gaussians in the same order as without the cull, and fewer instances are made in all
    ntx, nty = -(-cam.width // K.TILE), -(-cam.height // K.TILE)
    tiles = K.covered_tiles(a.alpha, ntx, nty, np.float32(cover), np.zeros(0, bool))
    assert tiles.any() and not tiles.all()
    culled, whole = _prepare(back, cam, RenderOptions(), covered=tiles), _prepare(back, cam, RenderOptions())
    for t in np.flatnonzero(~tiles):
        np.testing.assert_array_equal(culled[4][culled[2][culled[1][t]:culled[1][t + 1]]],
                                      whole[4][whole[2][whole[1][t]:whole[1][t + 1]]])
    assert len(culled[2]) < len(whole[2])
    assert len(culled[3]) < len(whole[3])       # a pinhole's pre-cull: fewer Gaussians projected (kernels._precull)


def test_covered_tiles_of_an_equirect_view_across_its_seam():
    """render's cover in a panorama: the front layer a shell around the camera on one side only (its x > -1 part:
    the seam at azimuth 180 degrees, behind, stays open); the Gaussians behind it whose tile range wraps the seam are
    kept where they touch an open tile (kernels.open_slots, both pieces), and the view equals the reference."""
    from render_scenes import sphere_shell
    from xyzcyl.runtime.camera import Camera

    rng = np.random.default_rng(8)
    shell = sphere_shell(3.0, (0, 0, 0), 60, rng)
    front = shell.subset(shell.means[:, 0] > -1.0)
    back = sphere_shell(8.0, (0, 0, 0), 40, rng)
    cam = Camera(model="equirectangular", cam_to_ego=np.eye(4), width=192, height=96)
    a = render(front, cam)
    cover = 0.1
    got = render(back, cam, background=(0.2, 0.5, 0.9), behind=render(front, cam), cover=cover)
    e_rgb, _, e_alpha = composite_layers(a, render(back, cam, background=(0.2, 0.5, 0.9)), cover=cover)
    np.testing.assert_allclose(got.rgb, e_rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(got.alpha, e_alpha, atol=LAYERED_ATOL)
    ntx, nty = -(-cam.width // K.TILE), -(-cam.height // K.TILE)
    tiles = K.covered_tiles(a.alpha, ntx, nty, np.float32(cover), np.zeros(0, bool))
    assert 0.2 < tiles.mean() < 0.8
    culled, whole = _prepare(back, cam, RenderOptions(), covered=tiles), _prepare(back, cam, RenderOptions())
    ids_in = [set(culled[4][culled[2][culled[1][t]:culled[1][t + 1]]].tolist()) for t in range(ntx * nty)]
    col = [set().union(*(ids_in[r * ntx + c] for r in range(nty))) for c in (0, ntx - 1)]
    assert col[0] & col[1]                  # Gaussians whose footprint wraps the seam, kept
    for t in np.flatnonzero(~tiles):
        np.testing.assert_array_equal(culled[4][culled[2][culled[1][t]:culled[1][t + 1]]],
                                      whole[4][whole[2][whole[1][t]:whole[1][t + 1]]])
    assert len(culled[2]) < len(whole[2])


def test_a_render_without_background_shares_one_black_image_and_draws_as_with_black():
    """background=None: one [H, W, 3] zeros per size shared by the renders (core._black; a drive view's layers draw
    with none), never written, and the same pixels as an explicit black; a later layer's check that the one in
    front had no background still refuses one that had."""
    rng = np.random.default_rng(4)
    g = random_gaussians(rng, 400)
    cam = pinhole(width=83, height=61)
    a, b = render(g, cam), render(g, cam, background=(0.0, 0.0, 0.0))
    for x, y in ((a.rgb, b.rgb), (a.alpha, b.alpha), (a.depth, b.depth)):
        np.testing.assert_array_equal(x, y)
    c = render(g, cam)
    assert c.state.bg is a.state.bg and not a.state.bg.any()
    assert render(g, pinhole(width=84, height=61)).state.bg is not a.state.bg
    behind = render(g, cam, behind=c, behind_inplace=True)       # behind a shared black one: allowed
    assert behind.rgb is c.rgb and not a.state.bg.any()          # drawn into c's arrays; the black image untouched
    with pytest.raises(ValueError, match="no background"):
        render(g, cam, behind=render(g, cam, background=(0.5, 0.5, 0.5)))
