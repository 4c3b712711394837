"""A drive scene's shared Gaussians in spatial tiles (runtime.tiles): the tile order, the visibility test against the
renderer (a tile left out changes no pixel), a scene folder read tile by tile, the cache's budget, the refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from render_scenes import look_at, pinhole, random_gaussians
from test_render_drive_layers import _drive
from test_render_lens import lens_camera
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import GaussianError, Gaussians, render
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import Scene, SceneError
from xyzcyl.runtime.tiles import HORIZON_M, TILE_M, TileError, Tiles, build_tiles, tile_order
from xyzcyl.testing import EXAMPLE_RIG


def _street(rng, n=3000) -> tuple[Gaussians, np.ndarray]:
    """A 200 m x 60 m street of Gaussians (scene frame, x forward) from 4 keyframes, big and small ones, and its
    keyframe_of [N] (keyframe k's Gaussians mostly near x = 40 k)."""
    g = random_gaussians(rng, n, lo=(-100, -30, -1), hi=(100, 30, 8), scale=(0.02, 3.0))
    kf = np.clip(np.floor((g.means[:, 0] + 100) / 50) + rng.integers(-1, 2, n), 0, 3).astype(np.int16)
    return g, kf


def _cameras() -> dict[str, Camera]:
    """Cameras at the street's middle and end, looking along it, across it, up, and the wide lenses."""
    at = lambda eye, target: look_at(eye, target)      # noqa: E731
    cams = {"ahead": pinhole(96, 64, 50.0, c2w=at([0, 0, 1.5], [50, 0, 1.5])),
            "side": pinhole(96, 64, 50.0, c2w=at([0, 0, 1.5], [0, 40, 1.5])),
            "back": pinhole(96, 64, 50.0, c2w=at([-40, 0, 1.5], [-90, 3, 1.5])),
            "narrow": pinhole(96, 64, 400.0, c2w=at([-50, 0, 1.5], [0, 0, 1.5])),
            "opencv": lens_camera("opencv", 96, 64, at([0, 0, 1.5], [0, -40, 1.5])),
            "fisheye_190": lens_camera("fisheye", 96, 64, at([10, 0, 1.5], [10, 40, 1.5])),
            "equirect": Camera(model="equirectangular", cam_to_ego=at([0, 0, 1.5], [50, 0, 1.5]), width=96,
                               height=48)}
    return cams


def test_tile_order_puts_tiles_then_keyframes_then_neighbours_together():
    means = np.array([[30, 0, 0], [-1, 0, 0], [5, 60, 0], [24.9, 1, 0], [26, -3, 0], [-30, 0, 0]], np.float32)
    kf = np.array([0, 1, 0, 1, 0, 0], np.int16)
    order, cells = tile_order(means, kf)
    # cells (x // 25, y // 25): (1,0) (-1,0) (0,2) (0,0) (1,-1) (-2,0); ordered by ix, then iy, then keyframe
    assert order.tolist() == [5, 1, 3, 2, 4, 0]
    assert cells.tolist() == [[-2, 0], [-1, 0], [0, 0], [0, 2], [1, -1], [1, 0]]
    g = Gaussians(means, np.tile([1, 0, 0, 0], (6, 1)).astype(np.float32), np.full((6, 3), -1, np.float32),
                  np.zeros(6, np.float32), np.zeros((6, 1, 3), np.float32)).subset(order)
    tiles = build_tiles(g, cells)
    assert [(t.cell, t.start, t.count) for t in tiles] == [((-2, 0), 0, 1), ((-1, 0), 1, 1), ((0, 0), 2, 1),
                                                           ((0, 2), 3, 1), ((1, -1), 4, 1), ((1, 0), 5, 1)]
    assert tiles[2].lo == (24.899, 1.0, 0.0) and tiles[2].hi == (24.9, 1.0, 0.0)      # mm, rounded outwards
    # within a tile, keyframe after keyframe, and each keyframe's in spatial order (runtime.viewpoints.spatial_order:
    # along x here, whatever their order before)
    means = np.array([[1, 1, 0], [2, 1, 0], [3, 1, 0], [4, 1, 0]], np.float32)
    order, _ = tile_order(means, np.array([1, 0, 1, 0], np.int16))
    assert order.tolist() == [1, 3, 0, 2]
    order, _ = tile_order(means[::-1].copy(), np.array([1, 0, 1, 0], np.int16))
    assert order.tolist() == [3, 1, 2, 0]


def test_tile_boxes_are_numpys_reduceat_and_in_tile_order_joins_parts_in_place():
    """build_tiles' boxes in one numba pass (tiles._run_boxes) against numpy's reduceat, runs of one row among them;
    in_tile_order of several parts: the tile order of their concatenation, each row moved with its keyframe."""
    from xyzcyl.runtime.tiles import _run_boxes, in_tile_order, run_boxes_reference

    rng = np.random.default_rng(7)
    g, kf = _street(rng)
    lone = g.slice(0, 1).transformed(np.array([[1, 0, 0, 500], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    g = Gaussians.joined(**{f: np.concatenate([getattr(g, f), getattr(lone, f)]) for f in
                            ("means", "quats", "log_scales", "opacity_logits", "sh")})     # a tile of one
    kf = np.r_[kf, kf[:1]]
    order, cells = tile_order(g.means, kf)
    t = g.subset(order)
    starts = np.r_[0, np.flatnonzero(np.any(cells[1:] != cells[:-1], axis=1)) + 1]
    stops = np.r_[starts[1:], len(t)]
    assert (stops - starts).min() == 1 < (stops - starts).max()
    for got, want in zip(_run_boxes(t.means, t.log_scales, starts, stops), run_boxes_reference(t.means, t.log_scales,
                                                                                                  starts)):
        np.testing.assert_array_equal(got, want)
    parts = [g.slice(0, 1000), g.slice(1000, 1001), g.slice(1001, len(g))]
    joined, kf_t, tiles = in_tile_order(parts, kf, 4)
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(joined, f), getattr(t, f), err_msg=f)
    np.testing.assert_array_equal(kf_t, kf[order])
    assert [(x.cell, x.start, x.count, x.lo, x.hi) for x in tiles.tiles] == \
        [(x.cell, x.start, x.count, x.lo, x.hi) for x in build_tiles(t, cells)]


@pytest.mark.parametrize("name", list(_cameras()))
def test_a_tile_left_out_changes_no_pixel(name):
    """Drawing only the tiles `visible` gives is drawing every tile (exactly: the renderer culls each of the left-out
    Gaussians itself), and a narrow camera leaves most tiles out; wide lenses and panoramas keep every tile."""
    rng = np.random.default_rng(11)
    g, kf = _street(rng)
    order, cells = tile_order(g.means, kf)
    g = g.subset(order)
    tiles = Tiles(build_tiles(g, cells), kf[order], 4, source=g)
    cam = _cameras()[name]
    seen = tiles.visible(cam)
    every = render([tiles.gaussians(t) for t in range(len(tiles))], cam, background=(0.1, 0.2, 0.3))
    some = render([tiles.gaussians(t) for t in seen] or [Gaussians.empty()], cam, background=(0.1, 0.2, 0.3))
    for a, b in ((every.rgb, some.rgb), (every.alpha, some.alpha), (every.depth, some.depth)):
        np.testing.assert_array_equal(a, b)
    assert every.alpha.max() > 0.5                       # the camera sees the street
    if name in ("fisheye_190", "equirect"):
        assert seen == list(range(len(tiles)))
    else:
        assert len(seen) < 0.75 * len(tiles), (name, len(seen), len(tiles))
    if name == "narrow":        # at x = -50 looking along +x: no tile behind it (x < -50 m)
        assert min(tiles.tiles[t].cell[0] for t in seen) == -2


def _drive_scene(rng) -> Scene:
    g, kf = _street(rng)
    drive = _drive([-60.0, -20.0, 20.0, 60.0], [0.0, 1.0, 2.0, 3.0], [0, 1, 2, 3])
    return Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive, keyframe_of=kf)


def test_a_scene_folder_is_read_tile_by_tile_and_draws_the_same(tmp_path):
    here = _drive_scene(np.random.default_rng(12))
    assert here.tiles is not None and not here.tiles.lazy and len(here.tiles) > 10
    here.save(tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "scene.json").read_text())
    assert meta["tiles"]["size_m"] == TILE_M and len(meta["tiles"]["tiles"]) == len(here.tiles)
    there = Scene.load(tmp_path / "s")
    assert there.tiles.lazy and there.tiles.held_bytes == 0
    assert there.__dict__["_gaussians"] is None                    # nothing read whole
    assert there.bbox() == meta["bbox"] == here.bbox()
    cams = _cameras()
    for name in ("side", "back"):
        a = here.render(cams[name], background=(0.0, 0.0, 0.0))
        b = there.render(cams[name], background=(0.0, 0.0, 0.0))
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    # only the tiles those views see were read
    read = {key[0] for key in there.tiles._cache}
    assert 0 < len(read) < len(there.tiles)
    assert read <= {t for n in ("side", "back") for t in here.tiles.visible(cams[n])}
    assert there.__dict__["_gaussians"] is None
    # asked for all of it (an export, the PLY download), the whole set is read once; the tiles are then its slices
    np.testing.assert_array_equal(there.gaussians.means, here.gaussians.means)
    np.testing.assert_array_equal(there.keyframe_of, here.keyframe_of)
    assert not there.tiles.lazy and there.tiles.held_bytes == 0
    # saved again without reading it whole: the same file
    again = Scene.load(tmp_path / "s")
    again.save(tmp_path / "t")
    assert (tmp_path / "t" / "scene.ply").read_bytes() == (tmp_path / "s" / "scene.ply").read_bytes()
    assert again.__dict__["_gaussians"] is None


def test_the_tile_cache_keeps_to_its_budget(tmp_path):
    _drive_scene(np.random.default_rng(13)).save(tmp_path / "s")
    scene = Scene.load(tmp_path / "s")
    tiles = scene.tiles
    one = max(t.count for t in tiles.tiles) * (3 + 4 + 3 + 1 + 3) * 4        # float32 fields of the largest tile
    tiles.cache_bytes = 2 * one
    for t in range(len(tiles)):
        tiles.gaussians(t)
        assert tiles.held_bytes <= 2 * one
    assert 1 <= len(tiles._cache) <= 2 * one // min(t.count * 56 for t in tiles.tiles)
    assert list(tiles._cache)[-1] == (len(tiles) - 1,)                 # the last used is kept
    tiles.cache_bytes = 1                                             # less than any tile: still the last one kept
    tiles.gaussians(0)
    assert list(tiles._cache) == [(0,)]


def test_rows_of_a_ply_read_alone(tmp_path):
    g = random_gaussians(np.random.default_rng(14), 50, degree=1)
    g.save_ply(tmp_path / "g.ply")
    part = Gaussians.load_ply_rows(tmp_path / "g.ply", 7, 31)
    whole = Gaussians.load_ply(tmp_path / "g.ply")
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(part, f), getattr(whole, f)[7:31])
    assert len(Gaussians.load_ply_rows(tmp_path / "g.ply", 50, 50)) == 0
    # every field its own writeable array, a run of one row too (a read-only one is another numba specialisation
    # of the projection: a second compile in a running service)
    for rows in (part, Gaussians.load_ply_rows(tmp_path / "g.ply", 3, 4)):
        assert all(getattr(rows, f).flags.writeable for f in ("means", "quats", "log_scales", "opacity_logits", "sh"))
    with pytest.raises(GaussianError, match="outside the file's 50") as e:
        Gaussians.load_ply_rows(tmp_path / "g.ply", 40, 51)
    assert e.value.field == "element vertex"
    data = (tmp_path / "g.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(data[:-100])
    with pytest.raises(GaussianError, match="truncated"):
        Gaussians.load_ply_rows(tmp_path / "short.ply", 40, 50)


def _edit(folder, change):
    p = folder / "scene.json"
    meta = json.loads(p.read_text())
    change(meta)
    p.write_text(json.dumps(meta))


@pytest.mark.parametrize("change, field, why", [
    (lambda m: m["tiles"].update(size_m=0), "tiles.size_m", "> 0"),
    (lambda m: m["tiles"].update(tiles={}), "tiles.tiles", "a list"),
    (lambda m: m["tiles"]["tiles"][1].update(start=m["tiles"]["tiles"][1]["start"] + 1), "tiles.tiles[1].start",
     "in order"),
    (lambda m: m["tiles"]["tiles"].pop(), "tiles.tiles", "scene.ply holds"),
    (lambda m: m["tiles"]["tiles"][0].pop("bounds"), "tiles.tiles[0]", "bounds"),
    (lambda m: m["tiles"]["tiles"][0].update(max_log_scale=float("nan")), "tiles.tiles[0]", "finite"),
])
def test_a_broken_tiles_block_is_refused_naming_the_entry(tmp_path, change, field, why):
    _drive_scene(np.random.default_rng(15)).save(tmp_path / "s")
    _edit(tmp_path / "s", change)
    with pytest.raises(SceneError, match=why) as e:
        Scene.load(tmp_path / "s")
    assert e.value.field == field


def test_a_tile_whose_box_does_not_hold_it_or_whose_keyframes_go_back_is_refused(tmp_path):
    _drive_scene(np.random.default_rng(16)).save(tmp_path / "s")
    # a box that leaves out some of its Gaussians would hide them from views that see them: refused when read
    _edit(tmp_path / "s", lambda m: m["tiles"]["tiles"][0]["bounds"].update(max=m["tiles"]["tiles"][0]["bounds"]
                                                                             ["min"]))
    scene = Scene.load(tmp_path / "s")
    with pytest.raises(TileError, match="outside its box") as e:
        scene.tiles.gaussians(0)
    assert e.value.field == "tiles[0].bounds"
    # keyframe_of must increase within each tile (a tile's keyframe is one run)
    _drive_scene(np.random.default_rng(16)).save(tmp_path / "u")
    kf = np.load(tmp_path / "u" / "keyframe_of.npy")
    meta = json.loads((tmp_path / "u" / "scene.json").read_text())
    t = next(i for i, e in enumerate(meta["tiles"]["tiles"]) if len(set(kf[e["start"]:e["start"] + e["count"]])) > 1)
    e0 = meta["tiles"]["tiles"][t]
    kf[e0["start"]:e0["start"] + e0["count"]] = kf[e0["start"]:e0["start"] + e0["count"]][::-1]
    np.save(tmp_path / "u" / "keyframe_of.npy", kf)
    with pytest.raises(SceneError, match="must increase") as e:
        Scene.load(tmp_path / "u")
    assert e.value.field == f"tiles.tiles[{t}]"


def test_a_folder_written_before_the_tiles_is_read_whole_and_tiled(tmp_path):
    here = _drive_scene(np.random.default_rng(17))
    here.save(tmp_path / "s")
    _edit(tmp_path / "s", lambda m: m.pop("tiles"))
    old = Scene.load(tmp_path / "s")
    assert old.tiles is not None and not old.tiles.lazy
    cam = _cameras()["ahead"]
    for x, y in zip(here.render(cam), old.render(cam)):
        np.testing.assert_array_equal(x, y)


def test_a_tiled_view_equals_the_layers_drawn_from_every_tile():
    """Scene's layers through the tiles it sees equal the same layers drawn from all of them (so the tiles change
    what a view reads, not what it shows)."""
    scene = _drive_scene(np.random.default_rng(18))
    cam = _cameras()["back"]
    a = scene.render(cam)
    every = list(range(len(scene.tiles)))
    scene.tiles.visible = lambda camera, **o: every
    b = scene.render(cam)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert len(Tiles.visible(scene.tiles, cam)) < len(every)


def test_beyond_the_horizon_a_view_draws_its_primary_keyframe_alone(tmp_path):
    """Tiles farther than HORIZON_M from the camera give the view's primary keyframe's Gaussians only (each
    keyframe's far background sphere, runtime.detail's far_depth, is drawn once, not once per keyframe), and a
    folder's far tile is read for those rows alone."""
    rng = np.random.default_rng(19)
    near = random_gaussians(rng, 200, lo=(5, -10, 0), hi=(60, 10, 5))                  # ahead, within the horizon
    far = random_gaussians(rng, 400, lo=(HORIZON_M + 60, -40, 0), hi=(HORIZON_M + 100, 40, 30))
    g = Gaussians(*(np.concatenate([getattr(near, f), getattr(far, f)]) for f in
                    ("means", "quats", "log_scales", "opacity_logits", "sh")))
    kf = np.r_[np.zeros(100), np.ones(100), np.zeros(200), np.ones(200)].astype(np.int16)  # each half of each
    drive = _drive([0.0, 30.0], [0.0, 1.0], [0, 1])
    scene = Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive, keyframe_of=kf)
    cam = pinhole(96, 64, 50.0, c2w=look_at([0, 0, 1.5], [100, 0, 1.5]))
    assert scene.primary_keyframe(cam) == 0
    rgb, _, alpha = scene.render(cam)
    # by hand: keyframe 0 everywhere, then keyframe 1 within the horizon, behind it
    first = render([near.subset(np.arange(200) < 100), far.subset(np.arange(400) < 200)], cam)
    by_hand = render(near.subset(np.arange(200) >= 100), cam, behind=first)
    np.testing.assert_array_equal(rgb, by_hand.rgb)
    np.testing.assert_array_equal(alpha, by_hand.alpha)
    # keyframe 1's far Gaussians would show: the horizon is what left them out
    every = render(far.subset(np.arange(400) >= 200), cam, behind=render(
        [near.subset(np.arange(200) < 100), far.subset(np.arange(400) < 200)], cam))
    assert np.abs(every.rgb - by_hand.rgb).max() > 0.05
    # from its folder: the far tiles' keyframe-0 rows alone are read
    scene.save(tmp_path / "s")
    back = Scene.load(tmp_path / "s")
    for x, y in zip(back.render(cam), scene.render(cam)):
        np.testing.assert_array_equal(x, y)
    far_tiles = {t for t, tile in enumerate(back.tiles.tiles) if tile.lo[0] > HORIZON_M}
    assert far_tiles and {key for key in back.tiles._cache if key[0] in far_tiles} == {(t, 0, 1) for t in far_tiles}
