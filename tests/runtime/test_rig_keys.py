"""Misspelt rig.json keys are named with the key they likely stand for (issue 35 item 12): an unknown key close to
a known one ("camras", "cam_to_eg") is refused naming its field path, before the error its absence would cause
("cameras: must be a list", "cam_to_ego: is missing"); every other unknown key is an extra, kept as before
(the real rigs' and the generated rigs' keys among them)."""

from __future__ import annotations

import copy
import json

import pytest
from xyzcyl.runtime.rig import Rig, RigError, load_rig, save_rig
from xyzcyl.testing.rigs import example_rig


def _rig() -> dict:
    return copy.deepcopy(example_rig())


def _refused(d: dict) -> RigError:
    with pytest.raises(RigError) as e:
        Rig.from_dict(d)
    return e.value


def test_misspelt_top_level_key_is_named():
    d = _rig()
    d["camras"] = d.pop("cameras")
    e = _refused(d)
    assert e.field == "camras" and e.where == "rig"
    assert str(e) == "rig: camras: unknown key (did you mean 'cameras'?)"


def test_misspelt_camera_key_is_named_before_the_missing_one():
    d = _rig()
    d["cameras"][0]["cam_to_eg"] = d["cameras"][0].pop("cam_to_ego")
    e = _refused(d)
    assert e.field == "cameras[0].cam_to_eg" and e.root_field == "cameras"
    assert str(e).endswith("cameras[0].cam_to_eg: unknown key (did you mean 'cam_to_ego'?)"), str(e)
    assert "CAM_FRONT" in str(e) and "missing" not in str(e)


@pytest.mark.parametrize("camera, key, meant, drop", [
    (3, "widht", "width", False),          # beside the right key: a stray misspelling, refused as well
    (2, "k", "K", True),                   # case-insensitive
    (5, "cam2ego", "cam_to_ego", True),    # less close, but the key it stands for is missing
    (1, "ego_mask_", "ego_mask", False),   # a key runtime.detail reads (kept in Camera.extra)
])
def test_nested_camera_keys(tmp_path, camera, key, meant, drop):
    d = _rig()
    cam = d["cameras"][camera]
    cam[key] = cam.pop(meant) if drop else cam.get(meant, "mask.png")
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(d))
    with pytest.raises(RigError) as e:                                  # the file path (CLI, workers) too
        load_rig(path, check_images=False)
    assert e.value.field == f"cameras[{camera}].{key}"
    assert e.value.message == f"unknown key (did you mean {meant!r}?)"
    assert e.value.where == f"camera {cam['name']!r}"


def test_misspelt_ego_pose_is_refused_not_dropped():
    """Without the check a scene posted with 'ego_to_wrld' would be placed at the simulator's origin."""
    d = _rig()
    d["ego_to_wrld"] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert _refused(d).field == "ego_to_wrld"


def test_other_unknown_keys_are_kept(tmp_path):
    d = _rig()
    d.update(notes="free text", ego_pose_source="gnss", timestamp_s=1.5, lidar_file="x.npy")
    d["cameras"][0].update(timestamp_s=2.0, cam_to_world=d["cameras"][0]["cam_to_ego"], exposure_ms=8.0,
                           depth_file="d.exr", serial="A1")
    d["cameras"][1].pop("model", None)                              # optional keys absent: their look-alikes stay
    rig = Rig.from_dict(d)
    assert {"notes", "ego_pose_source", "timestamp_s", "lidar_file"} <= set(rig.extra)
    assert {"timestamp_s", "cam_to_world", "exposure_ms", "depth_file", "serial", "sky", "semantic"} \
        <= set(rig.cameras[0].extra)
    save_rig(rig, tmp_path / "rig.json")                            # written back and read again unchanged
    again = load_rig(tmp_path / "rig.json", check_images=False)
    assert again.to_dict() == rig.to_dict()


def test_real_rigs_keep_their_extras(real_data):
    """Every rig.json of ../shared/data/real loads with its extra keys; the same rig with one key misspelt
    does not."""
    rigs = sorted(real_data.rglob("rig.json"))
    assert rigs
    for path in rigs:
        doc = json.loads(path.read_text())
        rig = load_rig(path, check_images=False)
        assert set(rig.extra) == set(doc) - {"cameras"}, path
        for cam, cd in zip(rig.cameras, doc["cameras"]):
            assert set(cd) - set(cam.to_dict()) == set(), (path, cam.name)
    doc = json.loads(rigs[0].read_text())
    doc["cameras"][-1]["heigth"] = doc["cameras"][-1].pop("height")
    e = _refused(doc)
    assert e.field == f"cameras[{len(doc['cameras']) - 1}].heigth"
    assert e.message == "unknown key (did you mean 'height'?)"
