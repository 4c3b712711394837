"""Render requests (runtime/views.py): camera conventions, batches, nerfstudio camera paths, encodings, keys."""

from __future__ import annotations

import copy
import io
import math

import cv2
import numpy as np
import pytest
from xyzcyl.runtime import convert
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.png import encode_png
from xyzcyl.runtime.png import to_u8 as _u8
from xyzcyl.runtime.render import Gaussians
from xyzcyl.runtime.rig import Rig, look_rotation
from xyzcyl.runtime.scene import Scene, render_view, rig_camera
from xyzcyl.runtime.views import (
    ViewError,
    ViewRequest,
    camera_from_carla_pose,
    camera_from_opencv,
    camera_from_rig,
    cameras_from_batch,
    depth_to_mm16,
    encode_view,
    render_request,
)


def _pose(yaw_deg=20.0, pitch_deg=-5.0, t=(1.5, -0.25, 1.75)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = look_rotation(math.radians(yaw_deg), math.radians(pitch_deg))
    T[:3, 3] = t
    return T


def _field(exc_info) -> str:
    e = exc_info.value
    assert str(e).startswith(f"{e.field}: "), str(e)   # the message names the field
    return e.field


def _rig() -> Rig:
    front = Camera(name="CAM_FRONT", width=160, height=90, K=[[100.0, 0, 79.5], [0, 100.0, 44.5], [0, 0, 1]],
                   cam_to_ego=_pose(0.0, 0.0, (1.5, 0.0, 1.6)))
    back = Camera(name="CAM_BACK", width=200, height=100, K=[[120.0, 0, 99.5], [0, 110.0, 49.5], [0, 0, 1]],
                  cam_to_ego=_pose(180.0, 0.0, (-1.0, 0.0, 1.6)))
    return Rig(cameras=(front, back))


# ------------------------------------------------------------------------------------------- OpenCV


def test_opencv_fov_gives_horizontal_focal_length_and_centred_principal_point():
    for W, H, fov in ((640, 480, 90.0), (1600, 900, 70.0), (33, 17, 1.5)):
        cam = camera_from_opencv(_pose(), W, H, fov=fov)
        f = W / (2.0 * math.tan(math.radians(fov) / 2.0))
        np.testing.assert_allclose(cam.K, [[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], rtol=1e-15)
        assert (cam.width, cam.height) == (W, H)
    assert camera_from_opencv(_pose(), 640, 480, fov=90).K[0, 0] == pytest.approx(320.0, rel=1e-15)


def test_opencv_K_and_pose_reach_the_camera_exactly():
    T = _pose(37.0, 3.0, (0.1, 0.2, 0.3))
    for pose in (T.ravel().tolist(), T.tolist(), T):
        cam = camera_from_opencv(pose, 321, 123, fx=211.25, fy=207.5, cx=160.25, cy=60.75)
        np.testing.assert_array_equal(cam.cam_to_ego, T)
        np.testing.assert_array_equal(cam.K, [[211.25, 0, 160.25], [0, 207.5, 60.75], [0, 0, 1]])
    cam = camera_from_opencv(T, 100, 50, fx=80.0)   # fy = fx, principal point at the OpenCV image centre
    np.testing.assert_array_equal(cam.K, [[80.0, 0, 49.5], [0, 80.0, 24.5], [0, 0, 1]])


def test_opencv_errors_name_the_field():
    T = _pose()
    bad = T.copy()
    bad[:3, :3] *= 1.01   # not orthonormal
    cases = [
        ({"cam_to_ego": bad, "width": 64, "height": 48, "fov": 60}, "cam_to_ego"),
        ({"cam_to_ego": np.diag([1.0, 1, -1, 1]), "width": 64, "height": 48, "fov": 60}, "cam_to_ego"),  # reflection
        ({"cam_to_ego": T.ravel()[:15].tolist(), "width": 64, "height": 48, "fov": 60}, "cam_to_ego"),
        ({"cam_to_ego": [[1, 0, 0, 0]] * 3 + [[0, 0, 0, 2]], "width": 64, "height": 48, "fov": 60}, "cam_to_ego"),
        ({"cam_to_ego": T.ravel().tolist()[:-1] + [float("nan")], "width": 64, "height": 48, "fov": 60}, "cam_to_ego"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fov": 60, "fx": 50.0}, "fov"),   # both
        ({"cam_to_ego": T, "width": 64, "height": 48}, "fov"),                    # neither
        ({"cam_to_ego": T, "width": 64, "height": 48, "fov": 180.0}, "fov"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fov": 0.0}, "fov"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fov": 60, "fy": 50.0}, "fy"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fov": 60, "cx": 3.0}, "cx"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fx": -5.0}, "fx"),
        ({"cam_to_ego": T, "width": 64, "height": 48, "fx": 50.0, "fy": 0.0}, "fy"),
        ({"cam_to_ego": T, "width": 0, "height": 48, "fov": 60}, "width"),
        ({"cam_to_ego": T, "width": 64.5, "height": 48, "fov": 60}, "width"),
        ({"cam_to_ego": T, "width": 64, "height": True, "fov": 60}, "height"),
        ({"cam_to_ego": T, "width": 64, "height": [48], "fov": 60}, "height"),
    ]
    for kwargs, field in cases:
        with pytest.raises(ViewError) as ei:
            camera_from_opencv(**kwargs)
        assert _field(ei) == field, (kwargs, str(ei.value))


# ------------------------------------------------------------------------------------------- CARLA


@pytest.mark.parametrize("pose", [(0, 0, 0, 0, 0, 0), (1.5, 0.5, 1.7, -10, 30, 2), (-2, -0.3, 2.2, 15, -135, -4),
                                  (0.2, 0, 3, -90, 45, 0)])
def test_carla_pose_is_convert_camera_from_carla(pose):
    x, y, z, pitch, yaw, roll = pose
    cam = camera_from_carla_pose(x, y, z, pitch, yaw, roll, 85.0, 800, 450)
    ref = convert.camera_from_carla({"transform": {"location": {"x": x, "y": y, "z": z},
                                                   "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
                                     "fov": 85.0, "image_size_x": 800, "image_size_y": 450})
    np.testing.assert_array_equal(cam.K, ref.K)
    np.testing.assert_array_equal(cam.cam_to_ego, ref.cam_to_ego)
    assert isinstance(cam, Camera) and (cam.width, cam.height) == (800, 450)


def test_carla_forward_camera_looks_along_ego_x():
    cam = camera_from_carla_pose(1.5, 0.5, 1.7, 0, 0, 0, 90, 640, 480)
    R = cam.cam_to_ego[:3, :3]
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)    # optical axis (OpenCV z) = ego forward
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-12)   # image right = ego right (-y)
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)   # image down = ego down
    np.testing.assert_allclose(cam.cam_to_ego[:3, 3], [1.5, -0.5, 1.7])   # CARLA y right -> ego -y
    right = camera_from_carla_pose(0, 0, 0, 0, 90, 0, 90, 640, 480)   # CARLA yaw + turns right
    np.testing.assert_allclose(right.cam_to_ego[:3, 2], [0, -1, 0], atol=1e-12)
    assert right.K[0, 0] == pytest.approx(320.0)


def test_carla_errors_name_the_field():
    ok = {"x": 0, "y": 0, "z": 1, "pitch": 0, "yaw": 0, "roll": 0, "fov": 90, "width": 64, "height": 48}
    for key, value in (("fov", 0), ("fov", 180), ("yaw", "a"), ("x", float("inf")), ("width", 1.5),
                       ("height", 0), ("roll", None)):
        with pytest.raises(ViewError) as ei:
            camera_from_carla_pose(**{**ok, key: value})
        assert _field(ei) == key


# ------------------------------------------------------------------------------------------- input cameras


def test_camera_from_rig_and_resizing():
    rig = _rig()
    cam = camera_from_rig(rig, "CAM_BACK")
    ref = rig_camera(rig.camera("CAM_BACK"))
    np.testing.assert_array_equal(cam.K, ref.K)
    np.testing.assert_array_equal(cam.cam_to_ego, ref.cam_to_ego)
    half = camera_from_rig(rig, "CAM_BACK", width=100)   # height follows the aspect ratio
    assert (half.width, half.height) == (100, 50)
    np.testing.assert_allclose(half.K, rig_camera(rig.camera("CAM_BACK"), width=100, height=50).K)
    assert (camera_from_rig(rig, "CAM_FRONT", height=45).width, camera_from_rig(rig, "CAM_FRONT", 32, 32).height) \
        == (80, 32)
    with pytest.raises(ViewError) as ei:
        camera_from_rig(rig, "CAM_LEFT")
    assert ei.value.field == "camera"
    assert str(ei.value) == "camera: no camera 'CAM_LEFT' in the scene's rig (cameras: CAM_FRONT, CAM_BACK)"
    with pytest.raises(ViewError) as ei:
        camera_from_rig(rig, "CAM_FRONT", width=-3)
    assert _field(ei) == "width"


# ------------------------------------------------------------------------------------------- nerfstudio paths


def _gl_pose(forward, right, up, t) -> list[float]:
    """camera_to_world with OpenGL camera axes (x right, y up, z back) as 16 row-major numbers."""
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, up, -np.asarray(forward, float), t
    return T.ravel().tolist()


def _camera_path() -> dict:
    return {"camera_type": "perspective", "render_width": 80, "render_height": 60, "seconds": 2.0,
            "camera_path": [
                {"camera_to_world": _gl_pose((1, 0, 0), (0, -1, 0), (0, 0, 1), (1, 2, 3)), "fov": 50, "aspect": 4 / 3},
                {"camera_to_world": _gl_pose((0, 1, 0), (1, 0, 0), (0, 0, 1), (0, 0, 1.5)), "fov": 30.0,
                 "aspect": 4 / 3, "render_time": 0.5},
            ]}


def test_camera_path_flips_opengl_to_opencv_and_uses_vertical_fov():
    cams = cameras_from_batch(_camera_path())
    assert len(cams) == 2 and all(isinstance(c, Camera) for c in cams)
    a, b = cams
    np.testing.assert_array_equal(a.cam_to_ego[:3, 2], [1, 0, 0])    # OpenCV z = ego +x (GL -z)
    np.testing.assert_array_equal(a.cam_to_ego[:3, 1], [0, 0, -1])   # OpenCV y (down) = -GL y (up)
    np.testing.assert_array_equal(a.cam_to_ego[:3, 0], [0, -1, 0])
    np.testing.assert_array_equal(a.cam_to_ego[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(b.cam_to_ego[:3, 2], [0, 1, 0])
    f = 30.0 / math.tan(math.radians(25.0))   # (H/2) / tan(vertical fov / 2), square pixels
    np.testing.assert_allclose(a.K, [[f, 0, 39.5], [0, f, 29.5], [0, 0, 1]], rtol=1e-15)
    assert math.degrees(2 * math.atan(60 / (2 * b.K[1, 1]))) == pytest.approx(30.0)
    assert (a.width, a.height) == (80, 60)


def test_camera_path_round_trip():
    doc = _camera_path()
    cams = convert.cameras_from_nerfstudio_path(doc)
    assert [c.name for c in cams] == ["frame_00000", "frame_00001"]
    out = convert.cameras_to_nerfstudio_path(cams, fps=1.0)
    assert (out["render_width"], out["render_height"], out["camera_type"], out["seconds"]) == (80, 60,
                                                                                                "perspective", 2.0)
    for fr_in, fr_out in zip(doc["camera_path"], out["camera_path"]):
        np.testing.assert_allclose(fr_out["camera_to_world"], fr_in["camera_to_world"], atol=1e-15)
        assert fr_out["fov"] == pytest.approx(fr_in["fov"], rel=1e-12)
        assert fr_out["aspect"] == pytest.approx(4 / 3)
    again = convert.cameras_from_nerfstudio_path(out)
    for c, d in zip(cams, again):
        np.testing.assert_allclose(d.K, c.K, rtol=1e-12)
        np.testing.assert_array_equal(d.cam_to_ego, c.cam_to_ego)
    # a rig camera that a three.js camera cannot express is refused (fx != fy; off-centre principal point)
    with pytest.raises(convert.ConversionError, match="fx != fy"):
        convert.cameras_to_nerfstudio_path([_rig().camera("CAM_BACK")])
    off = _rig().camera("CAM_FRONT").replace(K=[[100.0, 0, 70], [0, 100.0, 44.5], [0, 0, 1]])
    with pytest.raises(convert.ConversionError, match="principal point"):
        convert.cameras_to_nerfstudio_path([off])


def test_camera_path_equirectangular():
    doc = _camera_path()
    doc["camera_type"] = "equirectangular"
    cams = cameras_from_batch(doc)
    assert all(isinstance(c, Camera) for c in cams)
    np.testing.assert_array_equal(cams[0].cam_to_ego[:3, 2], [1, 0, 0])
    out = convert.cameras_to_nerfstudio_path(convert.cameras_from_nerfstudio_path(doc))
    assert out["camera_type"] == "equirectangular" and "fov" not in out["camera_path"][0]


def test_camera_path_errors_name_the_json_path():
    def field_of(mutate, **kw):
        doc = copy.deepcopy(_camera_path())
        mutate(doc)
        with pytest.raises(ViewError) as ei:
            cameras_from_batch(doc, **kw)
        return _field(ei)

    assert field_of(lambda d: d["camera_path"][1].pop("fov")) == "camera_path[1].fov"
    assert field_of(lambda d: d["camera_path"][0].update(fov=180)) == "camera_path[0].fov"
    assert field_of(lambda d: d["camera_path"][0].update(camera_to_world=[1.0] * 15)) \
        == "camera_path[0].camera_to_world"
    assert field_of(lambda d: d["camera_path"][1].update(camera_to_world=np.diag([2.0, 1, 1, 1]).ravel().tolist())) \
        == "camera_path[1].camera_to_world"
    assert field_of(lambda d: d["camera_path"][1].pop("camera_to_world")) == "camera_path[1].camera_to_world"
    assert field_of(lambda d: d.pop("render_width")) == "render_width"
    assert field_of(lambda d: d.update(render_height=0.5)) == "render_height"
    assert field_of(lambda d: d.update(camera_type="vr180_l")) == "camera_type"
    assert field_of(lambda d: d.update(camera_path=[])) == "camera_path"
    assert field_of(lambda d: d["camera_path"].__setitem__(0, 7)) == "camera_path[0]"
    assert field_of(lambda d: None, max_frames=1) == "camera_path"
    assert field_of(lambda d: d.update(cameras=[])) == "cameras"   # both forms at once


# ------------------------------------------------------------------------------------------- batches


def test_batch_accepts_each_item_kind():
    rig = _rig()
    T = _pose(-30.0, 2.0, (0.5, 0.5, 1.5))
    K = [[200.0, 0, 150.0], [0, 190.0, 80.0], [0, 0, 1]]
    carla = {"transform": {"location": {"x": 1.0, "y": 0.5, "z": 1.8}, "rotation": {"pitch": -5, "yaw": 20, "roll": 0}},
             "fov": 70, "image_size_x": 320, "image_size_y": 180, "sensor_tick": 0.05}
    doc = {"output": "rgb", "cameras": [
        {"K": K, "cam_to_ego": T.tolist(), "width": 300, "height": 160},
        {"K": np.ravel(K).tolist(), "cam_to_ego": T.ravel().tolist(), "width": 300, "height": 160, "name": "a"},
        {"fov": 60, "cam_to_ego": T.ravel().tolist(), "width": 320, "height": 240},
        carla,
        {"camera": "CAM_BACK"},
        {"camera": "CAM_FRONT", "width": 80, "height": 45},
    ]}
    cams = cameras_from_batch(doc, rig=rig, max_frames=6)
    assert len(cams) == 6
    ref_k = camera_from_opencv(T, 300, 160, fx=200.0, fy=190.0, cx=150.0, cy=80.0)
    for c in cams[:2]:
        np.testing.assert_array_equal(c.K, ref_k.K)
        np.testing.assert_array_equal(c.cam_to_ego, T)
    np.testing.assert_array_equal(cams[2].K, camera_from_opencv(T, 320, 240, fov=60).K)
    ref_carla = camera_from_carla_pose(1.0, 0.5, 1.8, -5, 20, 0, 70, 320, 180)
    np.testing.assert_array_equal(cams[3].K, ref_carla.K)
    np.testing.assert_array_equal(cams[3].cam_to_ego, ref_carla.cam_to_ego)
    np.testing.assert_array_equal(cams[4].K, camera_from_rig(rig, "CAM_BACK").K)
    assert (cams[5].width, cams[5].height) == (80, 45)


def test_batch_errors_name_the_json_path():
    rig = _rig()
    T = _pose().ravel().tolist()
    good = {"fov": 60, "cam_to_ego": T, "width": 32, "height": 24}
    carla = {"transform": {"location": {"x": 1.0, "y": 0.5, "z": 1.8}, "rotation": {"pitch": 0, "yaw": 0, "roll": 0}},
             "fov": 70, "image_size_x": 32, "image_size_y": 24}

    def field_of(doc, **kw):
        with pytest.raises(ViewError) as ei:
            cameras_from_batch(doc, **kw)
        return _field(ei)

    skew = {"K": [[100.0, 0.5, 16], [0, 100, 12], [0, 0, 1]], "cam_to_ego": T, "width": 32, "height": 24}
    assert field_of({"cameras": [good, good, skew]}) == "cameras[2].K"
    assert field_of({"cameras": [good, {**skew, "K": [1, 2, 3]}]}) == "cameras[1].K"
    assert field_of({"cameras": [good, {"fov": 60, "width": 32, "height": 24}]}) == "cameras[1].cam_to_ego"
    assert field_of({"cameras": [{**good, "fov": 200}]}) == "cameras[0].fov"
    assert field_of({"cameras": [good, good, good, {**good, "fov": "wide"}]}) == "cameras[3].fov"
    assert field_of({"cameras": [{**good, "width": 0}]}) == "cameras[0].width"
    assert field_of({"cameras": [{**good, "heigth": 24}]}) == "cameras[0].heigth"   # misspelt, not dropped
    assert field_of({"cameras": [{**good, "K": skew["K"]}]}) == "cameras[0].fov"    # K and fov together
    bent = list(T)
    bent[0] += 0.1
    assert field_of({"cameras": [{**good, "cam_to_ego": bent}]}) == "cameras[0].cam_to_ego"
    no_x = copy.deepcopy(carla)
    del no_x["transform"]["location"]["x"]
    assert field_of({"cameras": [no_x]}) == "cameras[0].transform.location.x"
    bad_yaw = copy.deepcopy(carla)
    bad_yaw["transform"]["rotation"]["yaw"] = None
    assert field_of({"cameras": [good, bad_yaw]}) == "cameras[1].transform.rotation.yaw"
    assert field_of({"cameras": [{**carla, "image_size_x": 3.5}]}) == "cameras[0].image_size_x"
    assert field_of({"cameras": [{**carla, "transform": []}]}) == "cameras[0].transform"
    assert field_of({"cameras": [good, {"camera": "CAM_LEFT"}]}, rig=rig) == "cameras[1].camera"
    assert field_of({"cameras": [{"camera": "CAM_FRONT"}]}) == "cameras[0].camera"   # no rig given
    assert field_of({"cameras": [{"camera": "CAM_FRONT", "width": "big"}]}, rig=rig) == "cameras[0].width"
    assert field_of({"cameras": [good, 3]}) == "cameras[1]"
    assert field_of({"cameras": [{"width": 3}]}) == "cameras[0]"
    assert field_of({"cameras": []}) == "cameras"
    assert field_of({"cameras": {"a": good}}) == "cameras"
    assert field_of({"cameras": [good] * 3}, max_frames=2) == "cameras"
    assert field_of({}) == "cameras"
    assert field_of([good]) == "cameras"
    assert len(cameras_from_batch({"cameras": [good] * 2}, max_frames=2)) == 2


# ------------------------------------------------------------------------------------------- requests and keys


def test_request_validation_and_media_types():
    cam = camera_from_opencv(_pose(), 64, 48, fov=60)
    r = ViewRequest(cam)
    assert (r.output, r.format, r.quality, r.media_type, r.extension, r.pixels) == ("rgb", "png", 90, "image/png",
                                                                                   ".png", 64 * 48)
    assert (ViewRequest(cam, "depth", "exr").media_type, ViewRequest(cam, "alpha", "jpeg").extension) == \
        ("image/x-exr", ".jpg")
    for kwargs, field in (({"output": "normals"}, "output"), ({"format": "gif"}, "format"),
                          ({"quality": 0}, "quality"), ({"quality": 101}, "quality"), ({"quality": True}, "quality"),
                          ({"quality": 90.0}, "quality"), ({"output": "depth", "format": "jpeg"}, "format")):
        with pytest.raises(ViewError) as ei:
            ViewRequest(cam, **kwargs)
        assert _field(ei) == field
    with pytest.raises(ViewError) as ei:
        ViewRequest("CAM_FRONT")   # a name, not a camera
    assert _field(ei) == "camera"
    ViewRequest(_rig().camera("CAM_FRONT"))    # one camera type: a rig's camera renders as it is, lens and all
    ViewRequest(_rig().camera("CAM_FRONT").replace(distortion=(0.1, 0.0, 0.0, 0.0)))


def test_key_is_stable_and_changes_with_every_field():
    T = _pose()

    def req(T=T, W=64, H=48, **kw):
        return ViewRequest(camera_from_opencv(T, W, H, fx=50.0, fy=51.0, cx=31.5, cy=23.5), **kw)

    base = req(format="jpeg")
    key = base.key()
    assert len(key) == 64 and int(key, 16) >= 0
    assert req(format="jpeg").key() == key                                   # equal requests, equal keys
    assert req(T=T.tolist(), format="jpeg").key() == key
    T_tiny = T.copy()
    T_tiny[0, 3] += 1e-13                                                    # below the 1e-9 rounding
    assert req(T=T_tiny, format="jpeg").key() == key
    others = [req(W=65, format="jpeg"), req(H=47, format="jpeg"), req(output="alpha", format="jpeg"),
              req(format="png"), req(format="jpeg", quality=91),
              ViewRequest(camera_from_opencv(T, 64, 48, fx=50.0, fy=51.0, cx=31.5, cy=23.25), format="jpeg"),
              ViewRequest(Camera(model="equirectangular", cam_to_ego=T, width=64, height=48), format="jpeg")]
    for i in range(3):   # every rotation and translation entry (1e-6 stays within the 1e-4 orthonormality test)
        for j in range(4):
            moved = T.copy()
            moved[i, j] += 1e-6
            others.append(req(T=moved, format="jpeg"))
    keys = [o.key() for o in others]
    assert key not in keys and len(set(keys)) == len(keys)
    zero = T.copy()
    zero[2, 0] = 0.0
    negz = T.copy()
    negz[2, 0] = -0.0
    assert req(T=zero).key() == req(T=negz).key()   # -0.0 and 0.0 describe the same pose


# ------------------------------------------------------------------------------------------- encoding


def _decode(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def _read_exr(data: bytes, tmp_path) -> tuple[np.ndarray, tuple[str, ...]]:
    import OpenImageIO as oiio

    path = tmp_path / "x.exr"
    path.write_bytes(data)
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    inp.close()
    return np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels), tuple(spec.channelnames)


@pytest.fixture
def planes():
    H, W = 23, 37
    rng = np.random.default_rng(7)
    rgb = rng.uniform(-0.1, 1.1, (H, W, 3)).astype(np.float32)   # out of range values must clip
    rgb[0, 0] = (1.0, 0.0, 0.0)                                     # pure red: catches a BGR/RGB swap
    depth = rng.uniform(0.5, 80.0, (H, W)).astype(np.float32)
    depth[0, :4] = (0.0, 70.0, 0.0002, np.nan)                      # no surface, saturated, sub-mm, invalid
    depth[1, :3] = (65.535, 65.5354, 1.0005)
    alpha = rng.uniform(0.0, 1.0, (H, W)).astype(np.float32)
    cam = camera_from_opencv(_pose(), W, H, fov=70)
    return cam, rgb, depth, alpha


def test_png_encodings_are_exact(planes):
    cam, rgb, depth, alpha = planes
    img = _decode(encode_view(rgb, depth, alpha, ViewRequest(cam, "rgb", "png")))
    assert img.dtype == np.uint8 and img.shape == (23, 37, 3)
    want = np.clip(np.rint(rgb.astype(np.float64) * 255), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(img[..., ::-1], want)            # decoded BGR -> RGB
    assert tuple(img[0, 0]) == (0, 0, 255)                          # red sits in OpenCV's last (R) channel

    d16 = _decode(encode_view(None, depth, None, ViewRequest(cam, "depth", "png")))
    assert d16.dtype == np.uint16 and d16.shape == (23, 37)
    ref = np.clip(np.rint(np.nan_to_num(depth.astype(np.float64), nan=0.0) * 1000), 0, 65535)
    ref[(np.nan_to_num(depth) > 0) & (ref == 0)] = 1
    np.testing.assert_array_equal(d16, ref.astype(np.uint16))
    assert tuple(d16[0, :4]) == (0, 65535, 1, 0) and tuple(d16[1, :3]) == (65535, 65535, 1000)

    a8 = _decode(encode_view(None, None, alpha, ViewRequest(cam, "alpha", "png")))
    assert a8.dtype == np.uint8 and a8.shape == (23, 37)
    np.testing.assert_array_equal(a8, np.rint(alpha.astype(np.float64) * 255).astype(np.uint8))


def test_exr_encodings_are_float32_exact(planes, tmp_path):
    cam, rgb, depth, alpha = planes
    for out, arr, names in (("rgb", rgb, ("R", "G", "B")), ("depth", depth, ("Z",)), ("alpha", alpha, ("A",))):
        data = encode_view(rgb, depth, alpha, ViewRequest(cam, out, "exr"))
        img, got = _read_exr(data, tmp_path)
        assert got == names
        np.testing.assert_array_equal(img, arr.reshape(23, 37, -1))   # unclipped, NaN kept (assert_array_equal
                                                                      # treats NaN == NaN)


def test_jpeg_encodings_are_close(planes):
    cam = planes[0]
    H, W = cam.height, cam.width
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    # A smooth image: JPEG's 8x8 DCT quantisation and OpenCV's default 4:2:0 chroma subsampling lose detail
    # the eye does not see; on smooth gradients at quality 95 that is a few 8-bit levels per pixel. Noise would
    # not be a fair test of the encoding path (it is the worst case for JPEG), a BGR/RGB swap would be 100+ levels.
    rgb = np.stack([xx / W, yy / H, 0.5 + 0.3 * np.sin(xx / 6.0)], axis=-1)
    img = _decode(encode_view(rgb, None, None, ViewRequest(cam, "rgb", "jpeg", quality=95)))
    assert img.shape == (H, W, 3)
    err = np.abs(img[..., ::-1].astype(np.float64) - rgb * 255)
    assert err.mean() < 2.0 and err.max() < 12.0, (err.mean(), err.max())
    alpha = (xx + yy) / (W + H)
    a8 = _decode(encode_view(None, None, alpha, ViewRequest(cam, "alpha", "jpeg", quality=95)))
    assert a8.shape == (H, W) and a8.dtype == np.uint8            # grey: no chroma, only the DCT loss
    assert np.abs(a8 - alpha * 255).max() < 4.0
    small = encode_view(rgb, None, None, ViewRequest(cam, "rgb", "jpeg", quality=10))
    assert len(small) < len(encode_view(rgb, None, None, ViewRequest(cam, "rgb", "jpeg", quality=95)))


def test_encode_checks_the_planes(planes):
    cam, rgb, depth, alpha = planes
    with pytest.raises(ValueError, match="rgb: expected shape"):
        encode_view(rgb[:, :-1], depth, alpha, ViewRequest(cam))
    with pytest.raises(ValueError, match="depth: needed"):
        encode_view(rgb, None, alpha, ViewRequest(cam, "depth"))


def _u8_reference(a) -> np.ndarray:
    x = np.rint(np.asarray(a, np.float64) * 255.0)
    return np.nan_to_num(np.clip(x, 0, 255), nan=0.0).astype(np.uint8)


def _halves(dtype) -> np.ndarray:
    """(k + 1/2) / 255 for every level k, as ``dtype``, with their neighbours one ulp either side: the values
    where round half to even, float32 vs float64 arithmetic and an off-by-one would show."""
    h = ((np.arange(-2, 258) + 0.5) / 255.0).astype(dtype)
    return np.concatenate([h, np.nextafter(h, dtype(-np.inf)), np.nextafter(h, dtype(np.inf)),
                           (np.arange(-2, 258) / 255.0).astype(dtype)])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_u8_equals_the_numpy_reference_exactly(dtype):
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-0.5, 1.5, 200_000).astype(dtype), _halves(dtype),
                        np.array([np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, 2.0, -1e30, 1e30,
                                  np.finfo(dtype).tiny, -np.finfo(dtype).tiny, 0.5 / 255, 254.5 / 255], dtype)])
    rng.shuffle(x)
    got = _u8(x)
    assert got.dtype == np.uint8 and got.shape == x.shape
    np.testing.assert_array_equal(got, _u8_reference(x))
    img = x[: 30 * 40 * 3].reshape(30, 40, 3)
    np.testing.assert_array_equal(_u8(img), _u8_reference(img))                 # [H, W, 3]
    np.testing.assert_array_equal(_u8(img, bgr=True), _u8_reference(img)[..., ::-1])   # OpenCV's order
    np.testing.assert_array_equal(_u8(img[:, ::-2, 1]), _u8_reference(img[:, ::-2, 1]))   # strided view


def test_depth_to_mm16_equals_the_numpy_reference_exactly():
    rng = np.random.default_rng(4)
    h = (np.arange(0, 70_000, 7) + 0.5) / 1000.0
    d = np.concatenate([rng.uniform(-1.0, 80.0, 100_000), h, np.nextafter(h, 0), np.nextafter(h, 1e9),
                        [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-9, 0.0004999, 0.0005, 0.0015, 65.535, 65.5355,
                         65.5354, 1e300, -1e-300]])
    with np.errstate(over="ignore"):
        d32 = d.astype(np.float32)                                     # 1e300 -> inf
    for arr in (d, d32):
        x = arr.astype(np.float64)
        ref = np.clip(np.rint(np.where(np.isfinite(x), x, 0.0) * 1000.0), 0, 65535)
        ref[np.isfinite(x) & (x > 0) & (ref < 1)] = 1
        got = depth_to_mm16(arr)
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, ref.astype(np.uint16))


def _decode_pil(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return np.array(im)


@pytest.mark.parametrize("row_filter", ["paeth", "sub", "up", "none"])
def test_encode_png_round_trips_exactly(row_filter):
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:45, 0:61]
    smooth = (xx * 3 + yy * 5) % 256                                   # long runs for the filters to find
    cases = [rng.integers(0, 256, (45, 61, 3), dtype=np.uint8),
             np.dstack([smooth, 255 - smooth, rng.integers(0, 256, (45, 61))]).astype(np.uint8),
             rng.integers(0, 256, (45, 61), dtype=np.uint8),
             rng.integers(0, 256, (45, 61, 1), dtype=np.uint8),
             rng.integers(0, 256, (45, 61, 2), dtype=np.uint8),
             rng.integers(0, 256, (45, 61, 4), dtype=np.uint8),
             rng.integers(0, 65536, (45, 61), dtype=np.uint16),
             (smooth * 257 + rng.integers(0, 3, (45, 61))).astype(np.uint16),
             rng.integers(0, 65536, (45, 61, 3), dtype=np.uint16),
             rng.integers(0, 256, (1, 1, 3), dtype=np.uint8), rng.integers(0, 65536, (1, 7), dtype=np.uint16),
             rng.integers(0, 256, (9, 1, 3), dtype=np.uint8)]
    for img in cases:
        data = encode_png(img, row_filter)
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        flat = img[..., 0] if img.ndim == 3 and img.shape[2] == 1 else img
        got = _decode(data)
        if got.ndim == 3:                                              # OpenCV decodes to BGR(A)
            got = cv2.cvtColor(got, cv2.COLOR_BGR2RGB if got.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
        if img.ndim == 3 and img.shape[2] == 2:                         # OpenCV: grey + alpha -> BGRA
            got = got[..., [0, 3]]
        assert got.dtype == img.dtype, (img.shape, img.dtype)
        np.testing.assert_array_equal(got, flat, err_msg=f"{img.dtype} {img.shape}")
        if img.dtype == np.uint8 or img.ndim == 2:                      # Pillow: 8-bit and 16-bit grey
            np.testing.assert_array_equal(_decode_pil(data).astype(img.dtype), flat)


def test_encode_png_refuses_what_png_cannot_hold():
    with pytest.raises(ValueError, match="uint8 or uint16"):
        encode_png(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        encode_png(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(ValueError, match="empty"):
        encode_png(np.zeros((0, 4), np.uint8))
    with pytest.raises(ValueError, match="row_filter"):
        encode_png(np.zeros((4, 4), np.uint8), "average")
    with pytest.raises(ValueError, match="level"):
        encode_png(np.zeros((4, 4), np.uint8), level=9)


def test_write_png_is_the_exact_encoder(tmp_path):
    from xyzcyl.runtime.imageio import write_png

    rgb = np.random.default_rng(8).uniform(-0.2, 1.2, (17, 23, 3)).astype(np.float32)
    rgb[0, :4, 0] = [np.nan, 0.5 / 255, 1.5 / 255, 2.5 / 255]
    write_png(tmp_path / "a.png", rgb)
    got = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got[..., ::-1], _u8_reference(rgb))
    assert (tmp_path / "a.png").read_bytes() == encode_png(_u8(rgb))
    with pytest.raises(OSError, match="cannot write"):
        write_png(tmp_path / "missing" / "a.png", rgb)


# ------------------------------------------------------------------------------------------- rendering


def _tiny_scene() -> Scene:
    """Three opaque Gaussians 4-6 m in front of the rig's one camera (ego +x), no background."""
    means = np.array([[4.0, 0.0, 1.6], [5.0, 0.8, 1.9], [6.0, -1.0, 1.3]], np.float32)
    quats = np.tile(np.array([1.0, 0, 0, 0], np.float32), (3, 1))
    log_scales = np.log(np.full((3, 3), 0.4, np.float32))
    opacity_logits = np.full(3, 4.0, np.float32)
    sh = np.array([[[1.5, -1.0, -1.0]], [[-1.0, 1.5, -1.0]], [[-1.0, -1.0, 1.5]]], np.float32)
    cam = Camera(name="CAM_FRONT", width=64, height=40, K=[[40.0, 0, 31.5], [0, 40.0, 19.5], [0, 0, 1]],
                 cam_to_ego=_pose(0.0, 0.0, (0.0, 0.0, 1.6)))
    return Scene(gaussians=Gaussians(means, quats, log_scales, opacity_logits, sh), background=None,
                 rig=Rig(cameras=(cam,)))


def test_render_request_returns_decodable_bytes_of_the_right_size(tmp_path):
    scene = _tiny_scene()
    cam = camera_from_rig(scene.rig, "CAM_FRONT", 48, 30)
    data = render_request(scene, ViewRequest(cam, "rgb", "png"))
    img = _decode(data)
    assert img.shape == (30, 48, 3)
    rgb, depth, alpha = render_view(scene, cam)
    assert alpha.max() > 0.5 and img.max() > 0   # the Gaussians are in view
    assert data == encode_view(rgb, depth, alpha, ViewRequest(cam, "rgb", "png"))
    z, names = _read_exr(render_request(scene, ViewRequest(cam, "depth", "exr")), tmp_path)
    assert names == ("Z",) and z.shape == (30, 48, 1)
    hit = alpha > 0.5
    assert np.all((z[..., 0][hit] > 3.0) & (z[..., 0][hit] < 7.0))   # metres along the optical axis
    assert _decode(render_request(scene, ViewRequest(cam, "alpha", "jpeg", quality=80))).shape == (30, 48)
