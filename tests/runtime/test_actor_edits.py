"""A view's edits of a drive's actors (common.wire.ActorEdit; runtime.actors.Actors.placements): moved to a pose or
by an offset, hidden, a copy inserted; refusals naming the field; a reconstructed drive's actor leaves nothing of
itself in the static scene, so hiding it leaves what is behind it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from xyzcyl.common.wire import ViewError, actor_edits, validated
from xyzcyl.testing.drives import moving_car, write_drive
from xyzcyl.testing.drives import pose as _pose


def _one_actor():
    """"car" annotated at t = 0, 1, 2 s moving +2 m/s along x (no turn), one copy at t = 0: two Gaussians, its
    centre and 1 m ahead along its length."""
    from xyzcyl.runtime.actors import Actors
    from xyzcyl.runtime.render import Gaussians

    g = Gaussians(np.array([[0, 0, 0], [1, 0, 0]], np.float32), np.tile(np.float32([1, 0, 0, 0]), (2, 1)),
                  np.full((2, 3), -2.0, np.float32), np.zeros(2, np.float32), np.full((2, 1, 3), 0.5, np.float32))
    return Actors(track_id=("car",), track_label=("Car",), track_size=np.array([[4.0, 2.0, 1.5]]),
                  pose_track=np.zeros(3, np.int32), pose_time=np.array([0.0, 1.0, 2.0]),
                  pose=np.array([_pose(2.0 * t) for t in (0.0, 1.0, 2.0)], float), copy_track=np.zeros(1, np.int32),
                  copy_time=np.zeros(1), copy_start=np.array([0, 2]), gaussians=g)


def test_edits_move_hide_and_insert_an_actor():
    a = _one_actor()
    assert a.at(0.5, 0.05, actor_edits([{"id": "car", "hide": True}]))[1] == []
    # an offset is along the actor's own axes from where it is then (x = 1 m at 0.5 s)
    g, drawn = a.at(0.5, 0.05, actor_edits([{"id": "car", "offset": [0.0, 1.5, 0.2]}]))
    np.testing.assert_allclose(g.means, [[1.0, 1.5, 0.2], [2.0, 1.5, 0.2]], atol=1e-6)
    # a pose places it anywhere, at any time (here turned 90 degrees left at (5, 5), after its span)
    c, s = math.cos(math.radians(90)), math.sin(math.radians(90))
    T = [c, -s, 0, 5, s, c, 0, 5, 0, 0, 1, 0, 0, 0, 0, 1]
    g, drawn = a.at(9.0, 0.05, actor_edits([{"id": "car", "pose": T}]))
    assert drawn == [0]
    np.testing.assert_allclose(g.means, [[5, 5, 0], [5, 6, 0]], atol=1e-6)
    assert a.at(9.0, 0.05)[1] == []                  # unedited: not drawn outside its span
    # a copy under a new id, the actor itself where it is
    g, drawn = a.at(1.0, 0.05, actor_edits([{"id": "car", "insert": "car-2", "offset": [0, -3, 0]}]))
    assert drawn == [0, 0]
    np.testing.assert_allclose(g.means, [[2, 0, 0], [3, 0, 0], [2, -3, 0], [3, -3, 0]], atol=1e-6)
    # hidden and inserted together: the copy stays
    g, drawn = a.at(1.0, 0.05, actor_edits([{"id": "car", "hide": True},
                                             {"id": "car", "insert": "ghost", "offset": [1, 0, 0]}]))
    np.testing.assert_allclose(g.means, [[3, 0, 0], [4, 0, 0]], atol=1e-6)


@pytest.mark.parametrize("edits, at, field", [
    ([{"id": "bus", "hide": True}], 1.0, "actors[0].id"),
    ([{"id": "car", "hide": True}, {"id": "car", "offset": [0, 1, 0]}], 1.0, "actors[1].id"),
    ([{"id": "car", "insert": "car", "offset": [0, 1, 0]}], 1.0, "actors[0].insert"),
    ([{"id": "car", "insert": "x", "offset": [0, 1, 0]}, {"id": "car", "insert": "x", "offset": [0, 2, 0]}], 1.0,
     "actors[1].insert"),
    ([{"id": "car", "offset": [0, 1, 0]}], 5.0, "actors[0].offset"),                   # not there at 5 s
    ([{"id": "car", "pose": [1, 0, 0, 1e4, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}], 1.0, "actors[0].pose"),   # 10 km
    ([{"id": "car", "offset": [0, 2000, 0]}], 1.0, "actors[0].offset"),
    ([{"id": "car", "pose": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}], 1.0, "actors[0].pose"),     # scaled
])
def test_edits_the_scene_cannot_honour_are_refused_naming_the_field(edits, at, field):
    a = _one_actor()
    with pytest.raises(ViewError) as e:
        a.placements(at, 0.05, actor_edits(edits), reach=(np.zeros((1, 3)), 1000.0))
    assert e.value.field == field, str(e.value)


@pytest.mark.parametrize("text, field", [
    ('[{"id": "car"}]', "actors[0]"),                                          # no edit
    ('[{"id": "car", "hide": true, "offset": [0, 1, 0]}]', "actors[0]"),        # two
    ('[{"id": "car", "hide": "yes"}]', "actors[0].hide"),
    ('[{"id": "car", "offset": [0, NaN, 0]}]', "actors[0].offset"),
    ('[{"id": "car", "pose": [1, 0, 0]}]', "actors[0].pose"),
    ('[{"id": "car", "hide": true, "insert": "b"}]', "actors[0]"),
    ('[{"id": "car", "hide": true, "colour": "red"}]', "actors[0].colour"),
    ('{"id": "car"}', "actors"),
    ("not json", "actors"),
])
def test_malformed_edits_are_refused_on_the_wire_naming_the_field(text, field):
    with pytest.raises(ViewError) as e:
        validated({"camera": "CAM_FRONT", "actors": text})
    assert e.value.field == field, str(e.value)
    q = validated({"camera": "CAM_FRONT", "actors": '[{"id": "car", "offset": [0, 1.5, 0]}]'})
    assert validated({"camera": "CAM_FRONT", **{"actors": q.params()["actors"]}}) == q      # the GET text round trip


def test_a_tracked_actor_leaves_nothing_in_the_static_scene_and_edits_change_only_its_pixels(tmp_path):
    """The Gaussians inside a moving object's box at a keyframe that saw it are the actor's, not the static
    scene's: hiding it changes the view only where it was drawn, and there the view is what a view with the actor
    moved far away shows; the edits reach the view through the request (ETag) and are refused without actors."""
    from xyzcyl.runtime.detail import DetailOptions
    from xyzcyl.runtime.drive import load_drive, moving_boxes, reconstruct_drive
    from xyzcyl.runtime.inference import Reconstructor
    from xyzcyl.runtime.scene import Scene, rig_camera
    from xyzcyl.runtime.views import request
    from xyzcyl.testing import SHIPPED_MODEL

    E = _pose(0, 0, 0)
    drive = load_drive(write_drive(tmp_path, [E, E], [0.0, 2.5], tracks=moving_car(E, ahead_m=12.0, moved_m=20.0)))
    scene = reconstruct_drive(Reconstructor.load(SHIPPED_MODEL, threads=2), drive, detail=DetailOptions(stride=8))
    scene.save(tmp_path / "scene")
    scene = Scene.load(tmp_path / "scene")
    assert scene.actors.track_id == ("car-1",) and len(scene.actors.gaussians) > 100
    # nothing of keyframe 0's static Gaussians lies inside the box where keyframe 0 saw the car (its grown box)
    (_, inv, half), = moving_boxes(drive, 0)
    first = scene.gaussians.means[scene.keyframe_of == 0].astype(np.float64)
    q = first @ inv[:3, :3].T + inv[:3, 3]
    assert not np.any(np.all(np.abs(q) <= half, axis=1))

    cam = rig_camera(scene.rig.camera("CAM_FRONT"), width=160, height=90)
    shown, _, a_shown = scene.render(cam, 0.0)
    hidden, _, _ = scene.render(cam, 0.0, actors=actor_edits([{"id": "car-1", "hide": True}]))
    away, _, _ = scene.render(cam, 0.0, actors=actor_edits([{"id": "car-1", "offset": [0, 200, 0]}]))
    changed = np.abs(shown - hidden).max(axis=2) > 1e-3
    assert changed.mean() > 0.02                           # the car was drawn, and now is not
    np.testing.assert_allclose(hidden, away, atol=1e-5)    # hidden = drawn where no camera sees it
    moved, _, _ = scene.render(cam, 0.0, actors=actor_edits([{"id": "car-1", "offset": [0, 1.5, 0]}]))
    assert np.abs(moved - shown).max() > 1e-2
    # a time's moving objects are made once for the views that share its edits (a rig's cameras), not for others
    m = scene.moving_at(0.0)
    assert scene.moving_at(0.0) is m and len(m) == len(scene.actors.copy_of(0, 0.0))
    assert scene.moving_at(0.0, actor_edits([{"id": "car-1", "hide": True}])) is None
    np.testing.assert_array_equal(scene.moving_at(0.0).means, m.means)
    assert scene.moving_at(2.5) is not m
    # the request carries the edits: another edit, another ETag; a scene without actors refuses them
    plain = request(validated({"camera": "CAM_FRONT", "time": 0.0}), scene.rig)
    edited = request(validated({"camera": "CAM_FRONT", "time": 0.0, "actors": [{"id": "car-1", "hide": True}]}),
                     scene.rig)
    assert plain.key() != edited.key() and edited.actors[0].hide
    scene.check_actors(edited.actors, 0.0)
    with pytest.raises(ViewError) as e:
        scene.check_actors(actor_edits([{"id": "car-2", "hide": True}]), 0.0, "cameras[3].actors")
    assert e.value.field == "cameras[3].actors[0].id"
    alone = Scene(gaussians=scene.gaussians, background=scene.background, rig=scene.rig)
    with pytest.raises(ViewError) as e:
        alone.render(cam, 0.0, actors=edited.actors)
    assert e.value.field == "actors[0].id"
    listed = scene.actor_list(1.0)["actors"]
    assert [r["id"] for r in listed] == ["car-1"] and listed[0]["tracked"] and len(listed[0]["pose"]) == 16
    assert listed[0]["copies"] >= 1 and listed[0]["gaussians"] == len(scene.actors.gaussians)
    # the ground no frame saw under it is filled and counted (runtime.groundfill), in the listing and scene.json
    assert listed[0]["filled_m2"] == pytest.approx(scene.counts["ground_filled_m2"], abs=0.01)
    assert scene.to_json()["actors"].get("filled_m2", {}).get("car-1", 0.0) == pytest.approx(listed[0]["filled_m2"])
    # the command line: `xyzcyl render --actors` draws what Scene.render draws with the edits; `xyzcyl actors`
    from xyzcyl import cli
    from xyzcyl.runtime.views import ViewRequest, encode_view

    out = tmp_path / "hidden.exr"
    assert cli.main(["render", str(tmp_path / "scene"), "--camera", "CAM_FRONT", "--width", "160", "--time", "0",
                     "--actors", '[{"id": "car-1", "hide": true}]', "--out", str(out), "--quiet"]) == 0
    rgb, depth, alpha = scene.render(cam, 0.0, actors=actor_edits([{"id": "car-1", "hide": True}]))
    assert out.read_bytes() == encode_view(rgb, depth, alpha, ViewRequest(cam, "all", "exr", time_s=0.0))
    assert cli.main(["render", str(tmp_path / "scene"), "--camera", "CAM_FRONT", "--width", "160", "--actors",
                     '[{"id": "bus", "hide": true}]', "--out", str(out), "--quiet"]) == 2
    assert cli.main(["actors", str(tmp_path / "scene"), "--time", "1.0"]) == 0


def test_the_ground_fill_is_drawn_only_where_a_view_takes_its_actor_away(tmp_path):
    """An actor's ground fill (runtime.groundfill: the road under it no frame saw) is drawn when the view hides it
    or moves it away (farther than CLEARED_TOL) from where it stands at the view's time; not without edits, not for
    a nudge within the tolerance, an inserted copy, or an actor not there then. Through actors.npz."""
    from xyzcyl.runtime.actors import Actors
    from xyzcyl.runtime.camera import Camera, pinhole_K
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import Scene
    from xyzcyl.testing import EXAMPLE_RIG

    x, y = (a.ravel() for a in np.meshgrid(np.arange(8.1, 12.0, 0.2), np.arange(-0.9, 1.0, 0.2), indexing="ij"))
    n = len(x)
    fill = Gaussians(np.column_stack([x, y, np.zeros(n)]).astype(np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                     np.tile(np.log(np.float32([0.14, 0.14, 0.02])), (n, 1)), np.full(n, 3.0, np.float32),
                     np.full((n, 1, 3), 1.5, np.float32))
    T = np.array(_pose(10.0), float)
    T[2, 3] = 0.75                                    # a 4 x 2 x 1.5 m box standing still at x = 10 m, 0..2 s
    empty = Gaussians.empty(0)
    Actors(track_id=("car",), track_label=("Car",), track_size=np.array([[4.0, 2.0, 1.5]]),
           pose_track=np.zeros(3, np.int32), pose_time=np.array([0.0, 1.0, 2.0]), pose=np.array([T] * 3),
           copy_track=np.zeros(1, np.int32), copy_time=np.zeros(1), copy_start=np.array([0, 0]), gaussians=empty,
           fill=fill, fill_track=np.zeros(n, np.int64)).save(tmp_path / "a.npz")
    back = Actors.load(tmp_path / "a.npz")
    assert back.listing()[0]["filled_m2"] == pytest.approx(n * 0.04)
    far = Gaussians(np.array([[60.0, 0.0, 5.0]], np.float32), np.float32([[1, 0, 0, 0]]),
                    np.full((1, 3), 0.0, np.float32), np.zeros(1, np.float32), np.zeros((1, 1, 3), np.float32))
    scene = Scene(gaussians=far, background=None, rig=load_rig(EXAMPLE_RIG), actors=back,
                  drive={"timestamp_s": 0.0, "times_s": [0.0, 1.0, 2.0], "trajectory": [np.eye(4).tolist()] * 3,
                         "keyframes": [0]})
    # a camera 1.5 m up looking down the road at the fill (8-12 m ahead: image rows 72-78)
    c2e = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]], float)
    cam = Camera(K=pinhole_K(100, 100, 79.5, 59.5), cam_to_ego=c2e, width=160, height=120)

    def alpha(t, edits=()):
        return scene.render(cam, t, background=None, actors=actor_edits(list(edits)))[2][73:78, 75:85]

    pose_far = [1, 0, 0, 0, 0, 1, 0, 40, 0, 0, 1, 0, 0, 0, 0, 1]
    assert alpha(1.0).max() < 0.01
    assert alpha(1.0, [{"id": "car", "hide": True}]).min() > 0.5          # thin discs seen at a grazing angle
    assert alpha(1.0, [{"id": "car", "offset": [0, 30, 0]}]).min() > 0.5
    assert alpha(1.0, [{"id": "car", "pose": pose_far}]).min() > 0.5
    assert alpha(1.0, [{"id": "car", "offset": [0.01, 0, 0]}]).max() < 0.01     # within CLEARED_TOL: still there
    assert alpha(1.0, [{"id": "car", "insert": "c2", "pose": pose_far}]).max() < 0.01
    assert alpha(5.0, [{"id": "car", "hide": True}]).max() < 0.01          # not there at 5 s: nothing uncovered
