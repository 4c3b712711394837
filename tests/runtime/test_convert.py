"""Foreign conventions: nerfstudio, CARLA, nuScenes, and the Waymo completion."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from xyzcyl.runtime.convert import (
    ConversionError,
    camera_from_carla,
    camera_from_nuscenes,
    camera_to_carla,
    camera_to_nuscenes,
    complete_waymo_rig,
    matrix_to_quat_wxyz,
    mirror_camera,
    quat_wxyz_to_matrix,
    rig_from_nerfstudio,
    rig_to_nerfstudio,
)
from xyzcyl.runtime.cylinder import CylinderSpec, overlay, project_rig
from xyzcyl.runtime.rig import Camera, Rig, load_rig, look_rotation, ring_rig


def _same_camera(a: Camera, b: Camera, atol=1e-9):
    assert (a.name, a.width, a.height, a.model, a.image) == (b.name, b.width, b.height, b.model, b.image)
    np.testing.assert_allclose(a.cam_to_ego, b.cam_to_ego, atol=atol)
    if a.K is not None or b.K is not None:
        np.testing.assert_allclose(a.K, b.K, atol=atol)
    assert a.distortion == b.distortion


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[0] < 0 else q
        R = quat_wxyz_to_matrix(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(matrix_to_quat_wxyz(R), q, atol=1e-10)
    # 180 deg about z: trace -1 branch
    np.testing.assert_allclose(np.abs(matrix_to_quat_wxyz(np.diag([-1.0, -1.0, 1.0]))), [0, 0, 0, 1], atol=1e-12)


# -- nerfstudio --------------------------------------------------------------------------------------------------

def test_nerfstudio_round_trip():
    rig = ring_rig(3, width=64, height=48)
    cams = list(rig.cameras)
    cams[0] = cams[0].replace(image="images/a.png", distortion=(0.1, -0.02, 0.001, 0.002, 0.003))
    cams[2] = cams[2].replace(model="equirectangular", K=None, extra={"colmap_im_id": 3})
    rig = Rig(tuple(cams), extra={"applied_scale": 1.0})
    ns = json.loads(json.dumps(rig_to_nerfstudio(rig)))
    back = rig_from_nerfstudio(ns)
    for a, b in zip(rig.cameras, back.cameras):
        _same_camera(a, b)
    assert back.cameras[2].extra["colmap_im_id"] == 3 and back.extra["applied_scale"] == 1.0


def test_nerfstudio_conventions():
    # camera looking along world -z in OpenGL (identity c2w) = OpenCV camera looking along ego -z (down),
    # image up (GL +y) = ego +y. Shared top-level intrinsics, COLMAP pixel centres (+0.5).
    ns = {"camera_model": "OPENCV", "fl_x": 100.0, "fl_y": 110.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48,
          "frames": [{"file_path": "images/frame_00001.png", "transform_matrix": np.eye(4).tolist()}]}
    (cam,) = rig_from_nerfstudio(ns).cameras
    assert cam.name == "frame_00001"
    np.testing.assert_allclose(cam.rotation[:, 2], [0, 0, -1])  # optical axis
    np.testing.assert_allclose(cam.rotation[:, 1], [0, -1, 0])  # image down
    np.testing.assert_allclose(cam.K, [[100, 0, 31.5], [0, 110, 23.5], [0, 0, 1]])
    again = rig_from_nerfstudio(rig_to_nerfstudio(rig_from_nerfstudio(ns)))
    _same_camera(again.cameras[0], cam)
    with pytest.raises(ConversionError, match=r"frames\[0\]: camera_model: 'FISHEYE624'"):
        rig_from_nerfstudio({**ns, "camera_model": "FISHEYE624"})
    with pytest.raises(ConversionError, match=r"frames\[0\]: fl_x: is missing"):
        rig_from_nerfstudio({k: v for k, v in ns.items() if k != "fl_x"})
    bad = json.loads(json.dumps(ns))
    bad["frames"][0]["transform_matrix"][0][0] = -1.0  # a reflection
    with pytest.raises(ConversionError, match=r"frames\[0\]: .*cam_to_ego.*det"):
        rig_from_nerfstudio(bad)


# -- CARLA -------------------------------------------------------------------------------------------------------

def _carla(pitch=0.0, yaw=0.0, roll=0.0, x=1.5, y=0.0, z=2.4, fov=90.0, w=800, h=600):
    return {"transform": {"location": {"x": x, "y": y, "z": z}, "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
            "fov": fov, "image_size_x": w, "image_size_y": h}


@pytest.mark.parametrize("kw, forward, right, down", [
    ({}, [1, 0, 0], [0, -1, 0], [0, 0, -1]),
    ({"yaw": 90.0}, [0, -1, 0], [-1, 0, 0], [0, 0, -1]),  # CARLA +y = right = ego -y
    ({"yaw": -90.0}, [0, 1, 0], [1, 0, 0], [0, 0, -1]),  # looks left
    ({"yaw": 180.0}, [-1, 0, 0], [0, 1, 0], [0, 0, -1]),
    ({"pitch": 30.0}, [math.cos(math.pi / 6), 0, 0.5], [0, -1, 0], [0.5, 0, -math.cos(math.pi / 6)]),  # + looks up
    ({"pitch": -90.0}, [0, 0, -1], [0, -1, 0], [-1, 0, 0]),  # bird's eye: image top = ego forward
    ({"roll": 90.0}, [1, 0, 0], [0, 0, -1], [0, 1, 0]),  # right wing down: image right = ego down
])
def test_carla_known_cases(kw, forward, right, down):
    cam = camera_from_carla(_carla(**kw, y=0.3), name="cam")
    np.testing.assert_allclose(cam.rotation[:, 2], forward, atol=1e-12)
    np.testing.assert_allclose(cam.rotation[:, 0], right, atol=1e-12)
    np.testing.assert_allclose(cam.rotation[:, 1], down, atol=1e-12)
    np.testing.assert_allclose(cam.position, [1.5, -0.3, 2.4])  # CARLA y right -> ego -y
    assert np.linalg.det(cam.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(cam.K, [[400, 0, 399.5], [0, 400, 299.5], [0, 0, 1]], atol=1e-9)  # fov 90: f = W/2


def test_carla_round_trip():
    rng = np.random.default_rng(1)
    for k in range(100):
        sensor = _carla(pitch=rng.uniform(-89, 89), yaw=rng.uniform(-179, 179), roll=rng.uniform(-179, 179),
                        x=rng.normal(), y=rng.normal(), z=rng.normal(), fov=rng.uniform(20, 150), w=640, h=480)
        cam = camera_from_carla(sensor, name=f"c{k}")
        out = camera_to_carla(cam)
        for key in ("pitch", "yaw", "roll"):
            assert out["transform"]["rotation"][key] == pytest.approx(sensor["transform"]["rotation"][key], abs=1e-7)
        for key in ("x", "y", "z"):
            assert out["transform"]["location"][key] == pytest.approx(sensor["transform"]["location"][key], abs=1e-12)
        assert out["fov"] == pytest.approx(sensor["fov"], abs=1e-9)
        _same_camera(camera_from_carla(out), cam)
    # gimbal lock: straight down, yaw and roll merge; the matrix still round-trips
    cam = camera_from_carla(_carla(pitch=-90.0, yaw=30.0, roll=10.0), name="bev")
    _same_camera(camera_from_carla(camera_to_carla(cam)), cam)


def test_carla_refusals():
    with pytest.raises(ConversionError, match="fov"):
        camera_from_carla(_carla(fov=180.0))
    with pytest.raises(ConversionError, match="transform.rotation.yaw: is missing"):
        s = _carla()
        del s["transform"]["rotation"]["yaw"]
        camera_from_carla(s)
    cam = ring_rig(1).cameras[0]
    with pytest.raises(ConversionError, match="principal point"):
        camera_to_carla(cam.replace(K=cam.K + np.array([[0, 0, 3.0], [0, 0, 0], [0, 0, 0]])))


# -- nuScenes ----------------------------------------------------------------------------------------------------

def test_nuscenes_round_trip_and_real_rig(real_data):
    rig = load_rig(real_data / "nuscenes_ca9a282c" / "rig.json", check_images=False)
    for cam in rig.cameras:
        rec = camera_to_nuscenes(cam)
        assert set(rec) >= {"translation", "rotation", "camera_intrinsic"}
        back = camera_from_nuscenes(json.loads(json.dumps(rec)), name=cam.name, image=cam.image)
        # 1e-7: rig.json stores the rotation rounded to 10 digits (not exactly orthonormal, ~1e-8); the
        # quaternion is of the nearest rotation, so the round trip moves entries by that rounding.
        _same_camera(back, cam.replace(extra={}), atol=1e-7)


def test_nuscenes_record():
    # CAM_FRONT-like record: camera z -> ego x, camera x -> ego -y, camera y -> ego -z
    R = look_rotation(0.0)
    q = matrix_to_quat_wxyz(R)
    rec = {"token": "t", "sensor_token": "s", "translation": [1.7, 0.0, 1.5], "rotation": q.tolist(),
           "camera_intrinsic": [[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]]}
    cam = camera_from_nuscenes(rec, "CAM_FRONT")
    np.testing.assert_allclose(cam.rotation, R, atol=1e-12)
    assert cam.extra["token"] == "t" and (cam.width, cam.height) == (1600, 900)
    assert camera_to_nuscenes(cam)["sensor_token"] == "s"
    with pytest.raises(ConversionError, match="'CAM_X': rotation: "):
        camera_from_nuscenes({**rec, "rotation": [2, 0, 0, 0]}, "CAM_X")
    with pytest.raises(ConversionError, match="'CAM_X': .*K\\[0\\]\\[1\\]"):
        camera_from_nuscenes({**rec, "camera_intrinsic": [[1, 1, 0], [0, 1, 0], [0, 0, 1]]}, "CAM_X")


# -- Waymo completion ---------------------------------------------------------------------------------------------

def _waymo_like():
    cams = []
    specs = [("FRONT", 0.0, 1.5, 0.0), ("FRONT_LEFT", 45.0, 1.4, 0.3), ("FRONT_RIGHT", -45.0, 1.4, -0.3),
             ("SIDE_LEFT", 90.0, 1.0, 0.9), ("SIDE_RIGHT", -90.0, 1.0, -0.9)]
    for name, yaw, x, y in specs:
        f = 96 / (2 * math.tan(math.radians(25)))  # 50 deg horizontal FoV like Waymo's cameras
        K = np.array([[f, 0, 40.0], [0, f, 30.0], [0, 0, 1]])  # off-centre principal point on purpose
        T = np.eye(4)
        T[:3, :3] = look_rotation(math.radians(yaw), math.radians(-2.0))
        T[:3, 3] = [x, y, 2.0]
        cams.append(Camera(name=name, width=96, height=64, K=K, cam_to_ego=T))
    rig = Rig(tuple(cams))
    rng = np.random.default_rng(2)
    return rig, [rng.random((64, 96, 3)).astype(np.float32) for _ in cams]


def test_mirror_camera_pixel_relation():
    rig, _ = _waymo_like()
    rng = np.random.default_rng(3)
    plane = 0.7
    for cam in rig.cameras:
        virt = mirror_camera(cam, plane, "v")
        assert np.linalg.det(virt.rotation) == pytest.approx(1.0)
        pts_cam = np.column_stack([rng.uniform(-4, 4, 100), rng.uniform(-3, 3, 100), rng.uniform(3, 40, 100)])
        P = pts_cam @ cam.rotation.T + cam.position
        uv, _, ok = cam.project(P)
        mirrored = P * [-1, 1, 1] + [2 * plane, 0, 0]
        uv2, _, ok2 = virt.project(mirrored)
        assert ok.all() and ok2.all()
        np.testing.assert_allclose(uv2[:, 0], cam.width - 1 - uv[:, 0], atol=1e-9)
        np.testing.assert_allclose(uv2[:, 1], uv[:, 1], atol=1e-9)


def test_complete_waymo_rig():
    rig, images = _waymo_like()
    out, out_images = complete_waymo_rig(rig, images)
    assert out.names == ["FRONT", "FRONT_RIGHT", "SIDE_RIGHT", "REAR_RIGHT", "REAR", "REAR_LEFT", "SIDE_LEFT",
                         "FRONT_LEFT"]
    plane = np.mean([c.position[0] for c in rig.cameras])
    azimuth = {c.name: math.degrees(math.atan2(c.rotation[1, 2], c.rotation[0, 2])) for c in out.cameras}
    assert azimuth["REAR"] == pytest.approx(180.0) or azimuth["REAR"] == pytest.approx(-180.0)
    assert azimuth["REAR_LEFT"] == pytest.approx(135.0) and azimuth["REAR_RIGHT"] == pytest.approx(-135.0)
    assert azimuth["SIDE_LEFT"] == pytest.approx(90.0)  # perpendicular to x: mirroring keeps the direction
    np.testing.assert_allclose(out.camera("REAR").position, [2 * plane - 1.5, 0, 2.0])
    np.testing.assert_array_equal(out_images[4], images[0][:, ::-1])  # REAR = flipped FRONT
    np.testing.assert_array_equal(out_images[6], images[3][:, ::-1])  # SIDE_LEFT = flipped side image
    np.testing.assert_array_equal(out_images[0], images[0])
    # the 8 cameras see (almost) the whole horizon of the middle cylinder row, in clockwise order
    spec = CylinderSpec.from_rig(out, height=16, width=256)
    maps, valid = project_rig(spec, out, out_images)
    assert valid.any(axis=0)[8].mean() > 0.95
    assert overlay(maps, "cw").shape == (16, 256, 3)
    with pytest.raises(ConversionError, match="rig: cameras: must be exactly"):
        complete_waymo_rig(Rig(rig.cameras[:4]), images[:4])
