"""The ground under a moving object that no frame saw is filled (runtime.groundfill.fill_under): exactly where no
static Gaussian lies on the ground, with the surrounding road's colour, its area counted per object."""

from __future__ import annotations

import numpy as np
from xyzcyl.testing.drives import pose as _pose


def _ground(hole: tuple[float, float, float, float] | None, dc=(0.2, -0.1, 0.3), step: float = 0.1,
            z: float = 0.0):
    """Static Gaussians every ``step`` metres on the plane z over x, y in [-10, 10], except inside ``hole``
    (x0, x1, y0, y1), with SH DC ``dc``; plus a roof of a different colour 1.5 m above the hole."""
    from xyzcyl.runtime.render import Gaussians

    g = np.arange(-10, 10, step) + step / 2
    x, y = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    keep = np.ones(len(x), bool) if hole is None else ~((x > hole[0]) & (x < hole[1]) & (y > hole[2]) & (y < hole[3]))
    pts = np.column_stack([x[keep], y[keep], np.full(keep.sum(), z)])
    roof = np.array([[(hole or (0, 0, 0, 0))[0] + 0.5, 0.0, z + 1.5]])
    means = np.concatenate([pts, roof]).astype(np.float32)
    n = len(means)
    sh = np.tile(np.float32(dc), (n, 1))
    sh[-1] = (-1.0, 1.0, -1.0)
    return Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), -3.0, np.float32),
                     np.zeros(n, np.float32), sh[:, None, :])


def test_the_hole_a_car_left_is_filled_with_the_roads_colour():
    from xyzcyl.runtime.groundfill import FILL_SPACING_M, GROW_M, fill_under

    size = np.array([4.0, 2.0, 1.5])
    T = np.array(_pose(1.0, 2.0), float)
    T[2, 3] = 0.75                                  # the box's centre half its height above the ground
    # no frame saw 3 x 1.6 m of the ground under the car (inside its footprint): filled, nothing else
    fill, area = fill_under(_ground((-0.5, 2.5, 1.2, 2.8)), [(1, T, size)], 3)
    assert area[0] == 0 and area[2] == 0
    # the lattice's cells whose 3 x 3 neighbourhood holds no ground Gaussian: the hole less one cell on each side
    # (0.2 m), give or take a cell along each edge (the lattice is not aligned with the hole)
    inner = (3.0 - 2 * FILL_SPACING_M) * (1.6 - 2 * FILL_SPACING_M)
    assert abs(area[1] - inner) <= 2 * FILL_SPACING_M * (3.0 + 1.6), area
    assert len(fill) == round(area[1] / FILL_SPACING_M ** 2)
    np.testing.assert_allclose(fill.means[:, 2], 0.0, atol=1e-6)                  # on the box's bottom face
    assert np.all((fill.means[:, 0] > -0.5) & (fill.means[:, 0] < 2.5))
    assert np.all((fill.means[:, 1] > 1.2) & (fill.means[:, 1] < 2.8))
    np.testing.assert_allclose(fill.sh[:, 0, :], np.tile([0.2, -0.1, 0.3], (len(fill), 1)), atol=1e-6)
    assert fill.sh_degree == 0 and np.all(fill.opacity_logits > 2)
    # seen whole: nothing filled; a hole outside the (grown) footprint: not ours to fill
    assert fill_under(_ground(None), [(0, T, size)], 1)[1].sum() == 0
    far = fill_under(_ground((5.0, 8.0, -8.0, -5.0)), [(0, T, size)], 1)
    assert len(far[0]) == 0
    # a hole larger than the footprint is filled only within the footprint grown by GROW_M
    big, a_big = fill_under(_ground((-6.0, 8.0, -3.0, 7.0)), [(0, T, size)], 1)
    assert a_big[0] <= (4.0 + 2 * GROW_M + FILL_SPACING_M) * (2.0 + 2 * GROW_M + FILL_SPACING_M)
    assert a_big[0] >= (4.0 + 2 * GROW_M - FILL_SPACING_M) * (2.0 + 2 * GROW_M - FILL_SPACING_M)
    # no ground around to copy: mid grey (DC 0)
    none, _ = fill_under(_ground((-20, 20, -20, 20)), [(0, T, size)], 1)
    assert len(none) and np.all(none.sh[:, 0, :] == 0)
