"""A drive's viewpoint chunks (runtime.viewpoints): through a scene folder and back, read when first used and kept
in a small cache, and the refusals of a scene.json block that does not match its files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl.runtime import viewpoints as vp
from xyzcyl.runtime.rig import load_rig
from xyzcyl.runtime.scene import Scene, SceneError
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import pose


def _scene(n_chunks=3) -> Scene:
    rng = np.random.default_rng(5)
    g = random_gaussians(rng, 30)
    drive = {"frames": n_chunks, "keyframes": list(range(n_chunks)), "timestamp_s": 0.0,
             "times_s": [float(t) for t in range(n_chunks)], "ego_to_world": np.eye(4).tolist(),
             "trajectory": [pose(5.0 * x, 0.0) for x in range(n_chunks)], "tracks": 0}
    chunks = vp.Viewpoints.build([[k] for k in range(n_chunks)],
                                 [random_gaussians(rng, 4 + k) for k in range(n_chunks)])
    return Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive,
                 keyframe_of=np.arange(30, dtype=np.int16) % n_chunks, viewpoints=chunks)


def test_chunks_through_the_scene_folder_read_when_used(tmp_path, monkeypatch):
    scene = _scene()
    scene.save(tmp_path / "s")
    meta = json.loads((tmp_path / "s" / "scene.json").read_text())
    assert [c["count"] for c in meta["viewpoints"]["chunks"]] == [4, 5, 6]
    assert meta["viewpoints"]["count"] == 15
    assert all((tmp_path / "s" / c["file"]).is_file() for c in meta["viewpoints"]["chunks"])
    back = Scene.load(tmp_path / "s")
    assert back.viewpoints.count == 15 and back.viewpoints.group_of(2) == 2
    assert not back.viewpoints._cache                          # nothing read before a view needs it
    monkeypatch.setattr(vp, "CACHE_CHUNKS", 2)
    for i in range(3):
        np.testing.assert_array_equal(back.viewpoints.gaussians(i).means, scene.viewpoints.gaussians(i).means)
    assert list(back.viewpoints._cache) == [1, 2]              # the last two used
    assert back.viewpoints.chunks[1].bbox == scene.viewpoints.chunks[1].bbox


def test_chunks_on_disk_are_linked_into_a_new_folder_and_survive_a_second_save(tmp_path, monkeypatch):
    """A scene whose chunks lie on disk (a loaded folder, or a drive's spilled chunks) writes them by a hard link where
    it can (viewpoints.link_or_copy), a copy where the file system refuses one, and saving again (into the same
    folder: the link is its own file) keeps them whole."""
    _scene().save(tmp_path / "a")
    src = Scene.load(tmp_path / "a")
    want = [src.viewpoints.gaussians(i).means.copy() for i in range(3)]
    src.save(tmp_path / "b")
    name = src.viewpoints.chunks[0].file
    assert (tmp_path / "b" / name).samefile(tmp_path / "a" / name)          # one file, not a copy
    src.save(tmp_path / "b")                                                 # again: links onto themselves
    assert (tmp_path / "b" / name).stat().st_nlink == 2

    def no_link(a, b):
        raise OSError(18, "Invalid cross-device link")

    monkeypatch.setattr(vp.os, "link", no_link)
    src.save(tmp_path / "c")
    assert not (tmp_path / "c" / name).samefile(tmp_path / "a" / name)     # copied
    for d in ("b", "c"):
        back = Scene.load(tmp_path / d)
        for i in range(3):
            np.testing.assert_array_equal(back.viewpoints.gaussians(i).means, want[i])


@pytest.mark.parametrize("edit, field", [
    (lambda m, d: m["viewpoints"]["chunks"][0].update(count=99), "viewpoints.chunks[0].count"),
    (lambda m, d: m["viewpoints"]["chunks"][1].update(keyframes=[0]), "viewpoints.chunks[1].keyframes"),
    (lambda m, d: m["viewpoints"]["chunks"].pop(), "viewpoints.chunks"),
    (lambda m, d: m["viewpoints"]["chunks"][0].update(file="../scene.ply"), "viewpoints.chunks[0].file"),
    (lambda m, d: (d / m["viewpoints"]["chunks"][2]["file"]).unlink(), "viewpoints.chunks[2].file"),
    (lambda m, d: m.update(viewpoints={"chunks": "x"}), "viewpoints.chunks"),
    (lambda m, d: m.pop("keyframe_of"), "viewpoints"),
    (lambda m, d: m["viewpoints"]["chunks"][1].update(viewpoint=2), "viewpoints.chunks[1].viewpoint"),
    (lambda m, d: m["viewpoints"]["chunks"][1].update(viewpoint="0"), "viewpoints.chunks[1].viewpoint"),
    # keyframe 1 is of group 0, so it cannot be the first of chunk 2's group
    (lambda m, d: [m["viewpoints"]["chunks"][i].update(viewpoint=v) for i, v in ((1, 0), (2, 1))],
     "viewpoints.chunks[2].viewpoint"),
])
def test_a_viewpoints_block_that_does_not_match_its_files_is_refused(tmp_path, edit, field):
    d = tmp_path / "s"
    _scene().save(d)
    meta = json.loads((d / "scene.json").read_text())
    edit(meta, d)
    (d / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError) as e:
        Scene.load(d)
    assert e.value.field == field, str(e.value)


def test_viewpoint_groups_through_the_scene_folder_and_a_folder_written_before_them(tmp_path):
    d = tmp_path / "s"
    _scene().save(d)
    meta = json.loads((d / "scene.json").read_text())
    assert [c["viewpoint"] for c in meta["viewpoints"]["chunks"]] == [0, 1, 2]
    meta["viewpoints"]["chunks"][2]["viewpoint"] = 1                # keyframes 1 and 2: one viewpoint group
    (d / "scene.json").write_text(json.dumps(meta))
    back = Scene.load(d).viewpoints
    assert back.groups() == [0, 1] and back.group_keyframes(1) == [1, 2]
    for c in meta["viewpoints"]["chunks"]:                          # written before: each chunk its own group
        c.pop("viewpoint")
    (d / "scene.json").write_text(json.dumps(meta))
    assert Scene.load(d).viewpoints.groups() == [0, 1, 2]


def test_a_chunk_changed_after_loading_is_an_error_naming_it(tmp_path):
    d = tmp_path / "s"
    _scene().save(d)
    back = Scene.load(d)
    random_gaussians(np.random.default_rng(1), 2).save_ply(d / back.viewpoints.chunks[0].file)
    with pytest.raises(vp.ViewpointError, match="group_000.ply"):
        back.viewpoints.gaussians(0)


def test_spread3_puts_each_bit_at_every_third_place():
    """The Morton code's magic numbers (viewpoints._spread3) against the loop over the bits, every 10-bit value."""
    from xyzcyl.runtime.viewpoints import _spread3

    for q in range(1024):
        assert _spread3(q) == sum(((q >> b) & 1) << (3 * b) for b in range(10)), q


def test_spatial_order_is_the_morton_order_of_the_points_in_their_box():
    """spatial_order against a plain definition: each point's 10-bit cell per axis in the box of all points, the
    bits interleaved (x lowest), sorted, ties in index order; and it keeps neighbours together."""
    from xyzcyl.runtime.viewpoints import SPATIAL_BITS, spatial_order

    rng = np.random.default_rng(4)
    pts = np.concatenate([rng.uniform(-50, 80, (3000, 3)), np.repeat(rng.uniform(0, 1, (5, 3)), 40, axis=0)])
    pts = pts.astype(np.float32)
    m = pts.astype(np.float64)
    lo, hi = m.min(0), m.max(0)
    top = 2 ** SPATIAL_BITS - 1
    codes = []
    for p in m:
        q = [min(int((p[a] - lo[a]) * ((top + 1) / max(hi[a] - lo[a], 1e-9))), top) for a in range(3)]
        codes.append(sum(((q[a] >> b) & 1) << (3 * b + a) for b in range(SPATIAL_BITS) for a in range(3)))
    ref = sorted(range(len(m)), key=lambda i: (codes[i], i))
    np.testing.assert_array_equal(spatial_order(pts), ref)
    assert len(spatial_order(np.zeros((0, 3), np.float32))) == 0
    # runs of 64 in that order span about half as far as runs of the random input (a run holds 1/47 of the
    # points: a box of ~0.36 of the side, where a random run spans nearly all of it)
    o = spatial_order(pts)
    span = lambda p: np.mean([np.ptp(p[i:i + 64], axis=0).max() for i in range(0, len(p) - 64, 64)])  # noqa: E731
    assert span(pts[o]) < 0.6 * span(pts)
