"""Drives (runtime.drive): the drive file and its refusals, keyframes, moving Gaussians into the scene's frame, the
cross-keyframe dedupe against its cell-by-cell reference, and a drive reconstructed end to end with the shipped
model: a still ego posted twice is kept once, a moving one grows the scene with the new ground only."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from xyzcyl.runtime.drive import (
    DriveError,
    VoxelOwners,
    dedupe_frames,
    dedupe_frames_reference,
    inside_boxes,
    is_drive_file,
    load_drive,
    pick_keyframes,
    transform_gaussians,
    viewpoint_origins,
    voxel_levels,
)
from xyzcyl.testing import EXAMPLE_RIG
from xyzcyl.testing.drives import pose as _pose
from xyzcyl.testing.drives import write_drive


def test_a_drive_file_loads_in_the_first_frames_frame(tmp_path):
    p = write_drive(tmp_path, [_pose(100, 50, 30), _pose(101, 50.5, 30), _pose(103, 51, 32)], [10.0, 10.1, 10.3])
    assert is_drive_file(p) and not is_drive_file(EXAMPLE_RIG)
    d = load_drive(p)
    assert len(d) == 3 and [f.timestamp_s for f in d.frames] == [10.0, 10.1, 10.3]
    traj = d.trajectory()
    np.testing.assert_allclose(traj[0], np.eye(4), atol=1e-12)
    # frame 1 in frame 0's ego frame: 1 m east and 0.5 m north of a car facing 30 degrees (ego x forward, y left)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    np.testing.assert_allclose(traj[1][:2, 3], [c * 1 + s * 0.5, -s * 1 + c * 0.5], atol=1e-9)


@pytest.mark.parametrize("case, field", [
    ("no_pose", "frames[1].rig"),
    ("no_time", "frames[1].timestamp_s"),
    ("same_time", "frames[2].timestamp_s"),
    ("backwards", "frames[2].timestamp_s"),
    ("jump", "frames[2].rig"),
    ("cameras", "frames[1].rig"),
    ("bad_rig", "frames[1].rig"),
    ("track_frame", "tracks[0].poses[1].frame"),
    ("track_size", "tracks[0].size"),
])
def test_bad_drives_are_refused_naming_the_frame_and_field(tmp_path, case, field):
    poses = [_pose(0), _pose(1), _pose(2)]
    times = [0.0, 0.1, 0.2]
    edit, tracks = None, None
    if case == "no_pose":
        poses[1] = None
    elif case == "no_time":
        times[1] = None
    elif case == "same_time":
        times[2] = 0.1
    elif case == "backwards":
        times[2] = 0.05
    elif case == "jump":
        poses[2] = _pose(5000.0)                     # 5 km in 0.1 s

    if case == "cameras":
        def edit(i, rig):
            if i == 1:
                rig["cameras"] = rig["cameras"][:5]
    elif case == "bad_rig":
        def edit(i, rig):
            if i == 1:
                rig["cameras"][0]["K"][0][0] = -1.0
    track = {"id": "a", "label": "Car", "size": [4.5, 1.9, 1.6], "stationary": False,
             "poses": [{"frame": 0, "object_to_world": _pose(10)}, {"frame": 1, "object_to_world": _pose(11)}]}
    if case == "track_frame":
        track["poses"][1]["frame"] = 7
        tracks = {"tracks": [track]}
    elif case == "track_size":
        track["size"] = [4.5, 0, 1.6]
        tracks = {"tracks": [track]}
    p = write_drive(tmp_path, poses, times, edit, tracks)
    with pytest.raises(DriveError) as e:
        load_drive(p)
    assert e.value.field == field, str(e.value)
    assert str(tmp_path / ("tracks.json" if field.startswith("tracks") else "drive.json")) in str(e.value)


def test_keyframes_by_distance_and_time(tmp_path):
    # 0.5 m a frame for 10 frames, then still for 30 frames at 10 Hz
    xs = [0.5 * i for i in range(10)] + [4.5] * 30
    p = write_drive(tmp_path, [_pose(x) for x in xs], [0.1 * i for i in range(40)])
    d = load_drive(p, check_images=False)
    keys = pick_keyframes(d, spacing_m=1.5, max_gap_s=2.0)
    assert keys[:4] == [0, 3, 6, 9]                    # every 1.5 m while moving
    assert keys[4:] == [29]                            # then one for the 2 s standing still (9 + 20 frames)
    assert pick_keyframes(d, every=8) == [0, 8, 16, 24, 32]
    # a drive posted at ~2 m spacing is used whole
    p2 = write_drive(tmp_path / "b", [_pose(2.0 * i) for i in range(6)], [0.4 * i for i in range(6)])
    assert pick_keyframes(load_drive(p2, check_images=False)) == list(range(6))


def test_moved_gaussians_render_as_the_moved_camera_sees_the_original():
    """A rigid move of the Gaussians and of the camera together changes nothing in the picture (means, rotations;
    SH degree 0)."""
    from xyzcyl.runtime.camera import Camera, pinhole_K
    from xyzcyl.runtime.render import Gaussians, render

    rng = np.random.default_rng(1)
    n = 400
    f32 = np.float32
    g = Gaussians(rng.normal([8, 0, 1], [2, 2, 1], (n, 3)).astype(f32), rng.normal(size=(n, 4)).astype(f32),
                  rng.uniform(-2.5, -1.0, (n, 3)).astype(f32), rng.normal(size=n).astype(f32),
                  rng.random((n, 1, 3)).astype(f32))
    cam = Camera(K=pinhole_K(60, 60, 39.5, 29.5), cam_to_ego=np.array(
        [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.2], [0, 0, 0, 1]], float), width=80, height=60)
    T = np.array(_pose(3.0, -2.0, 40.0))
    T[2, 3] = 0.5
    a = render(g, cam)
    b = render(transform_gaussians(g, T), cam.replace(cam_to_ego=T @ cam.cam_to_ego))
    # float32 means moved in float64 and rounded back: the pictures agree to float32 rounding of the projections
    np.testing.assert_allclose(b.rgb, a.rgb, atol=2e-4)
    np.testing.assert_allclose(b.alpha, a.alpha, atol=2e-4)


@pytest.mark.parametrize("with_origins", [False, True])
def test_dedupe_frames_matches_its_reference_and_does_not_depend_on_the_order(with_origins):
    rng = np.random.default_rng(5)
    n = 400
    pts = rng.uniform(0, 1.0, (n, 3))                  # dense: many shared voxels at every level
    level = rng.integers(0, 6, n).astype(np.int8)
    frame = rng.integers(0, 4, n)
    # keyframes 0 and 1 one viewpoint (their tie: the earlier), 2 and 3 elsewhere
    origins = viewpoint_origins(np.array([[0, 0, 0], [0.1, 0, 0], [3, 1, 0], [0.5, 4, 0.0]])) if with_origins \
        else None
    keep = dedupe_frames(pts, level, frame, origins)
    np.testing.assert_array_equal(keep, dedupe_frames_reference(pts, level, frame, origins))
    assert 0 < keep.sum() < n
    # keyframes added one at a time, deduping each time, keep what deduping them all at once keeps
    alive = np.zeros(n, bool)
    for f in range(4):
        alive |= frame == f
        idx = np.flatnonzero(alive)
        k = dedupe_frames(pts[idx], level[idx], frame[idx], origins)
        alive[idx[~k]] = False
    np.testing.assert_array_equal(alive, keep)
    # one keyframe alone keeps everything; a finer cell of another keyframe takes a voxel over
    assert dedupe_frames(pts, level, np.zeros(n, int)).all()
    two = np.array([[0.001, 0.001, 0.001], [0.002, 0.002, 0.002]])
    assert dedupe_frames(two, np.array([3, 1]), np.array([0, 1])).tolist() == [False, True]
    assert dedupe_frames(two, np.array([2, 2]), np.array([1, 0])).tolist() == [False, True]


def test_cell_voxels_kernel_gives_the_reference_bits():
    """The dedupe's voxel of each cell (floor of point / size), its packed key and its voxel-to-viewpoint distance in
    one numba pass equal their numpy references exactly: the ties between the keyframes of one viewpoint group (the
    earliest keeps the voxel) rest on equal values; points beyond the packed range clamp as _pack does."""
    from xyzcyl.runtime.drive import _NO_ORIGINS, _cell_voxels, _pack, _voxel_distance_reference

    rng = np.random.default_rng(11)
    points = rng.normal(scale=400.0, size=(5000, 3)).astype(np.float32)
    points[:3] = [[1e5, -1e5, 0.0], [-0.0, 0.02, -0.02], [0.019999, 40.96, -40.96]]   # clamped; on voxel edges
    origins = rng.normal(scale=300.0, size=(7, 3))
    frame = rng.integers(0, 7, 5000)
    for size in (0.02, 0.02 * 2 ** 7, 40.96):
        coords, keys, dists = np.empty((5000, 3), np.int64), np.empty(5000, np.int64), np.empty(5000)
        _cell_voxels(points, size, frame, origins, True, coords, keys, dists)
        want = np.floor(points.astype(np.float64) / size).astype(np.int64)
        np.testing.assert_array_equal(coords, want)
        np.testing.assert_array_equal(keys, _pack(want))
        np.testing.assert_array_equal(dists, _voxel_distance_reference(want, size, frame, origins))
        _cell_voxels(points, size, frame, _NO_ORIGINS, False, coords, keys, dists)
        assert not dists.any()


@pytest.mark.parametrize("seed", range(6))
def test_voxel_owners_keep_what_dedupe_frames_keeps_as_keyframes_arrive(seed):
    """VoxelOwners (the fusion's dedupe, one keyframe's cells at a time) against dedupe_frames over all of them:
    dense and sparse cells, with and without viewpoints, keyframes in time order and shuffled."""
    rng = np.random.default_rng(seed)
    n, frames = 600, 5
    pts = rng.uniform(0, 1.0 if seed % 2 else 5.0, (n, 3))
    level = rng.integers(0, 7, n).astype(np.int8)
    frame = rng.integers(0, frames, n)
    origins = viewpoint_origins(rng.uniform(-3, 3, (frames, 3))) if seed % 3 else None
    full = dedupe_frames(pts, level, frame, origins)
    owners = VoxelOwners(origins)
    alive = np.zeros(n, bool)
    for f in (rng.permutation(frames) if seed >= 4 else range(frames)):
        idx = np.flatnonzero(frame == f)
        keep, lost = owners.add(pts[idx], level[idx], int(f), idx + 1000)        # ids: any names
        assert alive[lost - 1000].all()                                           # only kept cells are lost
        alive[idx[keep]] = True
        alive[lost - 1000] = False
    np.testing.assert_array_equal(alive, full)
    assert 0 < alive.sum() < n


@pytest.mark.parametrize("box_m, frames, per", [(0.5, 4, 3000), (0.06, 40, 1000)])
def test_voxel_owners_grow_their_tables_and_drop_lost_cells_entries(box_m, frames, per):
    """VoxelOwners' hash tables (runtime.voxelhash) past their first sizes, with 2 cm voxels: in a 0.5 m box (~two
    cells a voxel: many voxels) a level's table is rehashed and a keyframe's own table is too small for its voxels
    at first (SCRATCH_CELLS); in a 6 cm box (27 voxels: each keyframe takes some over, most cells are lost) the
    entries of lost cells are compacted away. What it keeps is still dedupe_frames' over all the cells."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, box_m, (frames * per, 3)).astype(np.float32)
    frame = np.repeat(np.arange(frames), per)
    level = rng.integers(0, 2, len(pts)).astype(np.int8)
    origins = viewpoint_origins(rng.uniform(-3, 3, (frames, 3)))
    owners = VoxelOwners(origins)
    alive = np.zeros(len(pts), bool)
    added = 0
    for f in range(frames):
        idx = np.flatnonzero(frame == f)
        keep, lost = owners.add(pts[idx], level[idx], f, idx)
        assert alive[lost].all()
        alive[idx[keep]] = True
        alive[lost] = False
        added += int(keep.sum())
    np.testing.assert_array_equal(alive, dedupe_frames(pts, level, frame, origins))
    assert owners.live == alive.sum()
    if box_m > 0.1:
        assert len(owners.keys[0]) > 1024 and owners.voxels[0] > 512         # rehashed past its first size
    else:
        assert owners.n_ent < added                                        # lost cells' entries compacted


def test_own_layer_rows_are_the_spatial_order_of_their_cells(tmp_path):
    """A keyframe's own cells as rows of its camera layer file in spatial order (_Kept.own_layer_rows: Morton codes
    beside the rows, no copy of the centres) against the reference (the centres made, spatial_order): parts with
    split cells (four rows each at the cell's centre) and without, an empty one, cells shared and not; a part
    without layer rows gives None."""
    from xyzcyl.runtime.drive import _Kept
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(5)
    kept = _Kept(np.zeros((2, 3)), tmp_path)
    kept.source = lambda n: tmp_path / f"layer_{n}.ply"          # never read here
    for n in (0, 1):
        start = 0
        for size, splits in ((4000, True), (2500, False), (0, False), (900, True)):
            g = Gaussians(rng.normal(scale=30.0, size=(size, 3)).astype(np.float32),
                          np.tile(np.float32([1, 0, 0, 0]), (size, 1)), np.full((size, 3), -2.0, np.float32),
                          np.zeros(size, np.float32), np.zeros((size, 1, 3), np.float32))
            split = None
            if splits:
                rows = np.where(rng.random(size) < 0.3, 0, -1)
                rows[rows == 0] = np.arange(int((rows == 0).sum()))
                split = (rows, np.zeros((int((rows >= 0).sum()), 4, 3), np.float32),
                         np.zeros((int((rows >= 0).sum()), 4, 3), np.float32))
            quarters = 0 if split is None else 3 * (split[0] >= 0)
            layer = (start + np.arange(size) + np.cumsum(quarters) - quarters).astype(np.int32)
            start += size + int(np.sum(quarters))
            kept.add(g, np.zeros(size, np.int8), n, split, layer)
    for i in range(len(kept.shared)):
        kept.shared[i] = rng.random(len(kept.shared[i])) < 0.6
    for n in (0, 1):
        got, want = kept.own_layer_rows(n), kept.own_layer_rows_reference(n)
        assert got.dtype == np.int32 and len(got) > 1000
        np.testing.assert_array_equal(got, want)
    kept.layer[0] = None
    assert kept.own_layer_rows(0) is None and kept.own_layer_rows(1) is not None


@pytest.mark.parametrize("reads", [1, 2])
def test_shared_parts_are_read_from_the_layer_files_with_each_chunks_box(tmp_path, monkeypatch, reads):
    """A drive's shared cells read from their keyframes' camera layer files (_Kept.shared_parts: past the page
    cache, Gaussians.read_ply_take, ``reads`` files at once) are those files' rows, a split cell's four quarters
    each its own row; each keyframe's box of its own rows (its chunk's box) found in the same reads is the box of
    own_layer_rows' rows' means in the file."""
    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.drive import _Kept
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.render import gaussians as G
    from xyzcyl.runtime.render.gaussians import save_ply_parts

    monkeypatch.setattr(D, "LAYER_READS", reads)
    monkeypatch.setattr(G, "READ_WINDOW_BYTES", 1 << 16)           # many windows a file
    rng = np.random.default_rng(6)

    def random(n):
        return Gaussians(rng.normal(scale=30.0, size=(n, 3)).astype(np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
                         rng.normal(size=n).astype(np.float32), rng.normal(size=(n, 1, 3)).astype(np.float32))

    kept = _Kept(np.zeros((3, 3)), tmp_path)
    kept.source = lambda n: tmp_path / f"layer_{n}.ply"
    files = {}
    for n in (0, 1, 2):
        start = 0
        for size, splits in ((4000, True), (2500, False), (0, False), (900, True)):
            split = None
            if splits:
                rows = np.where(rng.random(size) < 0.3, 0, -1)
                rows[rows == 0] = np.arange(int((rows == 0).sum()))
                s = int((rows >= 0).sum())
                split = (rows, np.zeros((s, 4, 3), np.float32), np.zeros((s, 4, 3), np.float32))
            quarters = 0 if split is None else 3 * (split[0] >= 0)
            layer = (start + np.arange(size) + np.cumsum(quarters) - quarters).astype(np.int32)
            start += size + int(np.sum(quarters))
            kept.add(random(size), np.zeros(size, np.int8), n, split, layer)
        files[n] = random(start)                    # the keyframe's layer file: its cells' rows, quarters apart
        save_ply_parts(kept.source(n), [files[n]], normals=False, direct=True)
    for i in range(len(kept.shared)):
        kept.shared[i] = rng.random(len(kept.shared[i])) < 0.4
    kept.shared[-1][:] = True                       # keyframe 2's last part: nothing of its own
    boxes = {}
    parts, frames = kept.shared_parts(lambda n, box: boxes.__setitem__(n, box))
    for i, (g, f) in enumerate(zip(parts, frames)):
        n = int(kept.frame[i][0]) if len(kept.frame[i]) else 0
        want = files[n].subset(kept._layer_take(i, kept.shared[i], centres=False)[0])
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(g, name), getattr(want, name))
        assert len(f) == len(g) and (f == n).all()
    assert sorted(boxes) == [0, 1, 2]
    for n in (0, 1, 2):
        m = files[n].means[kept.own_layer_rows(n)].astype(np.float64)
        np.testing.assert_array_equal(boxes[n], [m.min(axis=0), m.max(axis=0)])


def test_spilled_parts_keep_the_rows_they_keep_in_memory(tmp_path):
    """A drive's kept cells spilled to disk (runtime.drive._Kept with a spill folder) are written once; each keep()
    after that narrows the rows of the file that part() reads: the same Gaussians as parts kept in memory."""
    from xyzcyl.runtime.drive import _Kept
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(2)

    def random_gaussians(rng, n):
        return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                         rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                         rng.normal(size=(n, 1, 3)).astype(np.float32))

    origins = np.zeros((1, 3))
    mem, disk = _Kept(origins), _Kept(origins, tmp_path)
    parts = [random_gaussians(rng, n) for n in (50, 80)]
    for k in (mem, disk):
        for g in parts:
            k.add(g, np.zeros(len(g), np.int8), 0)
    written = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    masks = [rng.random(50) < 0.7, rng.random(80) < 0.5]
    for i, m in enumerate(masks):
        mem.keep(i, m)
        disk.keep(i, m)
    for i, m in enumerate(masks):       # a second narrowing, of what the first kept
        again = rng.random(int(m.sum())) < 0.6
        mem.keep(i, again)
        disk.keep(i, again)
    for i in range(2):
        a, b = mem.part(i), disk.part(i)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(disk.part(1)) == int(again.sum()) < 40
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == written and len(written) == 2


def test_kept_split_cells_are_deduped_as_cells_and_drawn_as_their_quarters(tmp_path):
    """A keyframe's split cells (runtime.detail.SplitCells) join a drive's kept cells as cells (one row each: the
    dedupe and every keep() see cells) and come out of shared_parts / own_of as their quarters, in memory and
    spilled: what expand_rows makes of the rows kept."""
    from xyzcyl.runtime.detail import expand_rows
    from xyzcyl.runtime.drive import _Kept
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(3)
    n, s = 60, 20
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, 1, 3)).astype(np.float32))
    rows = np.full(n, -1, np.int32)
    rows[rng.choice(n, s, replace=False)] = np.arange(s, dtype=np.int32)
    quarters = (rng.normal(size=(s, 4, 3)).astype(np.float32), rng.random((s, 4, 3)).astype(np.float32))
    for k in (_Kept(np.zeros((1, 3))), _Kept(np.zeros((1, 3)), tmp_path)):
        k.add(g, np.zeros(n, np.int8), 0, (rows, *quarters))
        m = rng.random(n) < 0.7
        k.keep(0, m)
        assert len(k.part(0)) == m.sum() == k.count()          # cells, not quarters
        shared = rng.random(int(m.sum())) < 0.5
        k.shared[0] = shared.copy()
        (got,), (frames,) = k.shared_parts()
        want = expand_rows(g.subset(m).subset(shared), rows[m][shared], *quarters)
        (own,) = k.own_of(0)
        want_own = expand_rows(g.subset(m).subset(~shared), rows[m][~shared], *quarters)
        for a, b in ((got, want), (own, want_own)):
            for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert len(got) == shared.sum() + 3 * (rows[m][shared] >= 0).sum() and len(frames) == len(got)


def test_dedupe_frames_prefers_the_nearer_viewpoint_among_equally_fine_cells():
    # one voxel seen as finely by three keyframes: the ones at the origin stood still (one viewpoint: the earlier
    # keeps it), the third drove 10 m on, next to the voxel, and takes it over; a coarser cell never does
    origins = viewpoint_origins(np.array([[0.0, 0, 0], [0.2, 0, 0], [10.0, 0, 0]]))
    np.testing.assert_array_equal(origins[1], [0, 0, 0])
    pts = np.array([[9.0, 2.0, 0.5]] * 3) + 0.001
    lv = np.array([5, 5, 5])
    assert dedupe_frames(pts[:2], lv[:2], np.array([1, 0]), origins).tolist() == [False, True]
    assert dedupe_frames(pts, lv, np.array([0, 1, 2]), origins).tolist() == [False, False, True]
    assert dedupe_frames(pts, np.array([4, 5, 5]), np.array([0, 1, 2]), origins).tolist() == [True, False, False]
    assert dedupe_frames(pts, lv, np.array([0, 1, 2])).tolist() == [True, False, False]     # no origins: earliest


def test_voxel_levels_and_boxes():
    from xyzcyl.runtime.drive import VOXEL_CELLS

    f = np.array([0.01, 0.02, 0.021, 0.04, 100.0]) / VOXEL_CELLS       # footprints: VOXEL_CELLS of them a voxel
    assert voxel_levels(f).tolist() == [0, 0, 1, 1, 11]
    # a Gaussian's footprint: twice its largest standard deviation (the largest log-scale, then exp: the same bits
    # as the largest of the exps)
    from xyzcyl.runtime.drive import _footprint
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(5)
    ls = rng.normal(-2.0, 1.0, (1000, 3)).astype(np.float32)
    g = Gaussians(means=np.zeros((1000, 3)), quats=np.tile([1.0, 0, 0, 0], (1000, 1)), log_scales=ls,
                  opacity_logits=np.zeros(1000), sh=np.zeros((1000, 1, 3)))
    np.testing.assert_array_equal(_footprint(g), 2.0 * np.sort(np.exp(ls.astype(np.float64)), axis=1)[:, 2])
    box = (np.linalg.inv(np.array(_pose(10, 0, 90))), np.array([2.0, 1.0, 1.0]))
    pts = np.array([[10, 1.9, 0], [10, 2.1, 0], [11.5, 0, 0], [10, 0, 1.5]])
    assert inside_boxes(pts, [box]).tolist() == [True, False, False, False]
    # box_members (only the points within a box's reach along x and y tested, in a kernel) against the direct test
    from xyzcyl.runtime.drive import box_members

    rng = np.random.default_rng(2)
    many = rng.uniform([-20, -20, -3], [20, 20, 3], (5000, 3))
    boxes = [(np.linalg.inv(np.array(_pose(*rng.uniform(-15, 15, 2), rng.uniform(0, 360)))), rng.uniform(0.5, 4, 3))
             for _ in range(12)]
    direct = np.full(len(many), -1)
    for b, (inv, half) in reversed(list(enumerate(boxes))):      # the first box wins
        q = many @ inv[:3, :3].T + inv[:3, 3]
        direct[np.all(np.abs(q) <= half, axis=1)] = b
    np.testing.assert_array_equal(box_members(many, boxes), direct)
    assert (direct >= 0).sum() > 100
    # float32 points (a keyframe's cells) as they are: the same as their float64 values (each widened exactly)
    few = many.astype(np.float32)
    np.testing.assert_array_equal(box_members(few, boxes), box_members(few.astype(np.float64), boxes))
    # footprints from the log-scales alone (a part whose cells are rows of a camera layer file) are the same
    np.testing.assert_array_equal(_footprint(ls), _footprint(g))


@pytest.fixture(scope="module")
def shipped():
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.testing import SHIPPED_MODEL

    return Reconstructor.load(SHIPPED_MODEL, threads=2)


def test_a_keyframe_without_a_sweep_carves_its_own_cameras_only_where_they_see_another_colour(
        tmp_path, shipped, monkeypatch):
    """reconstruct_drive: a keyframe's cameras carve each other's cells (carve_details_both: the fused cells with the
    dedupe, the camera layers without) with the colour test (SEE_THROUGH_PHOTO) when it has no LiDAR sweep (the
    model's depths, scaled per camera), by depth alone when it has one."""
    from xyzcyl.runtime import detail
    from xyzcyl.runtime import drive as drive_mod
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import SEE_THROUGH_PHOTO, reconstruct_drive

    calls = []
    carve = detail.carve_details_both       # the fused cells and the camera layers from one pass
    monkeypatch.setattr(detail, "carve_details_both", lambda d, tol, dedupe, photo=None: calls.append(photo) or
                        carve(d, tol, dedupe, photo))
    drive = load_drive(write_drive(tmp_path, [_pose(0, 0, 0), _pose(3, 0, 0)], [0.0, 1.0]))
    reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8), stereo=False)
    assert calls == [SEE_THROUGH_PHOTO] * 2
    ring = np.array([[10 * math.cos(a), 10 * math.sin(a), z] for a in np.linspace(0, 2 * math.pi, 720)
                     for z in (-1.5, 0.0, 1.0)], np.float32)               # a wall 10 m around the ego
    monkeypatch.setattr(drive_mod, "_sweep", lambda drive, k, lidar: ring if k == 1 else None)
    calls.clear()
    reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8), stereo=False)
    assert calls == [SEE_THROUGH_PHOTO, None]


def test_a_still_ego_posted_twice_is_kept_once(tmp_path, shipped):
    """Two keyframes of one place (the example rig twice, 2.5 s apart, the ego still): the second adds nothing
    (every surface it sees, the first saw as finely); a one-frame drive is the rig's own reconstruction."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import drive_of_rig, reconstruct_drive
    from xyzcyl.runtime.rig import load_rig

    opts = DetailOptions(stride=8)
    p = write_drive(tmp_path, [_pose(7, 3, 20)] * 2, [0.0, 2.5])
    drive = load_drive(p)
    assert pick_keyframes(drive) == [0, 1]
    two = reconstruct_drive(shipped, drive, detail=opts)
    one = shipped.reconstruct(load_rig(EXAMPLE_RIG), detail=opts)
    shown = int((one.gaussians.opacity_logits > -20).sum())         # the one-rig scene keeps hidden cells
    assert two.counts["keyframes"] == 2 and two.drive["keyframes"] == [0, 1]
    assert len(two.gaussians) <= 1.02 * shown, (len(two.gaussians), shown)
    assert len(two.gaussians) >= 0.9 * shown
    # one viewpoint group, and a chunk a keyframe: the first's holds what it saw beyond the shared cells (nearly
    # nothing here), the second's its own copy of what the first kept (drawn first at the second's time)
    vp = two.viewpoints
    assert vp.groups() == [0] and [c.keyframes for c in vp.chunks] == [(0,), (1,)]
    assert vp.chunks[0].count <= 0.02 * shown and vp.chunks[1].count >= 0.8 * shown, (vp.chunks, shown)
    single = reconstruct_drive(shipped, drive_of_rig(load_rig(EXAMPLE_RIG)), detail=opts)
    np.testing.assert_array_equal(single.gaussians.means, one.gaussians.means)
    # the scene folder records the drive, and reads it back
    two.save(tmp_path / "scene")
    from xyzcyl.runtime.scene import Scene, rig_camera

    back = Scene.load(tmp_path / "scene")
    assert back.drive["keyframes"] == [0, 1] and len(back.drive["trajectory"]) == 2
    # each Gaussian's keyframe (a view draws its primary keyframe's first: the first's, at a camera of frame 0)
    assert back.keyframe_of.shape == (len(two.gaussians),) and set(np.unique(back.keyframe_of)) <= {0, 1}
    assert back.primary_keyframe(rig_camera(back.rig.cameras[0])) == 0
    np.testing.assert_allclose(back.drive["ego_to_world"], _pose(7, 3, 20))


def test_each_viewpoint_keeps_what_its_keyframe_saw_whole(tmp_path, shipped, monkeypatch):
    """A moving ego (two keyframes 3 m apart): the shared Gaussians keep each surface once, and each viewpoint's
    chunk keeps the rest of its keyframe's cells, so a viewpoint's shared cells and its chunk are exactly that
    keyframe's cells without the cross-keyframe dedupe (runtime.viewpoints); through the scene folder and back."""
    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.scene import Scene

    opts = DetailOptions(stride=8)
    E = np.array(_pose(7, 3, 20))
    p = write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5])
    drive = load_drive(p)
    scene = D.reconstruct_drive(shipped, drive, detail=opts)
    vp = scene.viewpoints
    assert len(vp) == 2 and [c.keyframes for c in vp.chunks] == [(0,), (1,)]
    assert scene.counts["viewpoint_gaussians"] == vp.count > 0
    monkeypatch.setattr(D, "dedupe_frames", lambda points, *a, **k: np.ones(len(points), bool))    # model's
    monkeypatch.setattr(D.VoxelOwners, "add", lambda self, points, level, frame, ids:                 # cells'
                        (np.ones(len(points), bool), np.zeros(0, np.int64)))
    pile = D.reconstruct_drive(shipped, drive, detail=opts)
    assert pile.viewpoints.count == 0 and len(pile.gaussians) == len(scene.gaussians) + vp.count

    def rows(g):            # a set of Gaussians as sorted rows (order aside, the same cells)
        a = np.concatenate([g.means, g.quats, g.log_scales, g.opacity_logits[:, None], g.sh[:, 0]], axis=1)
        return a[np.lexsort(a.T[::-1])]

    from xyzcyl.runtime.detail import concat_gaussians

    for k in (0, 1):
        whole = pile.gaussians.subset(pile.keyframe_of == k)
        mine = concat_gaussians([scene.gaussians.subset(scene.keyframe_of == k), vp.gaussians(k)])
        np.testing.assert_array_equal(rows(mine), rows(whole))
    scene.save(tmp_path / "scene")
    back = Scene.load(tmp_path / "scene")
    np.testing.assert_array_equal(rows(back.viewpoints.gaussians(1)), rows(vp.gaussians(1)))
    # two frames are too few to find the ego's body (runtime.egobody takes a median over at least three)
    assert scene.ego_body.frames == (0, 1) and not scene.ego_body.masks and scene.ego_body.travelled_m == 3.0


def test_a_found_ego_body_gets_no_cells_and_travels_with_the_scene(tmp_path, shipped, monkeypatch):
    """The body runtime.egobody finds is used as the camera's ego mask in every keyframe (its detail layer has no
    cell there) and is written to and read from the scene folder (ego_body/<camera>.png)."""
    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.egobody import EgoBody
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.scene import Scene, rig_camera

    E = np.array(_pose(7, 3, 20))
    p = write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5])
    drive = load_drive(p)
    cam = next(c for c in drive.frames[0].rig.cameras if c.model == "pinhole")
    body = np.zeros((cam.height, cam.width), bool)
    body[: cam.height // 2] = True                         # the top half: enough to see it go
    monkeypatch.setattr(D, "find_drive_ego_body", lambda drive, lidar=True: EgoBody(
        masks={cam.name: body}, fractions={cam.name: 0.5}, frames=(0, 1), travelled_m=3.0))
    seen = []
    keyframe = Reconstructor.keyframe

    def spy(self, rig, *a, **k):
        kf = keyframe(self, rig, *a, **k)
        seen.append(kf)
        return kf

    monkeypatch.setattr(Reconstructor, "keyframe", spy)
    scene = D.reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8))
    assert len(seen) == 2
    k = drive.frames[0].rig.names.index(cam.name)
    for kf in seen:                                        # each keyframe's cells are in its own ego frame
        g = kf.parts[kf.owners.index(k)]
        uv, _, _ = rig_camera(cam).project(g.means)
        # cells only below the masked half (a stride-8 cell whose centre sample is unmasked may start a row above)
        assert len(g) and (uv[:, 1] >= cam.height // 2 - 8).all()
    assert scene.counts["ego_body_cameras"] == 1
    scene.save(tmp_path / "scene")
    assert (tmp_path / "scene" / "ego_body" / f"{cam.name}.png").is_file()
    back = Scene.load(tmp_path / "scene")
    np.testing.assert_array_equal(back.ego_body.masks[cam.name], body)
    assert back.ego_body.travelled_m == 3.0
    # a mask file outside the folder's ego_body/ is refused, naming the entry
    import json

    from xyzcyl.runtime.scene import SceneError

    doc = json.loads((tmp_path / "scene" / "scene.json").read_text())
    doc["ego_body"]["files"][cam.name] = "../elsewhere.png"
    (tmp_path / "scene" / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=f"ego_body.files.{cam.name}"):
        Scene.load(tmp_path / "scene")


def test_the_ego_body_is_found_beside_the_first_keyframes_network(tmp_path, shipped, monkeypatch):
    """reconstruct_drive looks for the ego's body in a thread while its first keyframe is decoded and run through the
    network (they need no mask: only the detail layer waits for the masks): the search here waits until that
    keyframe's encoder has run, which it never would if the keyframe waited for the search; the detail layer then
    gets the masks found."""
    import threading

    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.egobody import EgoBody
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.numba_cache import threadsafe

    if not threadsafe():
        pytest.skip("numba has no thread-safe threading layer here: the search runs first")
    E = np.array(_pose(7, 3, 20))
    drive = load_drive(write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5]))
    cam = next(c for c in drive.frames[0].rig.cameras if c.model == "pinhole")
    body = np.zeros((cam.height, cam.width), bool)
    body[: cam.height // 2] = True
    encoded, waited = threading.Event(), []

    def find(drive, lidar=True):
        waited.append(encoded.wait(60))         # 60 s: the first keyframe's encoder runs within a second here
        return EgoBody(masks={cam.name: body}, fractions={cam.name: 0.5}, frames=(0, 1), travelled_m=3.0)

    encode, details = Reconstructor.encode, Reconstructor.camera_details
    masks_seen = []

    def encode_spy(self, *a, **k):
        encoded.set()
        return encode(self, *a, **k)

    def details_spy(self, rig, rgb, gauss, lidar, detail, counts, ego_masks=None, *a, **k):
        masks_seen.append({name: np.array(m) for name, m in (ego_masks or {}).items()})
        return details(self, rig, rgb, gauss, lidar, detail, counts, ego_masks, *a, **k)

    monkeypatch.setattr(D, "find_drive_ego_body", find)
    monkeypatch.setattr(Reconstructor, "encode", encode_spy)
    monkeypatch.setattr(Reconstructor, "camera_details", details_spy)
    scene = D.reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8))
    assert waited == [True]
    assert len(masks_seen) == 2 and all(list(m) == [cam.name] for m in masks_seen)
    for m in masks_seen:
        np.testing.assert_array_equal(m[cam.name], body)
    assert scene.counts["ego_body_cameras"] == 1 and "ego_body" in scene.timings


def test_a_keyframes_detail_pyramids_are_made_once(tmp_path, shipped, monkeypatch):
    """The depth pyramids of a keyframe's detail layers (detail_pyramids) cull its own model Gaussians when it
    arrives and, kept, the scene's model Gaussians when it is committed: made once a keyframe, not twice."""
    from xyzcyl.runtime import detail
    from xyzcyl.runtime import drive as D
    from xyzcyl.runtime.detail import DetailOptions

    made, real = [], detail.CameraDetail.max_pyramid
    monkeypatch.setattr(detail.CameraDetail, "max_pyramid", lambda d: made.append(id(d)) or real(d))
    E = np.array(_pose(7, 3, 20))
    drive = load_drive(write_drive(tmp_path, [E.tolist(), (E @ np.array(_pose(3.0, 0.0))).tolist()], [0.0, 0.5]))
    scene = D.reconstruct_drive(shipped, drive, detail=DetailOptions(stride=8))
    # each keyframe's pinhole cameras' detail layers (the lens cameras' too): one pyramid each, two keyframes
    cameras = len(drive.frames[0].rig.cameras)
    assert scene.counts["keyframes"] == 2 and len(made) == 2 * cameras


def test_only_a_keyframe_with_measured_depth_carves_its_neighbours(monkeypatch):
    """runtime.drive._carve_pair: b's cameras carve a's cells when b had a LiDAR sweep, never on the model's depth
    alone (each of a's cameras against all of b's)."""
    from xyzcyl.runtime import detail
    from xyzcyl.runtime.drive import SEE_THROUGH_PHOTO, _carve_pair

    calls = []
    monkeypatch.setattr(detail, "carve_against",
                        lambda d, others, keep, tol, photo: calls.append((d, others, tol, photo)))
    monkeypatch.setattr(detail.CarveCameras, "of", staticmethod(list))      # b's cameras as they are, to compare
    a = (0, ["a0", "a1"], [], [np.ones(2, bool), np.ones(3, bool)], False, [np.zeros(2, bool), np.zeros(3, bool)])
    b_camera_only = (1, ["b0"], [], [np.ones(1, bool)], False, [np.zeros(1, bool)])
    b_lidar = (1, ["b0"], [], [np.ones(1, bool)], True, [np.zeros(1, bool)])
    _carve_pair(a, b_camera_only, 0.1)
    assert calls == []
    _carve_pair(a, b_lidar, 0.1)
    assert calls == [("a0", ["b0"], 0.1, SEE_THROUGH_PHOTO), ("a1", ["b0"], 0.1, SEE_THROUGH_PHOTO)]


def test_a_keyframes_cameras_are_stacked_once_for_all_its_pairs(monkeypatch):
    """runtime.drive._carve_pair with ``stacks``: b's cameras are stacked (CarveCameras.of) the first time b carves
    and that stack carves each later keyframe; without ``stacks`` each pair stacks them again."""
    from xyzcyl.runtime import detail
    from xyzcyl.runtime.drive import _carve_pair

    built, used = [], []
    monkeypatch.setattr(detail, "carve_against", lambda d, others, keep, tol, photo: used.append((d, others)))
    monkeypatch.setattr(detail.CarveCameras, "of", staticmethod(lambda ds: built.append(list(ds)) or ("stack", *ds)))
    b = (4, ["b0"], [], [np.ones(1, bool)], True, [np.zeros(1, bool)])
    a1 = (2, ["a0"], [], [np.ones(2, bool)], False, [np.zeros(2, bool)])
    a2 = (3, ["c0", "c1"], [], [np.ones(2, bool), np.ones(1, bool)], False, [np.zeros(2, bool), np.zeros(1, bool)])
    stacks = {}
    _carve_pair(a1, b, 0.1, stacks)
    _carve_pair(a2, b, 0.1, stacks)
    assert built == [["b0"]] and stacks == {4: ("stack", "b0")}
    assert used == [("a0", ("stack", "b0")), ("c0", ("stack", "b0")), ("c1", ("stack", "b0"))]
    _carve_pair(a1, b, 0.1)
    assert built == [["b0"], ["b0"]]


def test_measured_cells_a_neighbour_sees_through_moved_away(monkeypatch):
    """runtime.drive._carve_pair: of a's cells that b (LiDAR) sees through, those a's own LiDAR placed
    (CONF_MEASURED) are marked as moved away (drawn around a's time); those on the model's depth are only dropped;
    a keyframe without a sweep marks none."""
    from xyzcyl.runtime import detail
    from xyzcyl.runtime.drive import _carve_pair

    class Cells:                                   # a camera's kept cells: their confidence, in Gaussian order
        def __init__(self, conf):
            self.conf = np.array(conf, np.int8)

        def cell_conf(self):
            return self.conf

    def see_through(d, others, keep, tol, photo):  # b sees through a's first two cells
        keep[:2] = False

    monkeypatch.setattr(detail, "carve_against", see_through)
    monkeypatch.setattr(detail.CarveCameras, "of", staticmethod(list))
    M, C = detail.CONF_MEASURED, detail.CONF_MODEL
    b = (1, ["b0"], [], [np.ones(1, bool)], True, [np.zeros(1, bool)])
    for measured, want in ((True, [True, False, False, False]), (False, [False] * 4)):
        keep, gone = np.ones(4, bool), np.zeros(4, bool)
        a = (0, [Cells([M, C, M, C])], [], [keep], measured, [gone])
        _carve_pair(a, b, 0.1)
        assert keep.tolist() == [False, False, True, True]
        assert gone.tolist() == want


def test_cells_that_moved_away_beside_a_moving_objects_box_are_its_spill():
    """spill_boxes: a moving object's box at a frame grown by how far it moves in a frame interval (track_speed from
    its poses at the frames before and after; one side at the ends; SPILL_MIN_M at least); without_spill leaves out
    the moved-away cells inside one (a sweep turning while the car drives puts its returns beside it), keeping the
    rest; a stationary track has none."""
    from pathlib import Path

    from xyzcyl.runtime.drive import (
        SPILL_MIN_M,
        TRACK_GROW,
        Drive,
        DriveFrame,
        Track,
        spill_boxes,
        track_speed,
        without_spill,
    )
    from xyzcyl.runtime.render import Gaussians

    frames = tuple(DriveFrame(index=i, rig_path=Path("rig.json"), rig=None, timestamp_s=5.0 + 0.1 * i,
                              ego_to_world=np.eye(4)) for i in range(6))
    fast = Track("car", "Car", (4.0, 2.0, 1.5), False, {i: np.array(_pose(10.0 + 1.2 * i, 0.0)) for i in range(6)})
    slow = Track("walker", "Pedestrian", (0.6, 0.6, 1.8), False, {2: np.array(_pose(0.0, 8.0)),
                                                                  3: np.array(_pose(0.1, 8.0))})
    parked = Track("parked", "Car", (4.0, 2.0, 1.5), True, {i: np.array(_pose(0.0, -8.0)) for i in range(6)})
    drive = Drive(path=None, frames=frames, tracks=(fast, slow, parked))
    assert track_speed(drive, fast, 2) == pytest.approx(12.0)          # 2.4 m over frames 1..3
    assert track_speed(drive, fast, 0) == pytest.approx(12.0)          # frames 0..1 at the start
    assert track_speed(drive, slow, 2) == pytest.approx(1.0)
    assert track_speed(drive, slow, 4) == 0.0                          # no pose there or after
    boxes = spill_boxes(drive, 2)
    assert len(boxes) == 2                                            # the parked car is static scene
    (inv_car, half_car), (_, half_walker) = boxes
    np.testing.assert_allclose(half_car, 0.5 * TRACK_GROW * np.array([4.0, 2.0, 1.5]) + 1.2)
    np.testing.assert_allclose(half_walker, 0.5 * TRACK_GROW * np.array([0.6, 0.6, 1.8]) + SPILL_MIN_M)
    centre = -inv_car[:3, :3].T @ inv_car[:3, 3]                       # the car at frame 2: x = 12.4
    np.testing.assert_allclose(centre, [12.4, 0.0, 0.0])
    means = np.array([[12.4 + 2.2 + 1.0, 0, 0.5],                    # a metre behind the box: spill
                      [12.4 + 2.2 + 1.5, 0, 0.5],                    # beyond the car's reach in a frame
                      [0.0, 8.0 + 0.33 + 0.2, 0.5],                  # beside the walker, within the least margin
                      [0.0, -8.0, 0.5]], np.float32)                 # at the parked car: not spill
    n = len(means)
    g = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), -3.0, np.float32),
                  np.zeros(n, np.float32), np.zeros((n, 1, 3), np.float32))
    np.testing.assert_array_equal(without_spill(g, boxes).means, means[[1, 3]])
    assert without_spill(g, []) is g


def test_moved_away_cells_are_drawn_only_around_their_keyframes_time():
    """actors_of: one object a keyframe for its cells that moved away, in the scene's frame, drawn from halfway to
    the keyframe before to halfway to the one after (moved_spans), so that one keyframe's are drawn at any time."""
    from pathlib import Path

    from xyzcyl.runtime.drive import MOVED_LABEL, Drive, DriveFrame, actors_of, moved_spans
    from xyzcyl.runtime.render import Gaussians

    def cells(n, x):
        return Gaussians(np.tile(np.float32([x, 0, 1]), (n, 1)), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                         np.full((n, 3), -3.0, np.float32), np.zeros(n, np.float32), np.zeros((n, 1, 3), np.float32))

    assert moved_spans([10.0, 11.0, 13.0], 9.5, 14.0, 0.05) == [(9.5, 10.45), (10.55, 11.95), (12.05, 14.0)]
    assert moved_spans([10.0, 10.04], 10.0, 10.04, 0.05) == [(10.0, 10.0), (10.04, 10.04)]   # never past its time
    frames = tuple(DriveFrame(index=i, rig_path=Path("rig.json"), rig=None, timestamp_s=10.0 + 0.1 * i,
                              ego_to_world=np.eye(4)) for i in range(31))          # 10.0 .. 13.0 s
    drive = Drive(frames=frames, path=None, tracks=())
    g0, g2 = cells(5, 1.0), cells(7, 3.0)
    actors = actors_of(drive, [], [(0, g0), (2, g2)], keys=[0, 10, 30])        # keyframes at 10, 11, 13 s
    assert actors.track_id == ("moved@0", "moved@30") and set(actors.track_label) == {MOVED_LABEL}
    for t, n in ((10.0, 5), (10.4, 5), (10.6, 0), (11.5, 0), (12.5, 7), (13.0, 7)):
        g, _ = actors.at(t, 0.05)
        assert len(g) == n, t
    g, _ = actors.at(12.5, 0.05)
    np.testing.assert_allclose(g.means, g2.means)                              # where it was: the scene's frame


def test_a_drive_with_stereo_triangulates_a_keyframe_between_its_partner_frames(tmp_path, shipped):
    """reconstruct_drive (stereo, the default): a keyframe without a sweep and with frames >= 1 m on both sides is
    matched with them (runtime.stereo; its images read once, for the stereo and the keyframe); with stereo=False,
    nothing."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import reconstruct_drive

    E = np.array(_pose(7, 3, 20))
    poses = [(E @ np.array(_pose(x, 0.0))).tolist() for x in (0.0, 1.2, 2.4)]
    drive = load_drive(write_drive(tmp_path, poses, [0.0, 0.25, 0.5]))
    said = []
    with_stereo = reconstruct_drive(shipped, drive, keyframes=[1], detail=DetailOptions(stride=8),
                                    progress=said.append)
    assert "stereo" in with_stereo.timings
    assert any(m.startswith("stereo: ") and "frames [0, 2]" in m for m in said), said
    said.clear()
    without = reconstruct_drive(shipped, drive, keyframes=[1], detail=DetailOptions(stride=8), stereo=False,
                                progress=said.append)
    assert "stereo" not in without.timings and not any(m.startswith("stereo") for m in said)


def _actors(copy_times=(0.0, 1.0)):
    """One object annotated at t = 0, 1, 2 s moving +2 m/s along x and turning 90 degrees over 2 s, with a copy
    (two Gaussians: its centre and 1 m ahead along its length) at each of ``copy_times``."""
    from xyzcyl.runtime.actors import Actors
    from xyzcyl.runtime.render import Gaussians

    poses = np.array([_pose(2.0 * t, 0.0, 45.0 * t) for t in (0.0, 1.0, 2.0)], float)
    n = len(copy_times)
    one = Gaussians(np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.tile(np.float32([1, 0, 0, 0]), (2, 1)),
                    np.full((2, 3), -2.0, np.float32), np.zeros(2, np.float32), np.full((2, 1, 3), 0.5, np.float32))
    from xyzcyl.runtime.detail import concat_gaussians

    return Actors(track_id=("car",), track_label=("Car",), track_size=np.array([[4.0, 2.0, 1.5]]),
                  pose_track=np.zeros(3, np.int32), pose_time=np.array([0.0, 1.0, 2.0]), pose=poses,
                  copy_track=np.zeros(n, np.int32), copy_time=np.array(copy_times, float),
                  copy_start=np.arange(0, 2 * n + 1, 2), gaussians=concat_gaussians([one] * n))


def test_actors_are_drawn_at_their_pose_at_a_time_and_not_outside_their_span(tmp_path):
    a = _actors()
    g, drawn = a.at(0.5, slack_s=0.05)                # halfway between t = 0 and 1: x = 1 m, turned 22.5 degrees
    assert drawn == [0] and len(g) == 2
    c, s = math.cos(math.radians(22.5)), math.sin(math.radians(22.5))
    np.testing.assert_allclose(g.means, [[1.0, 0, 0], [1.0 + c, s, 0]], atol=1e-6)
    assert len(a.at(2.04, 0.05)[0]) == 2 and len(a.at(2.2, 0.05)[0]) == 0      # within the slack, then gone
    assert len(a.at(-0.2, 0.05)[0]) == 0
    np.testing.assert_allclose(a.at(2.0, 0.05)[0].means[1], [4.0, 1.0, 0.0], atol=1e-6)   # turned 90 degrees
    a.save(tmp_path / "actors.npz")
    from xyzcyl.runtime.actors import Actors

    b = Actors.load(tmp_path / "actors.npz")
    np.testing.assert_array_equal(b.at(1.3, 0.05)[0].means, a.at(1.3, 0.05)[0].means)
    assert b.track_id == ("car",) and b.track_label == ("Car",)


def test_a_drive_with_a_moving_track_draws_it_at_the_render_time(tmp_path, shipped):
    """A tracked object that moves leaves the static scene and is drawn where it is at the render's time."""
    from xyzcyl.runtime.camera import Camera, pinhole_K
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import reconstruct_drive
    from xyzcyl.runtime.scene import Scene

    E = _pose(7, 3, 20)
    box_at = lambda dx: (np.array(E) @ np.array(_pose(12.0 + dx, 0.0))).tolist()    # 12 m ahead of the ego
    tracks = {"tracks": [{"id": "car-1", "label": "Car", "size": [5.0, 6.0, 4.0], "stationary": False,
                          "poses": [{"frame": 0, "object_to_world": box_at(0.0)},
                                    {"frame": 1, "object_to_world": box_at(3.0)}]}]}
    p = write_drive(tmp_path, [E, E], [0.0, 2.5], tracks=tracks)
    scene = reconstruct_drive(shipped, load_drive(p), detail=DetailOptions(stride=8))
    assert scene.actors is not None and scene.counts["actors"] == 1 and scene.counts["actor_gaussians"] > 0
    assert scene.counts["moving_removed"] > 0
    scene.save(tmp_path / "scene")
    back = Scene.load(tmp_path / "scene")
    cam = Camera(K=pinhole_K(200, 200, 159.5, 89.5), cam_to_ego=np.array(
        [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], float), width=320, height=180)
    at0 = back.gaussians_at(cam, 0.0)
    at1 = back.gaussians_at(cam, 1.0)        # still the first keyframe's copy (the nearer), its box 1.2 m on
    n_static = len(back.gaussians)
    assert len(at0) > n_static and len(at1) == len(at0)
    moved = at1.means[n_static:] - at0.means[n_static:]
    np.testing.assert_allclose(moved[:, :2], np.tile([1.2, 0.0], (len(moved), 1)), atol=1e-3)
    assert len(back.gaussians_at(cam, 2.5)) > n_static                       # the second keyframe's copy
    assert len(back.gaussians_at(cam, 10.0)) == n_static                     # after its last pose: not drawn


def test_render_time_flag_draws_the_objects_of_that_time(tmp_path, shipped, capsys):
    """`xyzcyl render --time T` on a drive's scene renders what Scene.render draws at T; another time moves the
    tracked object; the time is refused when it is not a number."""
    from xyzcyl import cli
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import reconstruct_drive
    from xyzcyl.runtime.scene import Scene

    E = _pose(0, 0, 0)
    tracks = {"tracks": [{"id": "c", "label": "Car", "size": [6.0, 6.0, 4.0], "stationary": False,
                          "poses": [{"frame": 0, "object_to_world": _pose(10.0, 0.0)},
                                    {"frame": 1, "object_to_world": _pose(16.0, 0.0)}]}]}
    p = write_drive(tmp_path, [E, E], [0.0, 2.5], tracks=tracks)
    reconstruct_drive(shipped, load_drive(p), detail=DetailOptions(stride=8)).save(tmp_path / "scene")
    outs = {}
    for t in ("0.0", "1.0"):
        out = tmp_path / f"t{t}.exr"
        assert cli.main(["render", str(tmp_path / "scene"), "--camera", "CAM_FRONT", "--width", "160", "--time", t,
                         "--out", str(out), "--quiet"]) == 0
        outs[t] = out.read_bytes()
    assert outs["0.0"] != outs["1.0"]
    capsys.readouterr()
    assert cli.main(["render", str(tmp_path / "scene"), "--camera", "CAM_FRONT", "--width", "160",
                     "--out", str(tmp_path / "v.png")]) == 0
    # the view stands at keyframe 0's front camera: its camera layer is drawn first (runtime.cameralayers)
    assert re.match(r"rendered \d+ Gaussians \(the \d+ of \d+ tiles the view sees\) and the view's viewpoint "
                    r"chunks, over them the camera layer of the camera it stands at \(\d+ Gaussians\) -> ",
                    capsys.readouterr().out)
    scene = Scene.load(tmp_path / "scene")
    from xyzcyl.runtime.scene import rig_camera
    from xyzcyl.runtime.views import ViewRequest, encode_view

    cam = rig_camera(scene.rig.camera("CAM_FRONT"), width=160, height=90)
    rgb, depth, alpha = scene.render(cam, time_s=1.0)
    assert encode_view(rgb, depth, alpha, ViewRequest(cam, "all", "exr", time_s=1.0)) == outs["1.0"]
    with pytest.raises(SystemExit) as e:          # argparse: usage and exit status 2
        cli.main(["render", str(tmp_path / "scene"), "--camera", "CAM_FRONT", "--time", "soon",
                  "--out", str(tmp_path / "x.png")])
    assert e.value.code == 2


def test_batch_items_carry_a_time():
    """Each item of a batch may carry its time (every kind of item); a bad one is refused naming its JSON path."""
    from xyzcyl.common.wire import ViewError
    from xyzcyl.runtime.views import views_from_batch

    c2e = [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]]
    carla = {"transform": {"location": {"x": 1, "y": 0, "z": 2}, "rotation": {"pitch": 0, "yaw": 0, "roll": 0}},
             "fov": 90, "image_size_x": 64, "image_size_y": 36, "time": 3.5}
    doc = {"cameras": [{"fov": 60, "cam_to_ego": c2e, "width": 64, "height": 36, "time": 1.25},
                       {"fov": 60, "cam_to_ego": c2e, "width": 64, "height": 36}, carla]}
    assert [t for _, t, _ in views_from_batch(doc)] == [1.25, None, 3.5]
    for bad in ("soon", float("nan"), True):
        doc["cameras"][0]["time"] = bad
        with pytest.raises(ViewError) as e:
            views_from_batch(doc)
        assert e.value.field == "cameras[0].time", str(e.value)


def test_keyframes_made_in_a_worker_process_give_the_same_scene(tmp_path, shipped):
    """workers=1: the next keyframe is reconstructed in a spawned worker process (its own model sessions) while
    this one fuses; the scene is the one made in one process (workers=0: the next keyframe made in a thread),
    Gaussian for Gaussian. A bad workers count is refused naming the field; a keyframe that fails fails the drive
    either way."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import DriveError, reconstruct_drive
    from xyzcyl.runtime.errors import RigError

    E = np.array(_pose(7, 3, 20))
    poses = [(E @ np.array(_pose(x, 0.0))).tolist() for x in (0.0, 1.5, 3.0)]
    drive = load_drive(write_drive(tmp_path, poses, [0.0, 0.3, 0.6]))
    opts = DetailOptions(stride=8)
    said: list[str] = []
    here = reconstruct_drive(shipped, drive, detail=opts, keyframes=[0, 1, 2], workers=0, progress=said.append)
    assert "frame 2: encode" in said, said            # the stage lines of a keyframe made ahead name its frame
    there = reconstruct_drive(shipped, drive, detail=opts, keyframes=[0, 1, 2], workers=1)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        # onnxruntime with the worker's thread count may sum in another order: float32 rounding of the model's
        # outputs, carried into the cells' positions and colours
        np.testing.assert_allclose(getattr(there.gaussians, name), getattr(here.gaussians, name), atol=1e-4)
    np.testing.assert_array_equal(there.keyframe_of, here.keyframe_of)
    assert there.viewpoints.count == here.viewpoints.count
    with pytest.raises(DriveError) as e:
        reconstruct_drive(shipped, drive, detail=opts, keyframes=[0, 1], workers=-1)
    assert e.value.field == "workers"
    # a keyframe that fails in the worker (an image that is not one) fails the drive, naming the camera
    (tmp_path / "bad.jpg").write_bytes(b"not a picture")

    def bad(i, rig):
        if i == 2:
            rig["cameras"][0]["image"] = str(tmp_path / "bad.jpg")

    broken = load_drive(write_drive(tmp_path / "broken", poses, [0.0, 0.3, 0.6], bad), check_images=False)
    for workers in (1, 0):
        with pytest.raises(RigError, match="image"):
            reconstruct_drive(shipped, broken, detail=opts, keyframes=[0, 1, 2], workers=workers)


def test_by_box_gives_each_boxs_members_in_order():
    """runtime.drive._by_box (one sort of a part's box members) against a mask per box: the same Gaussians in the
    same order."""
    from xyzcyl.runtime.drive import _by_box
    from xyzcyl.runtime.render import Gaussians

    rng = np.random.default_rng(5)
    n = 300
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, 1, 3)).astype(np.float32))
    member = rng.integers(-1, 5, n)                 # -1: in no box; box 5 of 6 holds nothing
    keep = rng.random(n) < 0.8
    got = _by_box(g, keep & (member >= 0), member, 6)
    for b in range(6):
        np.testing.assert_array_equal(got[b].means, g.subset(keep & (member == b)).means)
    assert len(got[5]) == 0 and sum(map(len, got)) == int((keep & (member >= 0)).sum())
