"""Gaussians.transformed (one numba pass) against transformed_reference (numpy): the same quaternions bit for bit,
the same means within a rounding, in float32 and float64; the refusals."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl.runtime.render import GaussianError, Gaussians
from xyzcyl.runtime.render.gaussians import transformed_reference
from xyzcyl.runtime.rotations import quat_to_rotmat


def _rigid(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(rng.normal(size=4))
    T[:3, 3] = rng.uniform(-300, 300, 3)
    return T


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_transformed_is_its_numpy_reference(dtype):
    rng = np.random.default_rng(3)
    g = random_gaussians(rng, 5000, lo=(-80, -80, -5), hi=(80, 80, 20)).astype(dtype)
    for _ in range(4):
        T = _rigid(rng)
        fast, ref = g.transformed(T), transformed_reference(g, T)
        assert fast.means.dtype == ref.means.dtype == dtype and fast.quats.dtype == dtype
        np.testing.assert_array_equal(fast.quats, ref.quats)     # the same float64 products, elementwise
        # numpy's matmul may add the three products and t in another order (or fused): the float64 sums differ
        # by a few roundings of their largest term (|R m| + |t|); stored as float32, one rounding step of the
        # result at most
        terms = np.abs(g.means.astype(np.float64)).sum(axis=1, keepdims=True) + np.abs(T[:3, 3]).max()
        err = np.abs(fast.means.astype(np.float64) - ref.means.astype(np.float64))
        assert (err <= 4 * np.finfo(np.float64).eps * terms
                + np.finfo(dtype).eps * np.abs(ref.means.astype(np.float64)) * (dtype == np.float32)).all()
        assert fast.log_scales is g.log_scales and fast.sh is g.sh   # shared, not copied
    back = g.transformed(T).transformed(np.linalg.inv(T))              # there and back
    np.testing.assert_allclose(back.means, g.means, atol=1e-3 if dtype == np.float32 else 1e-9)


def test_transformed_refuses_what_it_cannot_move():
    g = random_gaussians(np.random.default_rng(1), 10, lo=(-1, -1, -1), hi=(1, 1, 1))
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(GaussianError) as e:
        g.transformed(T)
    assert e.value.field == "means"
    T = np.eye(4)
    T[:3, :3] = np.nan
    with pytest.raises(GaussianError):
        g.transformed(T)
    sh1 = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.zeros((10, 4, 3), np.float32))
    with pytest.raises(GaussianError) as e:
        sh1.transformed(np.eye(4))
    assert e.value.field == "sh"
