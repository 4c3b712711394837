"""server/sensorsim/frames.py without a server (issue 29): poses and the frame chain, mid-exposure, intrinsics
rescaled as Camera.resized does, the lens objects of each camera model both ways, the JPEG quality, and every
refusal naming the protocol field, the time of an exposure and a trajectory. The live gRPC calls are
tests/server/test_grpc.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("grpc")

from xyzcyl.runtime.camera import Camera, pinhole_K  # noqa: E402
from xyzcyl.runtime.rig import Rig  # noqa: E402
from xyzcyl.runtime.views import ViewError  # noqa: E402
from xyzcyl.server.sensorsim import frames  # noqa: E402
from xyzcyl.server.sensorsim import sensorsim_pb2 as pb  # noqa: E402


def rigid(yaw: float, t, pitch: float = 0.0) -> np.ndarray:
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    T = np.eye(4)
    T[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T[:3, 3] = t
    return T


CAM = np.array([[0, 0, 1, 1.7], [-1, 0, 0, 0.0], [0, -1, 0, 1.5], [0, 0, 0, 1.0]])   # looks along ego +x


def request(T=CAM, param="opencv_pinhole_param", w=512, h=320, nw=800, nh=450, end=None, **kw) -> pb.RGBRenderRequest:
    spec = pb.CameraSpec(logical_id="CAM_FRONT", resolution_w=nw, resolution_h=nh)
    if param == "opencv_pinhole_param":
        spec.opencv_pinhole_param.CopyFrom(pb.OpenCVPinholeCameraParam(
            focal_length_x=633.2, focal_length_y=633.4, principal_point_x=407.9, principal_point_y=245.5))
    elif param == "opencv_fisheye_param":
        spec.opencv_fisheye_param.CopyFrom(pb.OpenCVFisheyeCameraParam(
            focal_length_x=300.0, focal_length_y=300.0, principal_point_x=399.5, principal_point_y=224.5,
            radial_coeffs=[0.05, -0.01, 0.002, 0.0], max_angle=math.radians(95.0)))
    elif param == "ftheta_param":
        spec.ftheta_param.CopyFrom(pb.FthetaCameraParam(
            principal_point_x=399.5, principal_point_y=224.5, reference_poly=pb.FthetaCameraParam.PIXELDIST_TO_ANGLE,
            pixeldist_to_angle_poly=[0.0, 2.45e-3, 1.2e-7, -2.3e-10], max_angle=math.radians(80.0)))
    pair = pb.PosePair(start_pose=frames.pose_message(T), end_pose=frames.pose_message(T if end is None else end))
    return pb.RGBRenderRequest(scene_id="s", resolution_w=w, resolution_h=h, camera_intrinsics=spec,
                               sensor_pose=pair, image_format=pb.PNG, **kw)


def test_pose_round_trip_and_the_frame_chain():
    T = rigid(0.7, [12.0, -3.5, 0.25], pitch=0.1)
    back = frames.pose_matrix(frames.pose_message(T), "p")
    assert np.allclose(back, T, atol=1e-6)                        # float32 on the wire
    E = rigid(-0.4, [100.0, 20.0, 0.5])
    # a camera at the ego's recorded pose, placed in the local frame as AlpaSim does (ego pose @ camera -> rig),
    # comes back as the rig camera's cam_to_ego
    assert np.allclose(frames.cam_to_ego(E @ CAM, E), CAM, atol=1e-12)
    assert np.array_equal(frames.CAMERA_AXES, np.eye(4))


def test_mid_exposure_is_halfway_in_translation_and_rotation():
    a, b = rigid(0.2, [0, 0, 0]), rigid(0.6, [2.0, 0, 0])
    pair = pb.PosePair(start_pose=frames.pose_message(a), end_pose=frames.pose_message(b))
    mid = frames.mid_exposure(pair, "sensor_pose")
    assert np.allclose(mid, rigid(0.4, [1.0, 0, 0]), atol=1e-6)
    # quaternions of opposite sign (the same rotation) still interpolate along the short arc
    q = frames.pose_message(b)
    q.quat.w, q.quat.x, q.quat.y, q.quat.z = -q.quat.w, -q.quat.x, -q.quat.y, -q.quat.z
    pair.end_pose.CopyFrom(q)
    assert np.allclose(frames.mid_exposure(pair, "sensor_pose"), mid, atol=1e-6)
    only_start = pb.PosePair(start_pose=frames.pose_message(a))
    assert np.allclose(frames.mid_exposure(only_start, "sensor_pose"), a, atol=1e-6)


def test_the_time_is_the_middle_of_the_exposure():
    """Seconds on the rigs' clock: (start + end) / 2 microseconds; unset (both 0): none; end 0: the start; an end
    before the start is refused naming frame_end_us. Microseconds of Unix time survive the float64 seconds."""
    t0 = 1557539956500022                       # the PandaSet drive's first frame, microseconds
    assert frames.exposure_time(t0 - 15_000, t0 + 15_000) == pytest.approx(1557539956.500022, abs=1e-6)
    assert frames.exposure_time(0, 0) is None and frames.exposure_time(2_000_000, 0) == 2.0
    assert frames.exposure_time(0, 30_000) == 0.015
    with pytest.raises(ViewError) as e:
        frames.exposure_time(10, 5, "items[3].request.")
    assert e.value.field == "items[3].request.frame_end_us"
    assert frames.view_request(request(frame_start_us=4_000_000, frame_end_us=4_030_000), np.eye(4)).time_s == 4.015
    assert frames.view_request(request(), np.eye(4)).time_s is None
    traj = frames.trajectory_message([1557539956.500022, 1557539956.600022], [np.eye(4), rigid(0.3, [1.0, 2.0, 0])])
    assert [p.timestamp_us for p in traj.poses] == [1557539956500022, 1557539956600022]
    assert np.allclose(frames.pose_matrix(traj.poses[1].pose, "p"), rigid(0.3, [1.0, 2.0, 0]), atol=1e-6)


def test_pinhole_rescaled_as_camera_resized_with_the_ego_pose():
    E = rigid(0.3, [50.0, -7.0, 0.0])
    view = frames.view_request(request(E @ CAM), E)
    native = Camera(K=pinhole_K(633.2, 633.4, 407.9, 245.5), cam_to_ego=CAM, width=800, height=450)
    want = native.resized(512, 320)
    assert np.allclose(view.camera.K, want.K, atol=1e-12) and view.camera.distortion is None
    assert np.allclose(view.camera.cam_to_ego, CAM, atol=1e-6)
    assert (view.camera.width, view.camera.height, view.format) == (512, 320, "png")
    # one side asked: the other follows the native aspect; none: the native size
    assert frames.view_request(request(w=400, h=0), np.eye(4)).camera.height == 225
    assert frames.view_request(request(w=0, h=0), np.eye(4)).camera.width == 800


@pytest.mark.parametrize("param, model", [("opencv_fisheye_param", "opencv_fisheye"), ("ftheta_param", "ftheta")])
def test_lens_models_become_rig_json_lenses_and_back(param, model):
    cam = frames.view_request(request(param=param, w=800, h=450), np.eye(4)).camera
    assert cam.distortion is not None and cam.distortion.model == model
    assert cam.distortion.max_angle_deg == pytest.approx(95.0 if model == "opencv_fisheye" else 80.0)
    # the rig camera of that lens, as get_available_cameras describes it, comes back as the same camera
    rig_cam = Camera(name="C", K=cam.K, cam_to_ego=CAM, width=800, height=450, distortion=cam.distortion)
    again = frames.camera_spec(rig_cam)
    assert again.WhichOneof("camera_param") == param
    req = request(param=param, w=800, h=450)
    req.camera_intrinsics.CopyFrom(again)
    back = frames.view_request(req, np.eye(4)).camera
    assert back.distortion == cam.distortion and np.allclose(back.K, cam.K)
    if model == "ftheta":     # rescaled as ncore does (Lens.resized)
        half = frames.view_request(request(param=param, w=400, h=225), np.eye(4)).camera
        assert half.distortion == cam.distortion.resized(0.5, 0.5)


def test_opencv_coefficients_and_available_cameras():
    req = request()
    p = req.camera_intrinsics.opencv_pinhole_param
    p.radial_coeffs.extend([0.1, -0.02])
    p.tangential_coeffs.extend([0.001, 0.0])
    cam = frames.view_request(req, np.eye(4)).camera
    assert cam.distortion.model == "opencv" and cam.distortion.coeffs[:4] == (0.1, -0.02, 0.001, 0.0)
    rig = Rig(cameras=(Camera(name="F", K=pinhole_K(600, 600, 399.5, 224.5), cam_to_ego=CAM, width=800, height=450),
                       Camera(name="P", model="equirectangular", cam_to_ego=CAM, width=64, height=32)))
    avail = frames.available_cameras(rig)                      # the panorama has no CameraSpec
    assert [a.logical_id for a in avail] == ["F"]
    assert avail[0].intrinsics.shutter_type == pb.GLOBAL
    assert np.allclose(frames.pose_matrix(avail[0].rig_to_camera, "r"), CAM, atol=1e-6)


def test_quality():
    assert [frames.quality(v, "q") for v in (0.0, 0.95, 1.0, 95.0, 100.0, 1.5)] == [90, 95, 100, 95, 100, 2]
    with pytest.raises(ViewError) as e:
        frames.quality(150.0, "image_quality")
    assert e.value.field == "image_quality"


def _broken(change):
    req = request()
    change(req)
    return req


P = "camera_intrinsics.opencv_pinhole_param"
BAD = {
    "no camera model": (lambda r: r.camera_intrinsics.ClearField("opencv_pinhole_param"),
                        "camera_intrinsics.camera_param"),
    "focal length 0": (lambda r: setattr(r.camera_intrinsics.opencv_pinhole_param, "focal_length_x", 0.0),
                       f"{P}.focal_length_x"),
    "principal point nan": (lambda r: setattr(r.camera_intrinsics.opencv_pinhole_param, "principal_point_y",
                                              math.nan), f"{P}.principal_point_y"),
    "seven radial coefficients": (lambda r: r.camera_intrinsics.opencv_pinhole_param.radial_coeffs.extend([0.0] * 7),
                                  f"{P}.radial_coeffs"),
    "pose unset": (lambda r: r.ClearField("sensor_pose"), "sensor_pose"),
    "zero quaternion": (lambda r: r.sensor_pose.start_pose.ClearField("quat"), "sensor_pose.start_pose.quat"),
    "quaternion not unit": (lambda r: setattr(r.sensor_pose.end_pose.quat, "w", 3.0), "sensor_pose.end_pose.quat"),
    "position inf": (lambda r: setattr(r.sensor_pose.start_pose.vec, "x", math.inf), "sensor_pose.start_pose.vec"),
    "video format": (lambda r: setattr(r, "image_format", pb.AVC), "image_format"),
    "quality": (lambda r: setattr(r, "image_quality", -1.0), "image_quality"),
    "ego mask": (lambda r: setattr(r, "insert_ego_mask", True), "insert_ego_mask"),
    "windshield": (lambda r: r.camera_intrinsics.bivariate_windshield_model_param.horizontal_poly.append(1.0),
                   "camera_intrinsics.bivariate_windshield_model_param"),
    "no size anywhere": (lambda r: [setattr(r, k, 0) for k in ("resolution_w", "resolution_h")]
                         and [setattr(r.camera_intrinsics, k, 0) for k in ("resolution_w", "resolution_h")],
                         "resolution_w"),
    "size over 16384": (lambda r: setattr(r, "resolution_w", 20000), "resolution_w"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_refusals_name_the_protocol_field(case):
    change, field = BAD[case]
    with pytest.raises(ViewError) as e:
        frames.view_request(_broken(change), np.eye(4), "items[3].request.")
    assert e.value.field == f"items[3].request.{field}", str(e.value)


def test_lens_errors_name_the_lens_field():
    req = request(param="opencv_fisheye_param", w=800, h=450)
    req.camera_intrinsics.opencv_fisheye_param.radial_coeffs[1] = math.inf
    with pytest.raises(ViewError) as e:
        frames.view_request(req, np.eye(4))
    assert e.value.field == "camera_intrinsics.opencv_fisheye_param.radial_coeffs"
    req = request(param="ftheta_param", w=800, h=450)
    req.camera_intrinsics.ftheta_param.max_angle = 0.0
    with pytest.raises(ViewError) as e:
        frames.view_request(req, np.eye(4))
    assert e.value.field.startswith("camera_intrinsics.ftheta_param.max_angle"), str(e.value)
    req = request(param="opencv_fisheye_param", w=800, h=450)
    req.camera_intrinsics.opencv_fisheye_param.radial_coeffs[:] = [-0.5, 0.0, 0.0, 0.0]
    with pytest.raises(ViewError) as e:                        # theta_d turns before 95 degrees
        frames.view_request(req, np.eye(4))
    assert e.value.field == "camera_intrinsics.opencv_fisheye_param.max_angle", str(e.value)

