"""A drive's camera layers (runtime.cameralayers): the files and their runs, the scene.json block and its refusals,
the split cells' quarters and the PLY written from parts without joining them, and a drive reconstructed with the
shipped model: each keyframe's cameras' layers, chosen for a view that stands at one of them and drawn first."""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile

import numpy as np
import pytest
from xyzcyl.runtime.cameralayers import (
    CAMERA_LAYER_DEG,
    CAMERA_LAYER_M,
    CameraLayerError,
    CameraLayers,
)
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.render.gaussians import ply_rows_layout, save_ply_parts
from xyzcyl.testing.drives import pose as _pose
from xyzcyl.testing.drives import write_drive


def _random(n: int, seed: int) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(means=rng.normal(size=(n, 3)).astype(np.float32),
                     quats=rng.normal(size=(n, 4)).astype(np.float32),
                     log_scales=rng.uniform(-4, -1, (n, 3)).astype(np.float32),
                     opacity_logits=rng.normal(size=n).astype(np.float32),
                     sh=rng.normal(size=(n, 1, 3)).astype(np.float32))


def _rows(g: Gaussians) -> np.ndarray:
    return np.concatenate([g.means, g.quats, g.log_scales, g.opacity_logits[:, None], g.sh.reshape(len(g), 3 * g.sh.shape[1])], 1)


def block_file(layers):
    """The first keyframe's layer file (relative to the scene folder)."""
    return layers.keyframes[0].file


def _joined(parts):
    return np.concatenate([_rows(p) for p in parts]) if parts else np.zeros((0, 14), np.float32)


def test_save_ply_parts_writes_the_bytes_of_the_joined_set(tmp_path):
    parts = [_random(5, 0), _random(0, 1), _random(300_001, 2)]      # an empty part; a part over one write block
    save_ply_parts(tmp_path / "parts.ply", parts)
    joined = Gaussians(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                         ("means", "quats", "log_scales", "opacity_logits", "sh")))
    joined.save_ply(tmp_path / "joined.ply")
    assert (tmp_path / "parts.ply").read_bytes() == (tmp_path / "joined.ply").read_bytes()
    with pytest.raises(ValueError, match="SH degree"):
        save_ply_parts(tmp_path / "x.ply", [_random(2, 0), Gaussians.empty(sh_degree=1)])
    # without normals: three columns fewer, the same Gaussians read back (whole, by rows, by taking rows)
    save_ply_parts(tmp_path / "bare.ply", parts[:1] + parts[2:], normals=False)
    n, dtype, _ = ply_rows_layout(tmp_path / "bare.ply")
    assert n == 300_006 and dtype.names[:4] == ("x", "y", "z", "f_dc_0") and "nx" not in dtype.names
    assert dtype.itemsize == ply_rows_layout(tmp_path / "joined.ply")[1].itemsize - 12
    for got in (Gaussians.load_ply(tmp_path / "bare.ply"), Gaussians.load_ply_rows(tmp_path / "bare.ply", 0, n),
                Gaussians.load_ply_take(tmp_path / "bare.ply", np.arange(n))):
        np.testing.assert_array_equal(_rows(got), _rows(joined))


def test_layers_are_written_by_camera_and_read_back_by_run(tmp_path):
    """Each keyframe's file holds its cameras' parts camera after camera; layer(k, c) is camera c's run (an empty
    camera: no rows); through a scene folder (linked, not copied where it can be) and scene.json's block."""
    tmp = tempfile.TemporaryDirectory(dir=tmp_path)
    layers = CameraLayers.spill(["a", "b", "c"], tmp)
    given = [[[_random(7, 1), _random(3, 2)], [], [_random(11, 3)]],
             [[_random(2, 4)], [_random(5, 5)], []]]
    for k in given:
        layers.add(k)
    assert len(layers) == 2 and layers.count == 7 + 3 + 11 + 2 + 5
    for k, cams in enumerate(given):
        for c, parts in enumerate(cams):
            np.testing.assert_array_equal(_rows(layers.layer(k, c)), _joined(parts))
    folder = tmp_path / "scene"
    folder.mkdir()
    layers.save(folder)
    assert "nx" not in ply_rows_layout(folder / block_file(layers))[1].names     # written without normals
    block = json.loads(json.dumps(layers.to_json()))
    assert block["keyframes"][0]["runs"] == [[0, 10], [10, 0], [10, 11]]
    back = CameraLayers.from_json(block, folder, 2, ["a", "b", "c"])
    for k, cams in enumerate(given):
        for c, parts in enumerate(cams):
            np.testing.assert_array_equal(_rows(back.layer(k, c)), _joined(parts))


def test_a_failed_write_is_raised_when_the_layers_are_finished(tmp_path, monkeypatch):
    """add writes on a thread of its own: what the write raised comes out of finish (and so out of the
    reconstruction), not lost with the thread."""
    from xyzcyl.runtime import cameralayers

    def fail(path, parts, normals=True, direct=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cameralayers, "save_ply_parts", fail)
    layers = CameraLayers.spill(["a"], tempfile.TemporaryDirectory(dir=tmp_path))
    layers.add([[_random(3, 0)]])
    with pytest.raises(OSError, match="No space"):
        layers.finish()


def _saved(tmp_path) -> tuple[dict, object]:
    tmp = tempfile.TemporaryDirectory(dir=tmp_path)
    layers = CameraLayers.spill(["a", "b"], tmp)
    layers.add([[_random(4, 0)], [_random(6, 1)]])
    folder = tmp_path / "scene"
    folder.mkdir()
    layers.save(folder)
    return layers.to_json(), folder


@pytest.mark.parametrize("edit, field", [
    (lambda b: b.update(cameras=["a", "x"]), "camera_layers.cameras"),
    (lambda b: b.update(keyframes=[]), "camera_layers.keyframes"),
    (lambda b: b["keyframes"][0].update(file="../../etc/passwd"), "camera_layers.keyframes[0].file"),
    (lambda b: b["keyframes"][0].update(file="cameras/missing.ply"), "camera_layers.keyframes[0].file"),
    (lambda b: b["keyframes"][0].update(runs=[[0, 4]]), "camera_layers.keyframes[0].runs"),
    (lambda b: b["keyframes"][0].update(runs=[[0, 4], [5, 6]]), "camera_layers.keyframes[0].runs"),
    (lambda b: b["keyframes"][0].update(runs=[[0, 4], [4, 7]]), "camera_layers.keyframes[0].runs"),
    (lambda b: b["keyframes"][0].update(runs=[[0, -1], [-1, 11]]), "camera_layers.keyframes[0].runs"),
    (lambda b: b["keyframes"][0].update(runs=[[0, True], [1, 9]]), "camera_layers.keyframes[0].runs"),
])
def test_a_bad_block_is_refused_naming_the_field(tmp_path, edit, field):
    block, folder = _saved(tmp_path)
    edit(block)
    with pytest.raises(CameraLayerError) as e:
        CameraLayers.from_json(block, folder, 1, ["a", "b"])
    assert e.value.field == field


def test_expand_split_parts_are_expand_splits_gaussians_in_order():
    """The parts a camera layer is written from are expand_split's Gaussians, in its order (the cells that do not
    split, then the quarters)."""
    from xyzcyl.runtime.detail import CameraDetail, SplitCells, expand_split, expand_split_parts

    n = 40
    rng = np.random.default_rng(3)
    g = _random(n, 7)
    index = np.array([1, 4, 5, 20, 39])
    split = SplitCells(index=index, means=rng.normal(size=(5, 4, 3)).astype(np.float32),
                       colours=rng.uniform(size=(5, 4, 3)).astype(np.float32))
    d = dataclasses.replace(_detail_stub(CameraDetail), split=split)
    for keep in (np.ones(n, bool), rng.uniform(size=n) < 0.5, np.zeros(n, bool)):
        parts = expand_split_parts(g, d, keep)
        np.testing.assert_array_equal(_joined(parts), _rows(expand_split(g, d, keep)))
    d0 = dataclasses.replace(d, split=None)
    np.testing.assert_array_equal(_joined(expand_split_parts(g, d0, keep)), _rows(g.subset(keep)))


def _detail_stub(cls):
    """A CameraDetail whose maps the split expansion does not read (its ``split`` set by the caller)."""
    fields = {f.name: None for f in dataclasses.fields(cls)}
    return cls(**fields)


@pytest.fixture(scope="module")
def shipped():
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.testing import SHIPPED_MODEL

    return Reconstructor.load(SHIPPED_MODEL, threads=2)


def test_a_drive_keeps_each_keyframes_camera_layers_and_a_view_at_a_camera_draws_its_first(
        tmp_path, shipped, monkeypatch):
    """Two keyframes 3 m apart: a layer per keyframe and camera, each the camera's cells that no other camera of
    its keyframe saw through (at least the cells the scene keeps of it, which the dedupe thinned); a view at a
    keyframe's camera draws that layer first (with the moving objects), one a metre away or turned past
    CAMERA_LAYER_DEG draws none; through the scene folder and back; a folder without the block draws as before."""
    from xyzcyl.runtime import scene as S
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.scene import Scene, rig_camera

    E = np.array(_pose(7, 3, 20))
    drive = load_drive(write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5]))
    scene = reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8))
    layers = scene.camera_layers
    names = scene.rig.names
    assert len(layers) == 2 and layers.cameras == tuple(names)
    assert scene.counts["camera_layer_gaussians"] == layers.count
    for k in (0, 1):
        sizes = [len(layers.layer(k, c)) for c in range(len(names))]
        assert all(s > 0 for s in sizes), sizes
        assert sum(sizes) >= int((scene.keyframe_of == k).sum()), (sizes, k)

    T1 = np.asarray(drive.relative(1))
    cam = rig_camera(scene.rig.cameras[2])
    at = dataclasses.replace(cam, cam_to_ego=T1 @ np.asarray(cam.cam_to_ego))
    assert scene.primary_keyframe(at) == 1
    np.testing.assert_array_equal(_rows(scene.camera_layer(at, 1)), _rows(layers.layer(1, 2)))
    away = np.array(at.cam_to_ego)
    away[:3, 3] += away[:3, 0] * (CAMERA_LAYER_M + 0.25)          # sideways, past the distance
    assert scene.camera_layer(dataclasses.replace(at, cam_to_ego=away), 1) is None
    a = np.radians(CAMERA_LAYER_DEG + 5)         # pitched about its own x axis, in place: no camera looks there
    turned = np.array(at.cam_to_ego)
    turned[:3, :3] = turned[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    assert scene.camera_layer(dataclasses.replace(at, cam_to_ego=turned), 1) is None

    drawn = []
    real = S.render

    def spy(parts, camera, **kw):
        drawn.append([len(p) for p in parts])
        return real(parts, camera, **kw)

    monkeypatch.setattr(S, "render", spy)
    rgb, depth, alpha = scene.render(at, time_s=drive.frames[1].timestamp_s)
    assert drawn[0] == [len(layers.layer(1, 2))], drawn            # the layer alone first (nothing moves here)
    assert np.isfinite(rgb).all() and alpha.max() > 0.5
    monkeypatch.setattr(S, "render", real)

    scene.save(tmp_path / "scene")
    back = Scene.load(tmp_path / "scene")
    np.testing.assert_array_equal(_rows(back.camera_layers.layer(1, 2)), _rows(layers.layer(1, 2)))
    again = back.render(at, time_s=drive.frames[1].timestamp_s)
    np.testing.assert_array_equal(again[0], rgb)
    meta = json.loads((tmp_path / "scene" / "scene.json").read_text())
    del meta["camera_layers"]
    (tmp_path / "scene" / "scene.json").write_text(json.dumps(meta))
    before = Scene.load(tmp_path / "scene")
    assert before.camera_layers is None and before.camera_layer(at, 1) is None
    assert np.isfinite(before.render(at, time_s=drive.frames[1].timestamp_s)[0]).all()


def _same_chunk(rows: np.ndarray, whole: np.ndarray, head: int) -> None:
    """A chunk of layer rows against the chunk written whole: its first ``head`` rows (the model's Gaussians) the
    same, in order; the rest the same rows in another order (spatial_order), and not already in the whole's."""
    np.testing.assert_array_equal(rows[:head], whole[:head])
    a, b = rows[head:], whole[head:]
    np.testing.assert_array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])
    assert not np.array_equal(a, b)


def test_a_drives_chunks_are_rows_of_its_camera_layers_the_same_gaussians_as_written_whole(
        tmp_path, shipped, monkeypatch):
    """A keyframe's kept cells are cells its cameras kept, so the fusion reads them from the keyframe's camera
    layer file (not spilled again), and a chunk is written as the model's Gaussians and rows of that file
    (runtime.viewpoints.LayerRows): the scene's shared Gaussians bit for bit those of cells spilled and read back,
    each chunk the same Gaussians as the chunk written whole (the fusion's own cells, own_of: the model's first, in
    the same order; the cells in spatial order), in memory and through the scene folder; every refusal of a chunk's
    layer_rows block names its field."""
    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import load_drive, reconstruct_drive
    from xyzcyl.runtime.scene import Scene, SceneError
    from xyzcyl.runtime.viewpoints import ViewpointError

    E = np.array(_pose(7, 3, 20))
    drive = load_drive(write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5]))
    # stride 10 tiles the 800x450 images in whole blocks, so cells split into quarters (a low split threshold:
    # many), which a layer holds after the cells that do not split
    opts = DetailOptions(stride=10, split=0.005)
    quartered = []
    real = D._layer_rows

    def spy(seen, d, start):
        quartered.append(d.split is not None and bool(seen[d.split.index].any()))
        return real(seen, d, start)

    monkeypatch.setattr(D, "_layer_rows", spy)
    scene = reconstruct_drive(shipped, drive, detail=opts)
    assert any(quartered)
    # no cell found in the layers (the fallback): the cells spilled and read back, the chunks written whole
    monkeypatch.setattr(D, "_layer_rows", lambda seen, d, start: np.full(len(seen), -1, np.int64))
    whole = reconstruct_drive(shipped, drive, detail=opts)
    np.testing.assert_array_equal(_rows(scene.gaussians), _rows(whole.gaussians))     # the shared set, bit for bit
    vp, wv = scene.viewpoints, whole.viewpoints
    assert len(vp) == len(wv) == 2
    for i in range(2):
        c = vp.chunks[i]
        assert c.rows is not None and c.layer == scene.camera_layers.keyframes[i].file and c.layer_count > 0
        assert wv.chunks[i].rows is None and c.count == wv.chunks[i].count and c.bbox == wv.chunks[i].bbox
        assert c.count > c.layer_count                   # the model's Gaussians in its PLY, then the rows
        _same_chunk(_rows(vp.gaussians(i)), _rows(wv.gaussians(i)), c.count - c.layer_count)

    scene.save(tmp_path / "scene")
    back = Scene.load(tmp_path / "scene")
    for i in range(2):
        _same_chunk(_rows(back.viewpoints.gaussians(i)), _rows(wv.gaussians(i)), vp.chunks[i].count - vp.chunks[i].layer_count)
    meta = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert meta["viewpoints"]["chunks"][0]["layer_rows"]["file"] == vp.chunks[0].rows

    def broken(edit, field, rows=None):
        folder = tmp_path / f"broken_{len(list(tmp_path.glob('broken_*')))}"
        shutil.copytree(tmp_path / "scene", folder)
        m = json.loads((folder / "scene.json").read_text())
        edit(m["viewpoints"]["chunks"][1]["layer_rows"])
        (folder / "scene.json").write_text(json.dumps(m))
        if rows is not None:
            np.save(folder / vp.chunks[1].rows, rows)
        return folder

    for edit, field in [(lambda b: b.update(file="../../etc/passwd"), "layer_rows.file"),
                        (lambda b: b.update(file="viewpoints/missing.npy"), "layer_rows.file"),
                        (lambda b: b.update(of="/etc/passwd"), "layer_rows.of"),
                        (lambda b: b.update(of="cameras/missing.ply"), "layer_rows.of"),
                        (lambda b: b.update(count=-1), "layer_rows.count"),
                        (lambda b: b.update(count=b["count"] + 1), "layer_rows.file")]:
        with pytest.raises(SceneError) as e:
            Scene.load(broken(edit, field))
        assert e.value.field == f"viewpoints.chunks[1].{field}", (field, e.value)
    # a row past the layer file's end: refused when the chunk is read, naming the chunk (a view answers it)
    n = vp.chunks[1].layer_count
    bad = Scene.load(broken(lambda b: None, "rows", rows=np.full(n, 10**8, np.int32)))
    with pytest.raises(ViewpointError, match="outside the file"):
        bad.viewpoints.gaussians(1)
