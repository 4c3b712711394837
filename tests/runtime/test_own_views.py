"""Each input camera's own view wins at its own pose (issue 35 item 2: CAM_FRONT's render at its own pose showed
CAM_FRONT_LEFT's cells over its left 150-200 px). runtime.detail.fuse_details keeps the cells the fusion drops as
hidden Gaussians and an OwnViews record; Scene.gaussians_for shows, at an input camera's pose, that camera's cells
wherever it has them. Two pinhole cameras look at one wall; B is nearer and resolves the shared part more finely,
so the fusion hands it B's cells: A's own view must still be A's cells alone there."""

from __future__ import annotations

import numpy as np
import pytest
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.detail import (
    HIDDEN_LOGIT,
    CameraDetail,
    DetailError,
    DetailOptions,
    OwnViews,
    cell_gaussians,
    fuse_details,
    grid_camera,
    own_view_hide,
    own_view_hide_reference,
)
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.rig import Rig
from xyzcyl.runtime.scene import Scene, render_view

RED, BLUE = (1.0, 0.1, 0.1), (0.1, 0.2, 1.0)
WALL_X = 10.0        # metres ahead (ego x): the wall both cameras see


def _camera(name: str, x: float, y: float, f: float) -> Camera:
    """An OpenCV camera at (x, y, 1.5) ego looking along ego +x (camera z), 96x64 px."""
    T = np.eye(4)
    T[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]       # columns: camera x, y, z in ego
    T[:3, 3] = (x, y, 1.5)
    K = np.array([[f, 0, 47.5], [0, f, 31.5], [0, 0, 1.0]])
    return Camera(K=K, cam_to_ego=T, width=96, height=64, name=name)


def _wall_detail(cam: Camera, colour, opts: DetailOptions) -> tuple[Gaussians, CameraDetail]:
    """Camera ``cam``'s detail layer of the wall x = WALL_X: every cell kept, measured, in ``colour``."""
    grid = grid_camera(cam, opts.stride)
    z = WALL_X - grid.position[0]                          # the wall's camera z (the camera looks along ego x)
    depth = np.full((grid.height, grid.width), z, np.float32)
    keep = np.ones(depth.shape, bool)
    colours = np.broadcast_to(np.asarray(colour, np.float32), (*depth.shape, 3)).copy()
    g = cell_gaussians(grid, colours, depth, np.full(depth.shape, opts.opacity), keep, opts.footprint,
                       opts.thickness, surface_stretch=opts.surface_stretch)
    return g, CameraDetail.build(grid, depth, keep, keep, g.means)


@pytest.fixture(scope="module")
def wall():
    opts = DetailOptions()
    a = _camera("A", 0.0, 0.0, 60.0)
    b = _camera("B", 4.0, 2.5, 60.0)                       # nearer the wall (6 m against 10 m): finer there
    (ga, da), (gb, db) = _wall_detail(a, RED, opts), _wall_detail(b, BLUE, opts)
    coarse = Gaussians.empty()
    g, own, counts = fuse_details(coarse, [ga, gb], [da, db], [0, 1], ("A", "B"), opts)
    rig = Rig(cameras=(a, b))
    return Scene(gaussians=g, background=None, rig=rig, own_views=own), counts, (da, db)


def _share(rgb: np.ndarray, alpha: np.ndarray, colour) -> float:
    """The fraction of the covered pixels drawn in ``colour`` (within 0.1 per channel)."""
    covered = alpha > 0.5
    close = np.all(np.abs(rgb - np.asarray(colour) * alpha[..., None]) < 0.1, axis=-1)
    return float((close & covered).sum() / max(covered.sum(), 1))


def test_the_fusion_hands_the_shared_wall_to_the_finer_camera(wall):
    scene, counts, _ = wall
    assert counts["carved"] > 100 and counts["detail"] + counts["carved"] == len(scene.gaussians)
    assert len(scene.own_views.index) == counts["carved"]
    assert np.all(scene.gaussians.opacity_logits[scene.own_views.index] == np.float32(HIDDEN_LOGIT))
    a = scene.rig.cameras[0]
    rgb, _, alpha = render_view(Scene(scene.gaussians, None, scene.rig), a)     # no own views: today's scene
    assert _share(rgb, alpha, BLUE) > 0.05                 # B's cells show in A's image (the picture)


@pytest.mark.parametrize("k, colour", [(0, RED), (1, BLUE)])
def test_each_camera_sees_its_own_cells_at_its_own_pose(wall, k, colour):
    scene, _, _ = wall
    cam = scene.rig.cameras[k]
    assert scene.own_camera(cam) == k
    rgb, _, alpha = render_view(scene, cam)
    assert alpha[4:-4, 4:-4].mean() > 0.9        # the wall fills the view (opacity 0.95 discs; they fade at the border)
    assert _share(rgb, alpha, colour) > 0.99


def test_a_pose_away_from_every_input_camera_is_the_default_scene(wall):
    scene, _, _ = wall
    cam = scene.rig.cameras[0]
    moved = np.array(cam.cam_to_ego)
    moved[1, 3] += 0.01                                    # 1 cm: beyond OWN_POSE_TOL's 1 mm
    other = cam.replace(cam_to_ego=moved)
    assert scene.own_camera(other) is None and scene.gaussians_for(other) is scene.gaussians
    near = np.array(cam.cam_to_ego)
    near[1, 3] += 2e-4                                     # a float32-composed pose: still A's own view
    assert scene.own_camera(cam.replace(cam_to_ego=near)) == 0


def test_own_view_hide_matches_its_reference(wall):
    _, _, (da, db) = wall
    rng = np.random.default_rng(3)
    kept = [rng.random(len(d.means)) < 0.7 for d in (da, db)]
    starts = [5, 5 + len(da.means)]
    fast = own_view_hide([da, db], kept, starts)
    ref = own_view_hide_reference([da, db], kept, starts)
    assert all(np.array_equal(f, r) for f, r in zip(fast, ref, strict=True))
    assert len(fast[0]) > 50 and len(fast[1]) > 50       # the two cameras overlap
    # the second camera's cells placed first: each camera's list still ascends (the runs are then sorted)
    starts = [5 + len(db.means), 5]
    fast = own_view_hide([da, db], kept, starts)
    ref = own_view_hide_reference([da, db], kept, starts)
    assert all(np.array_equal(f, r) for f, r in zip(fast, ref, strict=True))


def test_scene_folder_keeps_the_own_views(wall, tmp_path):
    scene, _, _ = wall
    loaded = Scene.load(scene.save(tmp_path / "s"))
    for cam in scene.rig.cameras:
        assert np.array_equal(render(loaded.gaussians_for(cam), cam).rgb, render(scene.gaussians_for(cam), cam).rgb)
    assert (tmp_path / "s" / "own_views.npz").is_file()


def test_a_damaged_own_views_file_is_named(wall, tmp_path):
    scene, _, _ = wall
    own = scene.own_views
    bad = OwnViews(own.cameras, own.index, own.logit, own.owner, own.hide, own.hide_offsets[:-1])
    with pytest.raises(DetailError) as e:
        bad.check(len(scene.gaussians), "test")
    assert e.value.field == "own_views.hide_offsets"
    far = OwnViews(own.cameras, own.index + len(scene.gaussians), own.logit, own.owner, own.hide, own.hide_offsets)
    with pytest.raises(DetailError) as e:
        far.check(len(scene.gaussians), "test")
    assert e.value.field == "own_views.index"
    (tmp_path / "x.npz").write_bytes(b"not a zip")
    with pytest.raises(DetailError) as e:
        OwnViews.load(tmp_path / "x.npz", 10)
    assert e.value.field == "own_views" and "x.npz" in str(e.value)
