"""`photo_textures`: real photo tiles (CC0 street panoramas) on facades, road and sidewalks. Off by default and
then the generator is unchanged; on, only colours change (geometry, depth and classes are the same scene's)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from synth_helpers import check_probability_field
from xyzcyl.model_export.data import classes as C
from xyzcyl.model_export.data.photos import LUMA, photo_bank, photo_indices
from xyzcyl.model_export.data.scene import (
    G_PHOTO,
    G_PHOTO_L,
    G_PHOTO_TILE,
    T_FACADE,
    T_PHOTO,
    T_SIDEWALK,
    SceneConfig,
    sample_scene,
)
from xyzcyl.model_export.data.synth import SynthConfig, render_scene
from xyzcyl.model_export.data.trace import photo_texel

PHOTO = SceneConfig(photo_textures=1.0)


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a.arrays().values(), b.arrays().values(), strict=True))


def test_the_bank_is_normalised_facades_first():
    bank, names = photo_bank()
    facades, grounds = photo_indices()
    assert bank.shape[1:] == (128, 128, 3) and len(facades) >= 6 and len(grounds) >= 3
    assert list(facades) == list(range(len(facades)))  # facades first, then ground tiles
    assert all(names[i].startswith("ground_") for i in grounds)
    # mean luminance 1 per tile (albedo = tile * the surface's luminance); 1e-9: float64 round-off of the mean
    np.testing.assert_allclose((bank @ LUMA).mean(axis=(1, 2)), 1.0, atol=1e-9)


def _texel_reference(tile, s, t, mirror_t):
    """Obviously correct: fold the coordinates into [0, 1], then bilinear interpolation written out per corner."""
    def fold(a, mirror):
        a = abs(a) % 2.0 if mirror else a - np.floor(a)
        return 2.0 - a if a > 1.0 else a
    s, t = fold(s, True), fold(t, mirror_t)
    H, W = tile.shape[:2]
    x, y = s * (W - 1), (1.0 - t) * (H - 1)
    x0, y0 = min(int(np.floor(x)), W - 2), min(int(np.floor(y)), H - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * tile[y0, x0] + fx * (1 - fy) * tile[y0, x0 + 1]
            + (1 - fx) * fy * tile[y0 + 1, x0] + fx * fy * tile[y0 + 1, x0 + 1])


def test_texel_matches_reference():
    bank = photo_bank()[0]
    rng = np.random.default_rng(0)
    for _ in range(300):
        i = int(rng.integers(len(bank)))
        s, t = rng.uniform(-5, 5, 2)
        mirror = bool(rng.random() < 0.5)
        # 1e-9: the kernel is compiled with fastmath (reassociated sums of 4 products of values <= ~4)
        np.testing.assert_allclose(photo_texel(bank, i, s, t, mirror), _texel_reference(bank[i], s, t, mirror),
                                   atol=1e-9)
    # corners of the tile: t = 0 is the bottom row, s = 0 the left column; mirrored repeat across
    np.testing.assert_allclose(photo_texel(bank, 0, 0.0, 0.0, False), bank[0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(photo_texel(bank, 0, 1.0, 0.999999999, False), bank[0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(photo_texel(bank, 0, 1.5, 0.5, False), photo_texel(bank, 0, 0.5, 0.5, False))


def test_zero_is_the_v1_generator_byte_for_byte():
    for i in range(4):
        assert _same(sample_scene(7, i), sample_scene(7, i, SceneConfig(photo_textures=0.0)))


def test_photo_scenes_change_surfaces_only():
    changed = 0
    for i in range(6):
        v1, s = sample_scene(7, i), sample_scene(7, i, PHOTO)
        for k in ("kind", "geo", "cls", "ego", "col", "col2", "sky"):
            assert np.array_equal(getattr(v1, k), getattr(s, k)), k  # same geometry, classes and colours
        photo = s.tex == T_PHOTO
        assert np.array_equal(photo | (s.tex == v1.tex), np.ones(s.n, bool))
        assert np.all(v1.tex[photo] == T_FACADE)
        facades = photo_indices()[0]
        assert np.all(np.isin(s.par[photo, 0], facades))
        # luminance kept: the tile's mean luminance 1 times the building's own
        np.testing.assert_allclose(s.par[photo, 3], v1.col[photo] @ LUMA)
        changed += photo.sum()
        if s.ground[G_PHOTO] > 0:
            assert s.ground[G_PHOTO] - 1 in photo_indices()[1] and 3.0 <= s.ground[G_PHOTO_TILE] <= 10.0
            assert s.ground[G_PHOTO_L] > 0
        walk = (s.tex == T_SIDEWALK) & (s.par[:, 1] > 0)
        assert np.array_equal(s.par[~walk & ~photo], v1.par[~walk & ~photo])
    assert changed > 0


def test_probability_draws_per_scene():
    near = [not _same(sample_scene(3, i), sample_scene(3, i, SceneConfig(photo_textures=0.5))) for i in range(40)]
    assert 8 <= sum(near) <= 32  # binomial(40, 0.5): outside this range with probability < 1e-4


def test_rendered_photo_scene_has_the_same_depth_and_classes_and_new_building_colours():
    cfg = SynthConfig(height=48, width=80, targets=(), voxels=(1.6,), seed=7)
    for i in range(6):
        if sample_scene(7, i, PHOTO).tex.tolist().count(T_PHOTO) > 0:
            break
    a, b = render_scene(cfg, i), render_scene(replace(cfg, photo_textures=1.0), i)
    differs = np.zeros((48, 80), bool)
    for va, vb in zip(a.input_views, b.input_views, strict=True):
        assert np.array_equal(va.depth, vb.depth) and np.array_equal(va.semantic, vb.semantic)
        d = np.any(va.rgb != vb.rgb, axis=2)
        # only surfaces that may carry a photo tile change colour. The classes come from the pixel-centre ray and
        # the colour from 2 x 2 sub-samples within the pixel, so a pixel next to such a surface may change too:
        # allowed = the surfaces' pixels grown by one pixel
        may = np.isin(va.semantic, (C.BUILDING, C.ROAD, C.SIDEWALK)).astype(np.uint8)
        assert not np.any(d & ~cv2.dilate(may, np.ones((3, 3), np.uint8)).astype(bool))
        differs |= d & (va.semantic == C.BUILDING)
    assert differs.any()


def test_config_validation_cli_and_index(tmp_path, capsys):
    check_probability_field(tmp_path, capsys, "photo_textures")
