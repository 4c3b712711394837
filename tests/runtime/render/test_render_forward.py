"""Fast renderer vs the per-pixel float64 reference, and analytic checks of the conventions."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from render_scenes import concat, look_at, pinhole, random_gaussians
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, RenderOptions, kernels, render, render_reference

# 1e-4: the fast path rasterises in float32 with a polynomial exp (relative error < 2e-6) and sums up to a
# few hundred float32 terms per pixel; the float64 reference differs by ~1e-6 typically. 1e-4 leaves room
# for accumulation but catches any real semantic difference (a single missed Gaussian is > 1/255 * 1e-2).
TOL = 1e-4
# depth is sum(w z)/alpha in metres: the same relative float32 error, scaled by the depth (up to ~40 m here).
DEPTH_REL = 1e-5


def _compare(g, cam, background=None, **options):
    fast = render(g, cam, background, **options)
    ref = render_reference(g, cam, background, **options)
    assert np.abs(fast.rgb - ref.rgb).max() <= TOL
    assert np.abs(fast.alpha - ref.alpha).max() <= TOL
    assert np.all(np.abs(fast.depth - ref.depth) <= TOL + DEPTH_REL * ref.depth)
    # where the reference saw nothing, the fast path must also see exactly nothing
    assert np.array_equal(fast.alpha == 0, ref.alpha == 0)
    return fast, ref


@pytest.mark.parametrize("seed", [0, 1])
def test_random_scene_matches_reference(seed):
    rng = np.random.default_rng(seed)
    g = random_gaussians(rng, 400, degree=seed * 3)
    fast, _ = _compare(g, pinhole(), background=(0.2, 0.3, 0.4))
    assert 0.3 < fast.alpha.mean() < 1.0  # the scene is not trivially empty


def test_rotated_camera_sh3_and_background_image():
    rng = np.random.default_rng(2)
    g = random_gaussians(rng, 300, lo=(-4, -4, -1), hi=(4, 4, 2), degree=3)
    cam = pinhole(70, 50, f=45.0, c2w=look_at((-9.0, 1.0, 2.5), (0.0, 0.0, 0.0)))
    bg = rng.uniform(0, 1, size=(50, 70, 3)).astype(np.float32)
    _compare(g, cam, background=bg)


@pytest.mark.parametrize("options", [dict(antialiased=True), dict(radius_mode="opacity"),
                                     dict(near=3.0, far=7.0, low_pass=0.1)])
def test_options_match_reference(options):
    g = random_gaussians(np.random.default_rng(3), 300)
    _compare(g, pinhole(), (1.0, 1.0, 1.0), **options)


def test_long_tile_lists_match_reference_and_do_not_depend_on_threads():
    """Hundreds of faint Gaussians per tile: more instances than one raster gather batch (kernels.GATHER),
    no early stop; the tile lists are built over one chunk per thread, so 1 and 2 threads must agree
    bit for bit."""
    rng = np.random.default_rng(7)
    g = random_gaussians(rng, 1500, lo=(-2, -1.5, 3), hi=(2, 1.5, 8), scale=(0.1, 0.4), opacity=(-5.0, -3.0))
    cam = pinhole(40, 30, f=30.0)
    fast, _ = _compare(g, cam, background=(0.1, 0.2, 0.3))
    starts = fast.state.start
    assert np.diff(starts).max() > 2 * kernels.GATHER
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = render(g, cam, (0.1, 0.2, 0.3))
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(one.state.ids, fast.state.ids)
    assert np.array_equal(one.rgb, fast.rgb) and np.array_equal(one.depth, fast.depth)


def test_structured_scene_tile_borders_behind_huge_tiny():
    rng = np.random.default_rng(4)
    cam = pinhole(83, 61, f=60.0, cx=41.0, cy=30.0)
    f, fy = 60.0, 63.0
    # means exactly on tile borders (pixel 15.5, 16, 31.5 ... in x and y) at several depths
    uv = np.array([(u, v) for u in (15.5, 16.0, 31.5, 47.75, 64.0) for v in (15.5, 16.0, 31.9, 47.5)])
    z = rng.uniform(3, 8, size=len(uv))
    borders = random_gaussians(rng, len(uv), scale=(0.02, 0.3))
    means = np.stack([(uv[:, 0] - 41.0) * z / f, (uv[:, 1] - 30.0) * z / fy, z], 1).astype(np.float32)
    borders = Gaussians(means, borders.quats, borders.log_scales, borders.opacity_logits, borders.sh)
    behind = random_gaussians(rng, 30, lo=(-3, -2, -6), hi=(3, 2, 0.005))     # behind / inside near plane
    huge = random_gaussians(rng, 3, lo=(-1, -1, 4), hi=(1, 1, 6), scale=(5.0, 30.0), opacity=(-2, -1))
    tiny = random_gaussians(rng, 50, scale=(1e-5, 1e-3), opacity=(2, 4))
    edge = random_gaussians(rng, 40, lo=(-12, -8, 2), hi=(12, 8, 6))          # many straddle the image edge
    _compare(concat(borders, behind, huge, tiny, edge), cam, (0.1, 0.5, 0.9))


def test_no_gaussians_gives_the_background():
    cam = pinhole()
    bg = np.random.default_rng(5).uniform(size=(61, 83, 3)).astype(np.float32)
    for g in (Gaussians.empty(), random_gaussians(np.random.default_rng(6), 20, lo=(-3, -2, -9), hi=(3, 2, -1))):
        res = render(g, cam, bg)
        assert np.array_equal(res.rgb, bg) and not res.alpha.any() and not res.depth.any()


def test_opaque_wall_stops_early_and_saturates():
    # 40 nearly opaque large Gaussians stacked: transmittance hits the 1e-4 stop; alpha = 1 - T, T > 1e-4.
    # Opacities stay below the 0.99 clamp: clamped alphas make T = 0.01^k land exactly on the 1e-4 stop,
    # where float32 and float64 legitimately decide differently.
    rng = np.random.default_rng(7)
    g = random_gaussians(rng, 40, lo=(-0.2, -0.2, 3), hi=(0.2, 0.2, 6), scale=(1.0, 2.0), opacity=(2.5, 3.5))
    fast, _ = _compare(g, pinhole(40, 30, f=30.0))
    assert fast.alpha[10:20, 15:25].min() > 0.99 and fast.alpha.max() < 1.0 - 1e-4 + 1e-7  # T stays > 1e-4


def test_single_gaussian_closed_form_and_pixel_convention():
    # isotropic Gaussian of sigma s at camera z = d on the optical axis: footprint centred at (cx, cy) exactly
    # (OpenCV convention: pixel (u, v) is evaluated at x = u), alpha = o exp(-r^2 / (2 (sigma_px^2 + 0.3))).
    s, d, f, o = 0.1, 5.0, 50.0, 0.8
    g = Gaussians(np.array([[0, 0, d]], np.float32), np.array([[1, 0, 0, 0]], np.float32),
                  np.full((1, 3), np.log(s), np.float32), np.array([np.log(o / (1 - o))], np.float32),
                  np.zeros((1, 1, 3), np.float32))
    cam = Camera(K=np.array([[f, 0, 20.0], [0, f, 13.0], [0, 0, 1]]), cam_to_ego=np.eye(4), width=41, height=27)
    var = (f * s / d) ** 2 + 0.3
    u, v = np.meshgrid(np.arange(41), np.arange(27))
    expect = o * np.exp(-((u - 20.0) ** 2 + (v - 13.0) ** 2) / (2 * var))
    expect = np.where((expect >= 1 / 255) & (((u - 20.0) ** 2 + (v - 13.0) ** 2) / var <= 9), expect, 0)
    for res in (render(g, cam), render_reference(g, cam)):
        assert np.abs(res.alpha - expect).max() < 1e-5  # float32 evaluation of the same closed form
        assert np.unravel_index(np.argmax(res.alpha), res.alpha.shape) == (13, 20)
        assert np.allclose(res.depth[res.alpha > 0], d, atol=1e-5)
        assert np.allclose(res.rgb, 0.5 * res.alpha[..., None], atol=1e-5)  # dc = 0 -> colour 0.5


def test_equirect_matches_reference_across_the_seam_and_poles():
    rng = np.random.default_rng(8)
    all_round = random_gaussians(rng, 300, lo=(-8, -3, -8), hi=(8, 3, 8), scale=(0.1, 0.8))
    seam = random_gaussians(rng, 20, lo=(-0.3, -1, -6), hi=(0.3, 1, -3), scale=(0.2, 0.5))  # straight behind
    poles = random_gaussians(rng, 10, lo=(-0.2, -6, -0.2), hi=(0.2, 6, 0.2), scale=(0.1, 0.4))
    g = concat(all_round, seam, poles)
    cam = Camera(model="equirectangular", cam_to_ego=np.eye(4), width=96, height=48)
    _compare(g, cam, (0.0, 0.2, 0.1))
    # a Gaussian straight behind the camera shows on both the first and the last columns
    behind = Gaussians(np.array([[0, 0, -4]], np.float32), np.array([[1, 0, 0, 0]], np.float32),
                       np.full((1, 3), np.log(0.3), np.float32), np.array([2.0], np.float32),
                       np.zeros((1, 1, 3), np.float32))
    res = render(behind, cam)
    assert res.alpha[24, 0] > 0.5 and np.isclose(res.alpha[24, 0], res.alpha[24, 95], atol=1e-5)


def test_equirect_pixel_convention():
    # forward (+z) -> u = (W-1)/2, right (+x) -> u = 3W/4 - 0.5, up (-y) -> top rows, horizon -> v = (H-1)/2
    W, H = 64, 32
    cam = Camera(model="equirectangular", cam_to_ego=np.eye(4), width=W, height=H)
    pts = {"fwd": ((0, 0, 5), (H / 2 - 0.5, W / 2 - 0.5)), "right": ((5, 0, 0), (H / 2 - 0.5, 3 * W / 4 - 0.5))}
    for name, (p, (v0, u0)) in pts.items():
        g = Gaussians(np.array([p], np.float32), np.array([[1, 0, 0, 0]], np.float32),
                      np.full((1, 3), np.log(0.02), np.float32), np.array([3.0], np.float32),
                      np.zeros((1, 1, 3), np.float32))
        a = render(g, cam).alpha
        vs, us = np.nonzero(a > 0)
        w = a[vs, us]
        assert abs((w * us).sum() / w.sum() - u0) < 1e-3, name  # symmetric footprint centred on u0
        assert abs((w * vs).sum() / w.sum() - v0) < 1e-3, name
    up = Gaussians(np.array([[0.5, -5, 0]], np.float32), np.array([[1, 0, 0, 0]], np.float32),
                   np.full((1, 3), np.log(0.2), np.float32), np.array([3.0], np.float32),
                   np.zeros((1, 1, 3), np.float32))
    assert render(up, cam).alpha[:3].sum() > 0 and render(up, cam).alpha[H // 2:].sum() == 0


def test_bad_inputs_name_the_field():
    g = random_gaussians(np.random.default_rng(9), 5)
    with pytest.raises(ValueError, match="background"):
        render(g, pinhole(), background=np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="radius_mode"):
        render(g, pinhole(), radius_mode="5sigma")
    with pytest.raises(ValueError, match="bogus"):
        render(g, pinhole(), bogus=1)
    with pytest.raises(ValueError, match="K"):
        Camera(K=np.eye(3) * -1, cam_to_ego=np.eye(4), width=10, height=10)
    with pytest.raises(ValueError, match="cam_to_ego"):
        Camera(K=np.eye(3), cam_to_ego=np.diag([1, 1, 2, 1.0]), width=10, height=10)
    assert RenderOptions().near == 0.01


def test_concurrent_renders_from_threads_equal_sequential_renders():
    """The kernels release the GIL (nogil) so the server renders in several threads at once: results must not
    depend on that (no shared scratch state between calls)."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(7)
    g = random_gaussians(rng, 3000)
    cams = [pinhole(97, 71, c2w=look_at((0.3 * k, 0.2, -1.0), (0, 0, 6))) for k in range(6)]
    seq = [render(g, c) for c in cams]
    with ThreadPoolExecutor(4) as ex:
        par = list(ex.map(lambda c: render(g, c), cams * 3))
    for i, r in enumerate(par):
        s = seq[i % len(cams)]
        # exact: the same kernels on the same inputs; threads only interleave whole calls
        np.testing.assert_array_equal(r.rgb, s.rgb)
        np.testing.assert_array_equal(r.depth, s.depth)


def _chunk_clusters(rng, n: int, depth, u_range, v_range, centre_px, f: float, spread_max: float,
                    big: tuple[float, float]) -> Gaussians:
    """n clusters of kernels.PROJ_CHUNK Gaussians each (one projection chunk apiece): cluster k around the point at
    depth ``depth()`` (metres, camera z) seen at a pixel uniform in u_range x v_range (principal point
    ``centre_px``, focal f), a cube of half-side up to spread_max; small scales for odd k, ``big`` for even."""
    parts = []
    for k in range(n):
        z = depth()
        u, v = rng.uniform(*u_range), rng.uniform(*v_range)
        centre = np.array([(u - centre_px[0]) * abs(z) / f, (v - centre_px[1]) * abs(z) / f, z])
        spread = rng.uniform(0.01, spread_max)
        parts.append(random_gaussians(rng, kernels.PROJ_CHUNK, lo=tuple(centre - spread), hi=tuple(centre + spread),
                                      scale=(0.003, 0.03) if k % 2 else big, opacity=(-2.0, 3.0)))
    return concat(*parts)


def test_chunk_culling_skips_only_chunks_that_would_be_culled_anyway():
    """The projection skips a chunk of kernels.PROJ_CHUNK Gaussians whose bounding box lies outside the camera's
    frustum planes (core.chunk_planes). Clusters of one chunk each are placed around the image edges (inside,
    just outside by a few footprints, far outside, behind the camera, beyond far), with small and large scales:
    the projection with the chunk test must write exactly what the projection without it writes, and render
    the same picture bit for bit."""
    from xyzcyl.runtime.render import core
    from xyzcyl.runtime.render.projection import RenderOptions as Opts

    rng = np.random.default_rng(11)
    cam = pinhole(83, 61, f=60.0)
    opts = Opts(far=30.0)
    c = kernels.PROJ_CHUNK
    # pixels: the image is 0..82 x 0..60, so many clusters straddle or miss it
    g = _chunk_clusters(rng, 48, lambda: rng.choice([rng.uniform(-3.0, 0.5), rng.uniform(1.0, 25.0),
                                                     rng.uniform(28.0, 40.0)], p=[0.2, 0.6, 0.2]),
                        (-60.0, 143.0), (-50.0, 111.0), (41.3, 30.3), 60.0, 0.6, (0.05, 0.4))
    a = core._prepare(g, cam, opts, cull_chunks=False)
    b = core._prepare(g, cam, opts, cull_chunks=True)
    planes = core.chunk_planes(cam, opts)
    skipped = [k for k in range(48) if kernels._chunk_outside(g.means, g.log_scales, planes, k * c, (k + 1) * c)]
    visible_chunks = set(np.unique(a[4][np.unique(a[2])] // c))
    assert 8 <= len(skipped) <= 40                # the scene exercises both outcomes
    assert not visible_chunks & set(skipped)      # a skipped chunk had no visible Gaussian
    assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])    # tile starts and lists
    used = np.unique(a[2])
    assert np.array_equal(a[3][used], b[3][used]) and np.array_equal(a[4][used], b[4][used])  # rows, slot->id
    fast = render(g, cam, (0.1, 0.2, 0.3), far=30.0)
    ref = render_reference(g, cam, (0.1, 0.2, 0.3), far=30.0)
    assert np.abs(fast.rgb - ref.rgb).max() <= TOL


def test_a_chunk_over_covered_tiles_only_is_skipped_and_no_gaussian_it_held_reaches_an_open_tile():
    """kernels._chunk_closed (a later layer's run of PROJ_CHUNK Gaussians whose box falls on tiles the layers in
    front covered): clusters in front of, across and beside the image, half the tiles covered (a block and a
    checkerboard corner); every chunk it skips lists none of its Gaussians in an open tile of the projection
    without cover (what the per-Gaussian test would keep); it skips some, and the covered projection lists the
    same Gaussians in the open tiles as the projection without cover."""
    from xyzcyl.runtime.render import core
    from xyzcyl.runtime.render.projection import RenderOptions as Opts

    rng = np.random.default_rng(5)
    cam = pinhole(160, 96, f=90.0)
    opts = Opts(far=60.0)
    c = kernels.PROJ_CHUNK
    g = _chunk_clusters(rng, 64, lambda: rng.choice([rng.uniform(0.05, 0.5), rng.uniform(1.0, 40.0)], p=[0.1, 0.9]),
                        (-40.0, 200.0), (-30.0, 126.0), (79.5, 47.5), 90.0, 0.4, (0.03, 0.2))
    ntx, nty = 10, 6
    covered = np.zeros((nty, ntx), bool)
    covered[:, :6] = True                            # the left 96 px
    covered[3:, 6:] = (np.add.outer(np.arange(3), np.arange(4)) % 2).astype(bool)
    covered = covered.ravel()
    sat = np.zeros((nty + 1, ntx + 1), np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(~covered.reshape(nty, ntx), axis=0), axis=1)
    model, (*cargs, ptab) = core._camera_args(cam)
    Rw, tw, lp, fx, fy, cx, cy, lxn, lxp, lyn, lyp = cargs
    closed = [k for k in range(64) if kernels._chunk_closed(g.means, g.log_scales, k * c, (k + 1) * c, Rw, tw, fx, fy,
                                                            cx, cy, lxn, lxp, lyn, lyp, 160, 96, opts.near,
                                                            opts.low_pass, sat)]
    _, start, ids, _, gid, _ = core._prepare(g, cam, opts)
    reach = set()                                    # chunks with a Gaussian listed in an open tile
    for t in np.flatnonzero(~covered):
        reach |= set((gid[ids[start[t]:start[t + 1]]] // c).tolist())
    assert 8 <= len(closed) <= 48, len(closed)       # both outcomes exercised
    assert not reach & set(closed)
    _, start2, ids2, _, gid2, _ = core._prepare(g, cam, opts, covered=covered)
    for t in np.flatnonzero(~covered):
        np.testing.assert_array_equal(gid2[ids2[start2[t]:start2[t + 1]]], gid[ids[start[t]:start[t + 1]]])


def test_ellipse_rows_cover_every_pixel_the_footprint_reaches():
    """kernels._ellipse_rows narrows a tile instance's rows to where its footprint ellipse meets the tile's
    columns. Against brute force on the 16x16 pixel centres: never a row with a pixel inside the ellipse left out
    (that pixel would lose the Gaussian), and tight: the first and last rows hold a pixel inside, but where the
    ellipse's chord on such a row falls between pixel centres."""
    ellipse_rows = numba.njit(lambda A, B, C, pm, mx, my, r0, r1: kernels._ellipse_rows(A, B, C, pm, mx, my, r0, r1))
    rng = np.random.default_rng(5)
    grid = np.arange(float(kernels.TILE))
    narrowed = missed = tight = cases = 0
    for _ in range(3000):
        m = rng.normal(size=(2, 2)) * rng.uniform(0.3, 6.0)
        cov = m @ m.T + 0.3 * np.eye(2)
        con = np.linalg.inv(cov)
        A, B, C, pm = con[0, 0] / 2, con[0, 1], con[1, 1] / 2, rng.uniform(2.0, 5.6)
        mx, my = rng.uniform(-12.0, 27.0, 2)
        ry = np.sqrt(2 * pm * cov[1, 1]) + kernels.ROW_PAD
        r0, r1 = max(0.0, np.floor(my - ry)), min(15.0, np.ceil(my + ry))
        if r0 > r1:
            continue
        a, b = ellipse_rows(A, B, C, pm, mx, my, r0, r1)
        dx, dy = grid[None, :] - mx, grid[:, None] - my
        rows = np.flatnonzero(((A * dx + B * dy) * dx + C * dy * dy <= pm).any(axis=1))
        if rows.size:
            assert a <= rows.min() and rows.max() <= b
            tight += (a, b) == (rows.min(), rows.max())
        else:
            tight += a > b
        cases += 1
        missed += rows.size == 0 and a > b
        narrowed += (b - a) < (r1 - r0)
    assert narrowed > 300 and missed > 100    # the narrowing happens (cases where the bounding box is loose)
    # loose only where a row's chord of the ellipse holds no pixel centre (measured: 138 of 15,689 cases)
    assert tight >= 0.95 * cases


def test_depth_order_is_a_stable_sort_by_key():
    """kernels.depth_order (three radix passes) against numpy's stable sort: random float32 depths with many
    exact ties, a pass whose digit all keys share (depths within one binade), and the empty list."""
    rng = np.random.default_rng(9)
    for depths in (rng.choice(rng.uniform(0.01, 500.0, 300).astype(np.float32), 20_000),
                   rng.uniform(4.0, 7.9, 5000).astype(np.float32), np.zeros(0, np.float32)):
        slots = np.sort(rng.choice(10 * max(len(depths), 1), len(depths), replace=False)).astype(np.int32)
        keys = depths.view(np.uint32)
        expected = slots[np.argsort(depths, kind="stable")]
        assert np.array_equal(kernels.depth_order(slots, keys), expected)


def test_scratch_buffers_are_reused_only_when_nothing_holds_them():
    """core._scratch hands a render its buffers from a per-thread pool. A RenderResult whose state is still
    held keeps its buffers: the next render must not write into them (its picture and state stay intact)."""
    from xyzcyl.runtime.render import core

    a = core._scratch("test", (100, 16), np.float32)
    assert a.ctypes.data % 64 == 0 and a.shape == (100, 16)
    a_ptr = a.ctypes.data
    b = core._scratch("test", (50, 16), np.float32)                 # `a` is held: a new buffer
    assert b.ctypes.data != a_ptr
    del a, b
    c = core._scratch("test", (80, 16), np.float32)                 # free and big enough: reused
    assert c.base is core._POOL.__dict__["test"]
    del c
    rng = np.random.default_rng(12)
    g1, g2 = random_gaussians(rng, 300), random_gaussians(rng, 300)
    cam = pinhole()
    first = render(g1, cam)
    kept = (first.rgb.copy(), first.state.rows.copy(), first.state.last.copy(), first.state.t_final.copy())
    render(g2, cam)                                                  # while `first` is alive
    assert np.array_equal(first.rgb, kept[0]) and np.array_equal(first.state.rows, kept[1])
    assert np.array_equal(first.state.last, kept[2]) and np.array_equal(first.state.t_final, kept[3])
    again = render(g1, cam)
    assert np.array_equal(again.rgb, first.rgb)
