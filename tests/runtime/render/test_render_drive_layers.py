"""A drive's scene of several keyframes draws in two layers (runtime.scene.Scene.render): the view's primary keyframe
(Scene.primary_keyframe: the keyframe whose cameras stood nearest, a still ego's by time) over the others; the
layers' composite against one pass of the renderer; keyframe_of through the scene folder and its refusals."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import concat, look_at, pinhole, random_gaussians
from test_render_parts import LAYERED_ATOL
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import LAYER_COVER, Scene, SceneError, composite_layers
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import pose


def _drive(xs, times, keyframes) -> dict:
    """scene.json's drive block of frames with the ego at x = ``xs`` (scene frame) and ``times`` (seconds)."""
    return {"frames": len(xs), "keyframes": list(keyframes), "timestamp_s": 100.0,
            "times_s": list(times), "ego_to_world": np.eye(4).tolist(),
            "trajectory": [pose(x, 0.0) for x in xs], "tracks": 0}


def _scene(g, keyframe_of, drive) -> Scene:
    return Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive,
                 keyframe_of=np.asarray(keyframe_of, np.int16))


def test_the_primary_layer_drawn_first_over_the_rest():
    rng = np.random.default_rng(3)
    near = random_gaussians(rng, 150, lo=(-2, -1.5, 2), hi=(2, 1.5, 4))      # camera frame: 2-4 m ahead
    far = random_gaussians(rng, 150, lo=(-3, -2, 6), hi=(3, 2, 10))          # 6-10 m: wholly behind them
    g = concat(near, far)
    cam = pinhole(c2w=np.eye(4))
    whole = render(g, cam)
    # the near layer first is what one pass draws (front-to-back compositing of two depth-separated sets);
    # atol: the one pass stops a pixel once its transmittance is ~1e-4, the layered one draws the far layer under
    # that remainder, a difference below 1e-3 of the colour
    a = render(g.subset(np.arange(len(g)) < 150), cam)
    b = render(g.subset(np.arange(len(g)) >= 150), cam)
    rgb, depth, alpha = composite_layers(a, b)
    np.testing.assert_allclose(rgb, whole.rgb, atol=1e-3)
    np.testing.assert_allclose(alpha, whole.alpha, atol=1e-3)
    np.testing.assert_allclose(depth, whole.depth, atol=1e-2)    # metres: the same remainder times ~8 m
    # through Scene.render: the camera stands nearest keyframe 0's cameras (ego at x = 0; keyframe 1's at 30 m)
    keyframe_of = np.r_[np.zeros(150), np.ones(150)]
    scene = _scene(g, keyframe_of, _drive([0.0, 30.0], [0.0, 1.0], [0, 1]))
    assert scene.primary_keyframe(cam) == 0
    s_rgb, s_depth, s_alpha = scene.render(cam)
    # Scene draws each layer behind the ones before in the raster (render's behind, the tiles those in front covered
    # theirs: LAYER_COVER): the composite's to LAYERED_ATOL
    c_rgb, _, c_alpha = composite_layers(a, b, cover=LAYER_COVER)
    np.testing.assert_allclose(s_rgb, c_rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(s_alpha, c_alpha, atol=LAYERED_ATOL)
    # the far keyframe primary: its Gaussians cover the near ones where they are opaque (not what one pass draws)
    flipped = _scene(g, 1 - keyframe_of, _drive([0.0, 30.0], [0.0, 1.0], [0, 1]))
    f_rgb, _, _ = flipped.render(cam)
    b_rgb, _, _ = composite_layers(b, a, cover=LAYER_COVER)
    np.testing.assert_allclose(f_rgb, b_rgb, atol=LAYERED_ATOL)
    assert np.abs(f_rgb - whole.rgb).max() > 0.1


def test_with_viewpoint_chunks_the_primary_group_then_its_neighbours_then_the_rest():
    from xyzcyl.runtime.viewpoints import Viewpoints

    rng = np.random.default_rng(4)
    sets = [random_gaussians(rng, 100, lo=(-2, -1.5, 2), hi=(2, 1.5, 4)),       # camera frame: 2-4 m ahead
            random_gaussians(rng, 100, lo=(-3, -2, 6), hi=(3, 2, 10)),          # 6-10 m
            random_gaussians(rng, 100, lo=(-4, -3, 12), hi=(4, 3, 16))]         # 12-16 m
    cam = pinhole(c2w=np.eye(4))
    drive = _drive([0.0, 30.0, 60.0, 90.0], [0.0, 1.0, 2.0, 3.0], [0, 1, 2, 3])

    def scene(order):
        """Keyframe 0's chunk holds sets[order[0]], keyframe 1's shared cells sets[order[1]], keyframe 2's
        sets[order[2]] (keyframes 2 and 3 one group: the rest is keyframe 3's, one Gaussian, hidden)."""
        hidden = random_gaussians(rng, 1).with_opacity_logits(np.float32([-30.0]))
        shared = concat(sets[order[1]], sets[order[2]], hidden)
        vp = Viewpoints.build([[0], [1], [2, 3]], [sets[order[0]], random_gaussians(rng, 0), hidden])
        return Scene(gaussians=shared, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive,
                     keyframe_of=np.r_[np.ones(100), np.full(100, 2), [3]].astype(np.int16), viewpoints=vp)

    layers = [render(g, cam) for g in sets]
    for order in ((0, 1, 2), (2, 1, 0), (1, 0, 2)):
        s = scene(order)
        assert s.primary_keyframe(cam) == 0
        rgb, depth, alpha = s.render(cam)
        e_rgb, e_depth, e_alpha = composite_layers(*(layers[i] for i in order), cover=LAYER_COVER)
        np.testing.assert_allclose(rgb, e_rgb, atol=LAYERED_ATOL)           # render's behind (first test)
        np.testing.assert_allclose(alpha, e_alpha, atol=LAYERED_ATOL)
        np.testing.assert_allclose(depth, e_depth, atol=LAYERED_ATOL * 16)  # metres: x the farthest, 16 m
    # in depth order it is what one pass draws (the layered draw's bound: a pixel with at most T_RESUME of light
    # left is not drawn behind; depth: that remainder times up to 16 m)
    whole = render(concat(*sets), cam)
    rgb, depth, _ = scene((0, 1, 2)).render(cam)
    np.testing.assert_allclose(rgb, whole.rgb, atol=LAYERED_ATOL)
    np.testing.assert_allclose(depth, whole.depth, atol=LAYERED_ATOL * 16)
    # from keyframe 3's place, group (2, 3) is primary, group 1 beside it, keyframe 0's chunk is never drawn
    far = scene((0, 1, 2))
    read = []
    chunk = far.viewpoints.gaussians
    far.viewpoints.gaussians = lambda i: read.append(i) or chunk(i)
    at3 = pinhole(c2w=look_at([90.0, 0.0, 1.5], [120.0, 0.0, 1.5]))
    assert far.primary_keyframe(at3) == 3
    far.render(at3)
    assert sorted(read) == [1, 2]


def test_a_still_egos_view_is_drawn_from_its_keyframe_nearest_in_time():
    """Keyframes 0 and 1 of one viewpoint group (the ego still), each with a chunk of its own (runtime.viewpoints):
    a view at keyframe 1's time draws keyframe 1's chunk first, then the group's and the next group's shared
    Gaussians; keyframe 0's chunk is not read. At keyframe 0's time, keyframe 0's."""
    from xyzcyl.runtime.viewpoints import Viewpoints

    rng = np.random.default_rng(6)
    a = random_gaussians(rng, 100, lo=(-2, -1.5, 2), hi=(2, 1.5, 4))          # camera frame: 2-4 m ahead
    b = random_gaussians(rng, 100, lo=(-2, -1.5, 2), hi=(2, 1.5, 4))          # the same place, another time
    s0 = random_gaussians(rng, 100, lo=(-3, -2, 6), hi=(3, 2, 10))            # keyframe 0's shared cells
    s2 = random_gaussians(rng, 100, lo=(-4, -3, 12), hi=(4, 3, 16))           # keyframe 2's (30 m on)
    drive = _drive([0.0, 0.0, 30.0], [0.0, 2.0, 4.0], [0, 1, 2])
    vp = Viewpoints.build([[0], [1], [2]], [a, b, random_gaussians(rng, 0)], viewpoints=[0, 0, 2])
    scene = Scene(gaussians=concat(s0, s2), background=None, rig=load_rig(EXAMPLE_RIG), drive=drive,
                  keyframe_of=np.r_[np.zeros(100), np.full(100, 2)].astype(np.int16), viewpoints=vp)
    assert vp.groups() == [0, 2] and vp.group_keyframes(0) == [0, 1]
    cam = pinhole(c2w=np.eye(4))
    read = []
    chunk = vp.gaussians
    vp.gaussians = lambda i: read.append(i) or chunk(i)
    assert scene.primary_keyframe(cam, 102.0) == 1 and scene.primary_keyframe(cam, 100.0) == 0
    nothing = render(Gaussians.empty(), cam)     # the third layer (no keyframe left): it still finishes covered tiles
    rgb, _, alpha = scene.render(cam, 102.0)
    e_rgb, _, e_alpha = composite_layers(render(b, cam), render(concat(s0, s2), cam), nothing,
                                       cover=LAYER_COVER)
    np.testing.assert_allclose(rgb, e_rgb, atol=LAYERED_ATOL)               # render's behind (first test)
    np.testing.assert_allclose(alpha, e_alpha, atol=LAYERED_ATOL)
    assert sorted(read) == [1, 2]
    read.clear()
    rgb0, _, _ = scene.render(cam, 100.0)
    e_rgb0, _, _ = composite_layers(render(concat(a, s0), cam), render(s2, cam), nothing, cover=LAYER_COVER)
    np.testing.assert_allclose(rgb0, e_rgb0, atol=LAYERED_ATOL)
    assert sorted(read) == [0, 2] and np.abs(rgb0 - rgb).max() > 0.1


def test_the_primary_keyframe_is_the_nearest_and_a_still_egos_by_time():
    g = random_gaussians(np.random.default_rng(0), 4)
    moving = _scene(g, [0, 1, 2, 2], _drive([0.0, 5.0, 10.0], [0.0, 0.5, 1.0], [0, 1, 2]))
    cam = pinhole(c2w=look_at([6.0, 0.0, 1.5], [20.0, 0.0, 1.5]))
    assert moving.primary_keyframe(cam) == 1                 # its cameras stood at 5 m + their offsets
    assert moving.primary_keyframe(pinhole(c2w=look_at([11.0, 0, 1.5], [20, 0, 1.5]))) == 2
    # a still ego: three keyframes in one place; the view's time picks (default: the drive's start)
    still = _scene(g, [0, 1, 2, 2], _drive([0.0, 0.01, 0.02], [0.0, 1.0, 2.0], [0, 1, 2]))
    assert still.primary_keyframe(cam) == 0
    assert still.primary_keyframe(cam, 100.0 + 1.9) == 2
    assert still.primary_keyframe(cam, 100.0 + 0.8) == 1
    # one keyframe, or no keyframe_of: one layer
    assert _scene(g, [0, 0, 0, 0], _drive([0.0], [0.0], [0])).primary_keyframe(cam) is None
    assert Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG)).primary_keyframe(cam) is None


def test_keyframe_of_through_the_scene_folder_and_its_refusals(tmp_path):
    g = random_gaussians(np.random.default_rng(1), 6)
    scene = _scene(g, [0, 0, 1, 1, 2, 2], _drive([0.0, 5.0, 10.0], [0.0, 0.5, 1.0], [0, 1, 2]))
    scene.save(tmp_path / "s")
    back = Scene.load(tmp_path / "s")
    # each Gaussian keeps its keyframe (the folder holds them in tile order: runtime.tiles)
    at = {tuple(m): k for m, k in zip(g.means.tolist(), [0, 0, 1, 1, 2, 2])}
    assert [at[tuple(m)] for m in back.gaussians.means.tolist()] == back.keyframe_of.tolist()
    for bad, why in ((np.zeros(5, np.int16), "one per Gaussian"), (np.full(6, 3, np.int16), "3 keyframes"),
                     (np.zeros(6, np.float32), "integers")):
        np.save(tmp_path / "s" / "keyframe_of.npy", bad)
        with pytest.raises(SceneError, match=why) as e:
            Scene.load(tmp_path / "s")
        assert e.value.field == "keyframe_of"


def test_a_drives_gaussians_are_kept_in_tile_order():
    """Scene keeps a drive's Gaussians tile after tile, each tile's keyframe after keyframe, each run in spatial order
    (runtime.tiles.tile_order; here along x): a scene folder written in another order reads back so, and a view
    draws the same."""
    g = random_gaussians(np.random.default_rng(5), 8, lo=(-30, -5, 0), hi=(30, 5, 2))
    g.means[:, 0] = [30.0, -10.0, 5.0, 40.0, -20.0, 10.0, 12.0, -1.0]     # tiles (x // 25): 1 -1 0 1 -1 0 0 -1
    g.means[:, 1] = 1.0
    g.means[:, 2] = 1.0
    drive = _drive([0.0, 5.0, 10.0], [0.0, 0.5, 1.0], [0, 1, 2])
    scene = _scene(g, [2, 0, 1, 0, 2, 1, 0, 0], drive)
    order = [1, 7, 4, 6, 2, 5, 3, 0]        # tile -1: keyframes 0 0 2; tile 0: 0 1 1; tile 1: 0 2
    np.testing.assert_array_equal(scene.keyframe_of, [0, 0, 2, 0, 1, 1, 0, 2])
    np.testing.assert_array_equal(scene.gaussians.means, g.means[order])
    assert [t.cell for t in scene.tiles.tiles] == [(-1, 0), (0, 0), (1, 0)]
    np.testing.assert_array_equal(scene.tiles.key_starts, [[0, 2, 2, 3], [0, 1, 3, 3], [0, 1, 1, 2]])
    cam = pinhole(c2w=look_at([6.0, 0.0, 1.5], [20.0, 0.0, 1.5]))
    by_hand = _scene(g.subset(order), [0, 0, 2, 0, 1, 1, 0, 2], drive)
    np.testing.assert_array_equal(scene.render(cam)[0], by_hand.render(cam)[0])


def test_a_layer_drawn_into_the_one_before_equals_one_drawn_into_copies():
    """render(..., behind=a, behind_inplace=True), what Scene's layers use, draws into a's arrays: the same pixels as
    into copies (exactly: the same operations on the same values), and a then holds the result."""
    rng = np.random.default_rng(5)
    near = random_gaussians(rng, 120, lo=(-2, -1.5, 2), hi=(2, 1.5, 4))
    far = random_gaussians(rng, 120, lo=(-3, -2, 6), hi=(3, 2, 10))
    cam = pinhole(c2w=np.eye(4))
    copied = render(far, cam, background=(0.2, 0.3, 0.4), behind=render(near, cam))
    a = render(near, cam)
    before = a.rgb.copy()
    inplace = render(far, cam, background=(0.2, 0.3, 0.4), behind=a, behind_inplace=True)
    assert inplace.rgb is a.rgb and not np.array_equal(a.rgb, before)
    for x, y in ((inplace.rgb, copied.rgb), (inplace.alpha, copied.alpha), (inplace.depth, copied.depth)):
        np.testing.assert_array_equal(x, y)
