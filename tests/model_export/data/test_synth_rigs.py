"""Rig presets: the nuScenes-like rig reproduces the real sample; the other presets have their FoVs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from xyzcyl.model_export.data.rigs import PRESETS, base_rig, ego_forward_targets, jitter


def test_nuscenes_rig_reproduces_template(real_data):
    tpl = json.loads((real_data / "nuscenes_ca9a282c" / "rig.json").read_text())["cameras"]
    for W, H in ((1600, 900), (400, 224)):
        cams = base_rig("nuscenes", W, H)
        assert [c.name for c in cams] == [c["name"] for c in tpl]
        for c, t in zip(cams, tpl):
            K = np.asarray(t["K"])
            hfov = math.degrees(2 * math.atan(t["width"] / (2 * K[0, 0])))
            vfov = math.degrees(2 * math.atan(t["height"] / (2 * K[1, 1])))
            # the table stores fx/W to 5 digits: 1e-5 relative ~ 0.001 deg; 224/900 != 400/1600 exactly (0.56
            # vs 0.5625) so the vertical FoV at 400x224 differs by the aspect change: 0.3 deg allowed there
            assert abs(math.degrees(c.horizontal_fov) - hfov) < 0.01
            assert abs(math.degrees(c.vertical_fov) - vfov) < (0.01 if H == 900 else 0.3)
            # mounts rounded to 1 mm and 0.001 deg
            np.testing.assert_allclose(c.cam_to_ego[:3, 3], np.asarray(t["cam_to_ego"])[:3, 3], atol=1e-3)
            np.testing.assert_allclose(c.cam_to_ego[:3, :3], np.asarray(t["cam_to_ego"])[:3, :3], atol=1e-4)
    fovs = sorted(round(math.degrees(c.horizontal_fov)) for c in base_rig("nuscenes", 400, 224))
    assert fovs[-1] == 89 and fovs[0] == 64


def test_pandaset_rig_reproduces_template(real_data):
    tpl = json.loads((real_data / "pandaset_002_00" / "rig.json").read_text())["cameras"]
    for c, t in zip(base_rig("pandaset", 1920, 1080), tpl):
        np.testing.assert_allclose(c.K, np.asarray(t["K"]), rtol=1e-4)
        np.testing.assert_allclose(c.cam_to_ego[:3, 3], np.asarray(t["cam_to_ego"])[:3, 3], atol=1e-3)


@pytest.mark.parametrize("name,n,fovs", [("carla-centric", 6, {70, 110}), ("waymo", 5, {50}), ("once", 6, {90}),
                                         ("argoverse", 7, {69}), ("pandaset", 6, {52, 92})])
def test_presets_fovs(name, n, fovs):
    cams = base_rig(name, 400, 224)
    assert len(cams) == n
    assert {round(math.degrees(c.horizontal_fov)) for c in cams} == fovs
    for c in cams:
        R = c.cam_to_ego[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert R[2, 1] < -0.99  # image down = ego -z (cameras level)


def test_every_preset_listed():
    for name in PRESETS:
        assert base_rig(name, 64, 32)


def test_rig_from_json_scales_intrinsics(tmp_path):
    cams = base_rig("nuscenes", 1600, 900)
    p = tmp_path / "rig.json"
    p.write_text(json.dumps({"cameras": [c.to_dict() for c in cams]}))
    small = base_rig(str(p), 400, 225)
    for a, b in zip(cams, small):
        assert abs(math.degrees(a.horizontal_fov) - math.degrees(b.horizontal_fov)) < 1e-9 and abs(math.degrees(a.vertical_fov) - math.degrees(b.vertical_fov)) < 1e-9
    with pytest.raises(ValueError, match="rig"):
        base_rig(str(tmp_path / "missing.json"), 400, 224)


def test_jitter_and_ego_forward():
    rng = np.random.default_rng(0)
    cams = base_rig("nuscenes", 400, 224)
    jit = jitter(cams, rng, 0.02, 0.5)
    for a, b in zip(cams, jit):
        assert np.abs(a.cam_to_ego[:3, 3] - b.cam_to_ego[:3, 3]).max() <= 0.02
        cosang = (np.trace(a.cam_to_ego[:3, :3].T @ b.cam_to_ego[:3, :3]) - 1) / 2
        assert math.degrees(math.acos(min(1.0, cosang))) < 1.0  # three 0.5 deg rotations compose to < 0.87 deg
    lane = np.array([math.cos(0.03), math.sin(0.03), 0.0])
    tg = ego_forward_targets(jit, lane, rng)
    assert len(tg) == 12
    assert [c.name for c in tg[:6]] == [f"{c.name}_t0" for c in jit]
    offs = [dict(c.extra)["ego_offset_m"] for c in tg]
    assert all(-3 <= o <= -1 for o in offs[:6]) and all(1 <= o <= 3 for o in offs[6:])
    for c, o in zip(tg, offs):
        src = jit[tg.index(c) % 6]
        np.testing.assert_allclose(c.cam_to_ego[:3, 3] - src.cam_to_ego[:3, 3], o * lane, atol=1e-6)


@pytest.mark.parametrize("name", PRESETS)
def test_every_camera_of_every_preset_sees_a_street(name):
    """360 degrees around the ego look like a street: every camera sees structures, not empty sky or an empty
    field, and the rig sees the street surface."""
    from xyzcyl.model_export.data.scene import sample_scene

    for seed, index in ((2, 4), (0, 1), (5, 7)):
        _check_street(sample_scene(seed, index), name)


def _check_street(scene, name):
    from xyzcyl.model_export.data.classes import BUILDING, ROAD, SIDEWALK, SKY
    from xyzcyl.model_export.data.trace import build_grid, render_view

    grid = build_grid(scene)
    street = []
    for cam in base_rig(name, 48, 27):
        sem = render_view(scene, grid, cam, ss=1, shadows=False).semantic
        # every camera: not an empty field (structures in view) and not mostly sky
        assert np.mean(sem == SKY) < 0.6, cam.name
        assert np.mean(sem >= BUILDING) > 0.05, cam.name
        street.append(np.mean(np.isin(sem, [ROAD, SIDEWALK])))
    # the rig as a whole sees the street surface (a side camera in a narrow street may see only wall and tree)
    assert np.mean(street) > 0.1
