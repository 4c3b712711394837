"""The pre-cull's boxes made once a set (kernels.sub_boxes, Gaussians.box_grid): a drive's later layers read each
run's box instead of its means, and a slice draws with its parent's boxes; the verdicts, and so the pictures, are
the ones made from the means."""

from __future__ import annotations

import pickle

import numpy as np
from render_scenes import pinhole, random_gaussians
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.render import kernels as K
from xyzcyl.runtime.render.core import _camera_args, chunk_planes
from xyzcyl.runtime.render.projection import RenderOptions


def _clustered(rng, n):
    """Random Gaussians sorted along x, so that runs of SUB_CHUNK are small boxes (as a drive's spatial order
    makes them) that can fall on covered tiles alone."""
    g = random_gaussians(rng, n, lo=(-6, -2, 3), hi=(6, 2, 9), scale=(0.01, 0.05))
    return g.subset(np.argsort(g.means[:, 0], kind="stable"))


def _copy(g: Gaussians) -> Gaussians:
    """The same Gaussians in arrays of their own (no parent: boxes made from their means)."""
    return Gaussians(*(np.array(getattr(g, f)) for f in ("means", "quats", "log_scales", "opacity_logits", "sh")))


def test_sub_boxes_are_each_runs_box():
    g = random_gaussians(np.random.default_rng(1), 3 * K.SUB_CHUNK + 41)
    boxes = K.sub_boxes(g.means, g.log_scales)
    assert boxes.shape == (4, 7) and boxes.dtype == np.float64
    for j in range(4):
        m = g.means[j * K.SUB_CHUNK:(j + 1) * K.SUB_CHUNK].astype(np.float64)
        ls = g.log_scales[j * K.SUB_CHUNK:(j + 1) * K.SUB_CHUNK].astype(np.float64)
        expect = [m[:, 0].min(), m[:, 0].max(), m[:, 1].min(), m[:, 1].max(), m[:, 2].min(), m[:, 2].max(), ls.max()]
        np.testing.assert_array_equal(boxes[j], expect)     # min and max of float32 values: exact
    assert K.sub_boxes(g.means[:0], g.log_scales[:0]).shape == (0, 7)


def test_other_opacities_keep_the_sets_boxes():
    g = random_gaussians(np.random.default_rng(4), 3 * K.SUB_CHUNK)
    grid, phase = g.box_grid()
    other = g.with_opacity_logits(np.zeros(len(g), np.float32))
    assert other.box_grid()[0] is grid and other.box_grid()[1] == phase == 0
    np.testing.assert_array_equal(grid, K.sub_boxes(other.means, other.log_scales))


def _precull(g, cam, sat, boxes, phase):
    opts = RenderOptions()
    model, (*cargs, ptab) = _camera_args(cam)
    camt = (*cargs, cam.width, cam.height, float(opts.near), float(opts.far), float(opts.low_pass))
    nch = (len(g) + K.PROJ_CHUNK - 1) // K.PROJ_CHUNK
    pre, keep = np.zeros(nch, np.int64), np.full(len(g), 7, np.uint8)    # 7: left unwritten (a chunk skipped whole)
    K.precull_counts(model)(g.means, g.log_scales, camt, ptab, chunk_planes(cam, opts), sat, boxes, phase, pre,
                            keep)
    for c in range(nch):            # a chunk counted 0 without a look leaves its verdicts unwritten
        if pre[c] == 0:
            keep[c * K.PROJ_CHUNK:(c + 1) * K.PROJ_CHUNK] = 0
    return pre, keep


def test_precull_with_boxes_gives_the_verdicts_made_from_the_means():
    rng = np.random.default_rng(2)
    g = _clustered(rng, 5 * K.PROJ_CHUNK + 333)
    cam = pinhole(width=160, height=96, f=90.0)
    ntx, nty = -(-cam.width // K.TILE), -(-cam.height // K.TILE)
    covered = np.zeros((nty, ntx), bool)
    covered[:, : ntx * 2 // 3] = True               # the left two thirds covered: runs there close
    sat = np.zeros((nty + 1, ntx + 1), np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(~covered, axis=0), axis=1)
    nothing = np.zeros((0, 7))
    grid, phase = g.box_grid()
    assert phase == 0 and grid.shape == (-(-len(g) // K.SUB_CHUNK), 7)
    for s in (np.zeros((0, 0), np.int64), sat):
        for a, b in ((0, len(g)), (189, len(g) - 5), (K.SUB_CHUNK, 3 * K.PROJ_CHUNK + 1), (1000, 1001)):
            part = g.slice(a, b)
            boxes, ph = part.box_grid()
            assert boxes is grid and ph == a            # the parent's boxes, at the slice's first row
            pre, keep = _precull(part, cam, s, boxes, ph)
            pre0, keep0 = _precull(_copy(part), cam, s, nothing, 0)
            assert set(pickle.loads(pickle.dumps(part)).__dict__) == set(vars(_copy(part)))  # no parent, no boxes
            np.testing.assert_array_equal(pre, pre0)
            np.testing.assert_array_equal(keep, keep0)
    # the covered tiles close most runs, and the boxes are what decides it: boxes said to lie on the covered side
    # drop Gaussians that stand in the open tiles
    pre, keep = _precull(g, cam, sat, grid, 0)
    assert 0 < keep.sum() < len(g) // 2
    wrong = grid.copy()
    wrong[:, 0:2] = grid[:, 0:2].min()              # every box squeezed to the left edge's x
    assert _precull(g, cam, sat, wrong, 0)[1].sum() < keep.sum()


def test_a_slice_draws_as_a_copy_of_its_rows_behind_a_layer():
    rng = np.random.default_rng(3)
    front = random_gaussians(rng, 300, lo=(-3, -2, 2), hi=(0.5, 2, 3), scale=(0.1, 0.3), opacity=(3.0, 6.0))
    g = _clustered(rng, 4 * K.PROJ_CHUNK + 77)
    cam = pinhole(width=160, height=96, f=90.0)
    for a, b in ((0, len(g)), (61, len(g) - 200)):
        got = render(g.slice(a, b), cam, background=(0.2, 0.5, 0.9), behind=render(front, cam), cover=0.05)
        plain = render(_copy(g.slice(a, b)), cam, background=(0.2, 0.5, 0.9), behind=render(front, cam), cover=0.05)
        assert got.state.finished.any()             # some tiles covered: the boxes close runs there
        for x, y in ((got.rgb, plain.rgb), (got.alpha, plain.alpha), (got.depth, plain.depth)):
            np.testing.assert_array_equal(x, y)
