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
    fill, owner, area = fill_under(_ground((-0.5, 2.5, 1.2, 2.8)), [(1, T, size)], 3)
    assert np.all(owner == 1)
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
    assert fill_under(_ground(None), [(0, T, size)], 1)[2].sum() == 0
    far = fill_under(_ground((5.0, 8.0, -8.0, -5.0)), [(0, T, size)], 1)
    assert len(far[0]) == 0
    # a hole larger than the footprint is filled only within the footprint grown by GROW_M
    big, _, a_big = fill_under(_ground((-6.0, 8.0, -3.0, 7.0)), [(0, T, size)], 1)
    assert a_big[0] <= (4.0 + 2 * GROW_M + FILL_SPACING_M) * (2.0 + 2 * GROW_M + FILL_SPACING_M)
    assert a_big[0] >= (4.0 + 2 * GROW_M - FILL_SPACING_M) * (2.0 + 2 * GROW_M - FILL_SPACING_M)
    # no ground around to copy: mid grey (DC 0)
    none, _, _ = fill_under(_ground((-20, 20, -20, 20)), [(0, T, size)], 1)
    assert len(none) and np.all(none.sh[:, 0, :] == 0)


def test_cells_near_a_box_along_their_rays_are_snapped_into_it():
    """runtime.boxes.snap_into_boxes: a camera without measured depth puts a moving object's cells where its
    model's depth says, often metres off; those whose ray passes through the object's box near it move onto the
    box's near side (their distance scaled by ``factor``), the rest stay."""
    from xyzcyl.runtime.boxes import SNAP_FAR, SNAP_INTO_M, SNAP_NEAR, snap_into_boxes

    origin = np.array([0.0, 0.0, 1.5])
    inv = np.linalg.inv(np.array(_pose(12.0, 0.0), float))         # a 4 x 2 x 3 m box centred 12 m ahead, z 0
    half = np.array([2.0, 1.0, 1.5])
    ray = np.array([1.0, 0.02, -0.05])
    ray /= np.linalg.norm(ray)
    # where the ray enters and leaves the box: x = 10 and 14 (|y| <= 1 and |z| <= 1.5 hold along the way)
    t_in, t_out = 10.0 / ray[0], 14.0 / ray[0]
    d = np.array([0.4 * t_in, SNAP_NEAR * t_in + 0.01, 12.0 / ray[0], SNAP_FAR * t_out - 0.01, SNAP_FAR * t_out + 1])
    cells = origin + d[:, None] * ray
    missing = origin + 12.0 * np.array([0.0, 1.0, 0.0])               # beside the camera: no box on its ray
    out, factor = snap_into_boxes(np.vstack([cells, missing]), origin, [(inv, half)])
    want = t_in + min(SNAP_INTO_M, 0.5 * (t_out - t_in))
    np.testing.assert_allclose(factor, [1.0, want / d[1], 1.0, want / d[3], 1.0, 1.0], rtol=1e-9)
    np.testing.assert_allclose(out[[1, 3]], origin + want * np.tile(ray, (2, 1)), atol=1e-9)
    np.testing.assert_array_equal(out[[0, 2, 4, 5]], np.vstack([cells, missing])[[0, 2, 4, 5]])
    # the camera inside the box: nothing to snap to
    assert np.all(snap_into_boxes(cells, np.array([12.0, 0.0, 1.0]), [(inv, half)])[1] == 1.0)


def test_snap_into_boxes_kernel_against_its_numpy_reference():
    """snap_into_boxes (one numba pass, each cell against the boxes whose bounding cone holds its ray) against
    snap_into_boxes_reference (box after box in numpy) on random cells and boxes, a box the camera stands in among
    them: the same cells moved, to the same place."""
    from xyzcyl.runtime.boxes import snap_into_boxes, snap_into_boxes_reference

    rng = np.random.default_rng(4)
    boxes = [(np.linalg.inv(np.array(_pose(*rng.uniform(-20, 20, 2), rng.uniform(0, 360)), float)),
              rng.uniform(0.5, 3.0, 3)) for _ in range(25)]
    boxes.insert(7, (np.linalg.inv(np.array(_pose(0.5, 0.0, 20.0), float)), np.array([2.0, 1.0, 1.0])))
    cells = rng.uniform([-40, -40, -3], [40, 40, 3], (40000, 3))
    origin = np.array([0.2, 0.1, 0.3])
    out, factor = snap_into_boxes(cells, origin, boxes)
    want, want_f = snap_into_boxes_reference(cells, origin, boxes)
    assert 1000 < int((want_f != 1.0).sum()) < len(cells)          # many snapped, not all
    np.testing.assert_array_equal(factor != 1.0, want_f != 1.0)
    # the same arithmetic but for the order of a 3-term dot product (BLAS in the reference): ulps
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(factor, want_f, rtol=1e-12)
    assert snap_into_boxes(cells[:0], origin, boxes)[0].shape == (0, 3)


def test_ground_cells_kernel_equals_its_numpy_reference():
    """The one-pass kernel picks exactly the reference's Gaussians and cells: points on the lattice's lines, outside
    its box, off the ground by more or less than the tolerance, on cells that are not in the lattice."""
    from xyzcyl.runtime.groundfill import GROUND_TOL_M, _pack, ground_cells, ground_cells_reference

    rng = np.random.default_rng(3)
    s = 0.2
    cells = np.unique(rng.integers(-40, 40, size=(900, 2)), axis=0)
    packed = np.sort(_pack(cells))
    z = rng.uniform(-1, 1, len(packed))
    keys = np.stack([packed >> 32, (packed & 0xFFFFFFFF).astype(np.int32)], axis=1)     # _pack's inverse
    n = 20_000
    pick = rng.integers(0, len(packed), n)
    xy = (keys[pick] + rng.uniform(0, 1, (n, 2))) * s
    xy[: n // 10] = np.round(xy[: n // 10] / s) * s                        # on the lattice's lines
    xy[n // 10: n // 5] = rng.uniform(-12, 12, (n // 10, 2))               # anywhere: cells not in it, outside it
    dz = rng.uniform(-2 * GROUND_TOL_M, 2 * GROUND_TOL_M, n)
    dz[n // 5: n // 4] = GROUND_TOL_M                                       # at the tolerance
    means = np.column_stack([xy, z[pick] + dz]).astype(np.float32)
    lo, hi = keys.min(axis=0) * s, (keys.max(axis=0) + 1) * s
    got, want = ground_cells(means, lo, hi, s, packed, z), ground_cells_reference(means, lo, hi, s, packed, z)
    assert len(want[0]) > n // 4                    # (not a test of nothing: many on the ground, many not)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    # a narrower box: the points outside it are not looked up
    got, want = ground_cells(means, lo + 1.0, hi - 1.0, s, packed, z), ground_cells_reference(means, lo + 1.0,
                                                                                                hi - 1.0, s, packed, z)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_no_footprint_lays_no_lattice_and_fills_nothing():
    """fill_lattice of no footprints (a drive whose moving objects have no annotated pose in the scene) is empty, and
    fill_lattice_under fills nothing on it: an empty fill, zero area for every object."""
    from xyzcyl.runtime.groundfill import fill_lattice, fill_lattice_under

    lattice = fill_lattice([], 3)
    assert lattice.n_objects == 3 and len(lattice.packed) == len(lattice.key) == len(lattice.z) == 0
    fill, owner, area = fill_lattice_under(_ground((-1.0, 1.0, -1.0, 1.0)), lattice)
    assert len(fill) == 0 and len(owner) == 0
    np.testing.assert_array_equal(area, np.zeros(3))
