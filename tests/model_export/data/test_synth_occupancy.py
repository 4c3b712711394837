"""Occupancy ground truth: exact voxel tests vs dense sampling, and consistency with the rendered depth."""

from __future__ import annotations

import math

import numpy as np
from xyzcyl.model_export.data.classes import EGO
from xyzcyl.model_export.data.occupancy import (
    OccupancyGrid,
    bev,
    box_overlaps,
    cylinder_overlaps,
    ellipsoid_overlaps,
    inside_any,
    occupancy,
)
from xyzcyl.model_export.data.scene import sample_scene

SAMPLES = 9  # per axis, dense sampling of a voxel for the reference


def _inside(kind, g, pts):
    c, s = g[6], g[7]
    r = pts - g[:3]
    lx = r[:, 0] * c + r[:, 1] * s
    ly = -r[:, 0] * s + r[:, 1] * c
    if kind == "box":
        return (np.abs(lx) < g[3]) & (np.abs(ly) < g[4]) & (np.abs(r[:, 2]) < g[5])
    if kind == "cyl":
        return (r[:, 0] ** 2 + r[:, 1] ** 2 < g[3] ** 2) & (np.abs(r[:, 2]) < g[5])
    return (lx / g[3]) ** 2 + (ly / g[4]) ** 2 + (r[:, 2] / g[5]) ** 2 < 1


def test_exact_voxel_tests_agree_with_dense_sampling():
    rng = np.random.default_rng(0)
    h = 0.2
    lin = (np.arange(SAMPLES) + 0.5) / SAMPLES * 2 * h - h
    cube = np.stack(np.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
    spacing = 2 * h / SAMPLES
    for fn, kind in ((box_overlaps, "box"), (cylinder_overlaps, "cyl"), (ellipsoid_overlaps, "ell")):
        agree = 0
        for _ in range(3000):
            yaw = rng.uniform(-np.pi, np.pi) if kind != "cyl" else 0.0
            half = rng.uniform(0.05, 1.0, 3)
            if kind == "cyl":
                half[1] = half[0]
            g = np.array([0, 0, 0, *half, math.cos(yaw), math.sin(yaw)])
            v = rng.uniform(-1.3, 1.3, 3)
            exact = fn(g, v[0], v[1], v[2], h)
            sampled = _inside(kind, g, v + cube).any()
            if sampled:
                assert exact, (kind, g, v)  # a point of the voxel is inside the solid
            elif exact:
                # the overlap must be thinner than the sampling: every voxel point is within spacing*sqrt(3)/2
                # of a sample, so the solid grown by that much must contain a sample. Boxes and cylinders grow
                # by adding it to the half extents; an ellipsoid E grown by d lies inside (1 + d/r_min) E.
                grow = spacing * math.sqrt(3) / 2
                gg = g.copy()
                if kind == "ell":
                    gg[3:6] *= 1 + grow / g[3:6].min()
                else:
                    gg[3:6] += grow
                assert _inside(kind, gg, v + cube).any(), (kind, g, v)
            agree += sampled == exact
        assert agree > 2700  # most random pairs are decided by the samples themselves


def test_scene_voxels_match_reference_points():
    scene = sample_scene(5, 1)
    grid = OccupancyGrid(voxel=0.8)
    sem = occupancy(scene, grid)
    assert sem.shape == (100, 100, 20)
    rng = np.random.default_rng(2)
    idx = rng.integers(0, [100, 100, 20], size=(3000, 3))
    # voxels with sample points strictly inside a solid must be occupied, with that point's class or higher
    r = np.asarray(grid.range_m)
    centres = r[:3] + (idx + 0.5) * grid.voxel
    cls = inside_any(scene, centres)
    got = sem[idx[:, 0], idx[:, 1], idx[:, 2]]
    assert np.all(got[cls > 0] > 0)
    # occupied fraction is plausible for a street (ground slab + buildings), and the ego car is there
    assert 0.05 < (sem > 0).mean() < 0.6
    assert np.any(sem == EGO)


def _dilate(occ: np.ndarray) -> np.ndarray:
    """3x3x3 binary dilation."""
    p = np.pad(occ, 1)
    out = np.zeros_like(occ)
    X, Y, Z = occ.shape
    for a in range(3):
        for b in range(3):
            for c in range(3):
                out |= p[a:a + X, b:b + Y, c:c + Z]
    return out


def test_bev_is_top_class():
    sem = np.zeros((2, 2, 4), np.uint8)
    sem[0, 0, 0], sem[0, 0, 2] = 1, 4
    sem[1, 1, 1] = 6
    b = bev(sem)
    assert b.tolist() == [[4, 0], [0, 6]]


def test_depth_points_fall_in_occupied_voxels(tiny_scenes):
    for data in tiny_scenes:
        for tag, sem in data.occupancy.items():
            voxel = float(tag.replace("p", "."))
            grid = OccupancyGrid(voxel=voxel)
            near = _dilate(sem > 0)  # occupied voxel or a 1-voxel neighbour
            r = np.asarray(grid.range_m)
            inside = total = 0
            views = list(zip(data.inputs, data.input_views))
            for s, cams in data.targets.items():
                views += list(zip(cams, data.target_views[s]))
            for cam, view in views:
                vv, uu = np.nonzero(view.depth > 0)
                d = view.depth[vv, uu].astype(np.float64)
                pc = np.stack([(uu - cam.K[0, 2]) / cam.K[0, 0] * d, (vv - cam.K[1, 2]) / cam.K[1, 1] * d, d], 1)
                p = pc @ cam.cam_to_ego[:3, :3].T + cam.cam_to_ego[:3, 3]
                ijk = np.floor((p - r[:3]) / voxel).astype(int)
                ok = np.all((ijk >= 0) & (ijk < sem.shape), axis=1)
                ijk = ijk[ok]
                total += len(ijk)
                inside += int(near[ijk[:, 0], ijk[:, 1], ijk[:, 2]].sum())
            assert total > 1000
            assert inside / total >= 0.99, (tag, inside / total)
