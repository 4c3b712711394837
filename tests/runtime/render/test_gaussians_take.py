"""Gaussians.subset / take_rows (one numba kernel over the rows) against numpy's indexing: the same arrays bit for
bit for masks and row lists above the kernel's threshold, every field and dtype; what goes to numpy still answers
as numpy does (its errors included)."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.render.gaussians import FIELDS, TAKE_ROWS_MIN, take_rows


def _big(rng, dtype=np.float32, sh_degree: int = 0) -> Gaussians:
    n = 3 * TAKE_ROWS_MIN
    g = random_gaussians(rng, n, lo=(-50, -50, -2), hi=(50, 50, 10)).astype(dtype)
    sh = rng.normal(size=(n, (sh_degree + 1) ** 2, 3)).astype(dtype)
    return Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh)


@pytest.mark.parametrize("dtype,sh_degree", [(np.float32, 0), (np.float32, 2), (np.float64, 1)])
def test_subset_is_numpy_indexing(dtype, sh_degree):
    rng = np.random.default_rng(5)
    g = _big(rng, dtype, sh_degree)
    mask = rng.random(len(g)) < 0.6
    rows = rng.integers(0, len(g), 2 * TAKE_ROWS_MIN)            # repeats and any order, as numpy takes them
    for index in (mask, rows, rows.astype(np.int32), np.flatnonzero(mask)):
        got = g.subset(index)
        for name in FIELDS:
            want = getattr(g, name)[index]
            a = getattr(got, name)
            assert a.dtype == want.dtype and a.shape == want.shape, name
            np.testing.assert_array_equal(a, want, err_msg=name)   # a copy of the same bits: exact
            assert not np.shares_memory(a, getattr(g, name))


def test_take_rows_kernel_is_used_and_copies():
    # the kernel path (enough rows, contiguous arrays) writes fresh arrays: a later write to the source leaves them
    rng = np.random.default_rng(6)
    a = rng.normal(size=(4 * TAKE_ROWS_MIN, 3)).astype(np.float32)
    b = rng.normal(size=4 * TAKE_ROWS_MIN)
    mask = np.ones(len(a), bool)
    mask[::3] = False
    ta, tb = take_rows([a, b], mask)
    want_a, want_b = a[mask].copy(), b[mask].copy()
    a[:] = 0.0
    np.testing.assert_array_equal(ta, want_a)
    np.testing.assert_array_equal(tb, want_b)


def test_what_numpy_indexes_goes_to_numpy():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(2 * TAKE_ROWS_MIN, 3)).astype(np.float32)
    neg = -np.arange(1, TAKE_ROWS_MIN + 2)                         # negative rows: numpy's meaning (from the end)
    np.testing.assert_array_equal(take_rows([a], neg)[0], a[neg])
    strided = a[:, ::2]                                              # not C-contiguous
    m = rng.random(len(a)) < 0.9
    np.testing.assert_array_equal(take_rows([strided], m)[0], strided[m])
    few = np.array([3, 1, 4])
    np.testing.assert_array_equal(take_rows([a], few)[0], a[few])
    with pytest.raises(IndexError):                                 # a row past the end: numpy's error
        take_rows([a], np.arange(len(a) + 1))
    with pytest.raises(IndexError):                                 # a mask of another length: numpy's error
        take_rows([a], np.ones(len(a) + 1, bool))
    assert take_rows([a], np.zeros(0, np.int64))[0].shape == (0, 3)
