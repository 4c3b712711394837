"""runtime/lenses.py and the lens of runtime.camera.Camera: projection against OpenCV itself (cv2.projectPoints with
the rational + thin-prism model, cv2.fisheye.projectPoints), f-theta against a float64 reference written from the
definition (NVIDIA NuRec / AlpaSim FthetaCameraParam), the inverses, rig.json's forms and the validation."""

from __future__ import annotations

import copy
import json
import math
import re

import cv2
import numpy as np
import pytest
from xyzcyl.runtime.camera import Camera, CameraError, pinhole_K
from xyzcyl.runtime.lenses import Lens, fisheye_theta, fisheye_theta_d, opencv_distort, opencv_undistort
from xyzcyl.runtime.rig import Rig, RigError, load_rig, ring_rig, save_rig

W, H = 1280, 960
K = pinhole_K(520.0, 515.0, 645.3, 478.9)
# OpenCV distCoeffs (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 [tauX tauY]) of the kind calibrateCamera fits with
# CALIB_RATIONAL_MODEL | CALIB_THIN_PRISM_MODEL on a ~100-degree lens
RATIONAL = (-0.12, 0.02, 8e-4, -6e-4, -0.001, 0.03, 0.004, -0.0002)
PRISM = (*RATIONAL, 1.1e-3, -2.4e-4, 6.5e-4, 1.3e-4)
FISHEYE = {"model": "opencv_fisheye", "k1": 0.052, "k2": -0.011, "k3": 0.0021, "k4": -0.00031, "max_angle_deg": 100}
# an f-theta lens of NuRec's kind: backward polynomial (pixel distance -> radians, degree 5) as the reference
BW = [0.0, 2.45e-3, 1.2e-7, -2.3e-10, 1.4e-13, -3.1e-17]
FTHETA = {"model": "ftheta", "pixeldist_to_angle_poly": BW, "max_angle_deg": 95.0, "linear_cde": [1.0004, 3e-4, -2e-4]}
FTHETA_FW = {"model": "ftheta", "angle_to_pixeldist_poly": [0.0, 410.0, -5.0, -9.5, 1.2], "max_angle_deg": 98.0,
             "linear_cde": [0.999, -4e-4, 2e-4]}


def _camera(distortion=None, w=W, h=H, k=K) -> Camera:
    cam = ring_rig(3, width=w, height=h).cameras[1]     # a posed camera (not the identity)
    return Camera(name="CAM", width=w, height=h, K=k, cam_to_ego=cam.cam_to_ego, distortion=distortion)


def _directions(n: int, max_deg: float, seed: int = 0, min_deg: float = 0.0) -> np.ndarray:
    """n unit camera-frame directions, uniform in azimuth, angle from the axis uniform in [min_deg, max_deg]."""
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(min_deg, max_deg, n))
    ph = rng.uniform(0.0, 2 * np.pi, n)
    return np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, radians (atan2 of |a x b| and a.b: accurate near 0, unlike arccos)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _to_ego(cam: Camera, q: np.ndarray) -> np.ndarray:
    return q @ cam.rotation.T + cam.position


def _in_image_points(cam: Camera, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n ego points seen by `cam` at random pixels of its image (through the camera's own unprojection) at 1-40 m
    along the ray, and those pixels."""
    rng = np.random.default_rng(seed)
    uv = np.column_stack([rng.uniform(-0.5, cam.width - 0.5, n), rng.uniform(-0.5, cam.height - 0.5, n)])
    o, d = cam.pixel_rays(uv)
    return o + d * rng.uniform(1.0, 40.0, (n, 1)), uv


# -- against OpenCV ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("coeffs", [RATIONAL[:4], RATIONAL[:5], RATIONAL, PRISM, (*PRISM, 0.0, 0.0)],
                         ids=["4", "5", "rational-8", "thin-prism-12", "thin-prism-14"])
def test_opencv_projection_matches_cv2_project_points(coeffs):
    cam = _camera(coeffs)
    rng = np.random.default_rng(1)
    # random points in the field of view: undistorted normalised coordinates inside the image's, 0.5-60 m deep
    x = rng.uniform(-1.25, 1.25, 4000)
    y = rng.uniform(-0.93, 0.93, 4000)
    z = rng.uniform(0.5, 60.0, 4000)
    q = np.column_stack([x * z, y * z, z])
    pts = _to_ego(cam, q)
    uv, depth, front = cam.project(pts)
    E = cam.ego_to_cam
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cv2.Rodrigues(E[:3, :3])[0], E[:3, 3], cam.K,
                               np.asarray(coeffs))
    assert front.all()
    np.testing.assert_allclose(depth, z, rtol=1e-12)
    err = np.abs(uv - ref.reshape(-1, 2)).max()
    assert err < 1e-3, err                          # measured: ~5e-13 px (round-off of the same float64 formula)
    assert cam.inside(uv).mean() > 0.5              # the points span the image, not just its centre


def test_fisheye_projection_matches_cv2_fisheye_up_to_90_and_the_definition_to_95_degrees():
    cam = _camera(FISHEYE)
    lens = cam.distortion
    q = _directions(4000, 95.0, seed=2) * np.random.default_rng(3).uniform(0.5, 50.0, (4000, 1))
    pts = _to_ego(cam, q)
    uv, depth, front = cam.project(pts)
    assert front.all()
    theta = np.arctan2(np.hypot(q[:, 0], q[:, 1]), q[:, 2])
    fold = theta < math.radians(89.9)                # cv2 divides by z: it cannot image a point beyond 90 degrees
    E = cam.ego_to_cam
    ref, _ = cv2.fisheye.projectPoints(pts[fold].reshape(-1, 1, 3), cv2.Rodrigues(E[:3, :3])[0], E[:3, 3], cam.K,
                                       np.asarray(lens.coeffs))
    err = np.abs(uv[fold] - ref.reshape(-1, 2)).max()
    assert err < 1e-3, err                          # measured: ~5e-13 px
    # 0..95 degrees: the definition, theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) along
    # the azimuth, written here with numpy's polynomial class (not the module's Horner form)
    k1, k2, k3, k4 = (FISHEYE[k] for k in ("k1", "k2", "k3", "k4"))
    td = np.polynomial.Polynomial([0, 1, 0, k1, 0, k2, 0, k3, 0, k4])(theta)
    phi = np.arctan2(q[:, 1], q[:, 0])
    want = np.column_stack([K[0, 0] * td * np.cos(phi) + K[0, 2], K[1, 1] * td * np.sin(phi) + K[1, 2]])
    assert (theta > math.radians(90)).sum() > 100
    assert np.abs(uv - want).max() < 1e-9


def test_cv2_fisheye_folds_points_beyond_90_degrees():
    """Why the test above stops cv2 at 90 degrees: cv2 normalises by z, so a point at 95 degrees lands where the
    point at 85 degrees on the opposite azimuth does; this lens images it further out."""
    lens = Lens.from_json(FISHEYE)
    t = math.radians(95.0)
    p = np.array([[math.sin(t), 0.0, math.cos(t)]])
    mirror = np.array([[-math.sin(math.pi - t), 0.0, math.cos(math.pi - t)]])   # 85 degrees, the other side
    ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(lens.coeffs))
    np.testing.assert_allclose(ref.reshape(-1, 2), lens.project(K, mirror)[0], atol=1e-9)
    assert lens.project(K, p)[0][0, 0] > K[0, 2] + K[0, 0] * math.radians(90)


# -- f-theta ---------------------------------------------------------------------------------------------------

def _ftheta_reference(d: dict, q: np.ndarray) -> np.ndarray:
    """The f-theta projection from its definition, float64, one point at a time: theta = angle from the optical
    axis; r = angle_to_pixeldist(theta), or the root in [0, r_max] of pixeldist_to_angle(r) = theta (numpy's
    companion-matrix roots, polished by one Newton step); pixel = (cx, cy) + [[c, d], [e, 1]] r (cos phi, sin phi)."""
    c, dd, e = d.get("linear_cde", (1.0, 0.0, 0.0))
    out = []
    for x, y, z in q:
        theta = math.atan2(math.hypot(x, y), z)
        if "angle_to_pixeldist_poly" in d:
            r = np.polynomial.Polynomial(d["angle_to_pixeldist_poly"])(theta)
        else:
            p = np.polynomial.Polynomial(d["pixeldist_to_angle_poly"])
            roots = (p - theta).roots()
            real = sorted(z.real for z in roots if abs(z.imag) < 1e-6 and z.real >= -1e-9)
            r = real[0]
            r -= (p(r) - theta) / p.deriv()(r)
        phi = math.atan2(y, x)
        ox, oy = r * math.cos(phi), r * math.sin(phi)
        out.append((c * ox + dd * oy + K[0, 2], e * ox + oy + K[1, 2]))
    return np.array(out)


@pytest.mark.parametrize("spec", [FTHETA, FTHETA_FW], ids=["backward-reference", "forward-reference"])
def test_ftheta_projection_matches_the_definition(spec):
    cam = _camera(spec)
    q = _directions(600, spec["max_angle_deg"], seed=4) * 7.0
    uv, _, front = cam.project(_to_ego(cam, q))
    assert front.all()
    err = np.abs(uv - _ftheta_reference(spec, q)).max()
    assert err < 1e-6, err


def test_ftheta_follows_the_alpasim_proto_convention():
    """AlpaSim's sensorsim.proto FthetaCameraParam: principal_point_x/y (pixels, origin at the first pixel's
    centre as in NVIDIA ncore, = K's cx, cy), pixeldist_to_angle_poly ("backward": pixel distance -> radians,
    constant term first), angle_to_pixeldist_poly ("forward"), reference_poly, max_angle, linear_cde = the
    matrix [[c, d], [e, 1]] on the pixel offset. The example of AlpaSim's own tests: principal point (32, 16),
    PIXELDIST_TO_ANGLE [0, 0.02]: the pixel 50 px right of it sees 1 radian off the axis towards camera +x."""
    cam = Camera(width=64, height=32, K=pinhole_K(1.0, 1.0, 32.0, 16.0), cam_to_ego=np.eye(4),
                 distortion={"model": "ftheta", "reference_poly": "pixeldist_to_angle",
                             "pixeldist_to_angle_poly": [0, 0.02], "max_angle_deg": 90})
    _, d = cam.pixel_rays(np.array([[82.0, 16.0], [32.0, 16.0 - 25.0]]))
    np.testing.assert_allclose(d, [[math.sin(1.0), 0, math.cos(1.0)], [0, -math.sin(0.5), math.cos(0.5)]],
                               atol=1e-15)
    # the linear term: u - cx = c x' + d y', v - cy = e x' + y' of the ideal offset (x', y')
    sheared = cam.replace(distortion={**cam.distortion.to_json(), "linear_cde": [1.1, 0.2, 0.05]})
    uv, _, _ = sheared.project(np.array([[math.sin(1.0), 0.0, math.cos(1.0)]]))
    np.testing.assert_allclose(uv, [[32.0 + 1.1 * 50.0, 16.0 + 0.05 * 50.0]], atol=1e-12)
    # both polynomials (NuRec ships both; reference_poly says which one is exact): the other is not used
    both = {"model": "ftheta", "reference_poly": "pixeldist_to_angle", "pixeldist_to_angle_poly": [0, 0.02],
            "angle_to_pixeldist_poly": [0, 49.0], "max_angle_deg": 90}
    a = cam.replace(distortion=both).project(np.array([[math.sin(1.0), 0.0, math.cos(1.0)]]))[0]
    np.testing.assert_allclose(a, [[82.0, 16.0]], atol=1e-12)
    b = cam.replace(distortion={**both, "reference_poly": "angle_to_pixeldist"}).project(
        np.array([[math.sin(1.0), 0.0, math.cos(1.0)]]))[0]
    np.testing.assert_allclose(b, [[81.0, 16.0]], atol=1e-12)


# -- inverses ----------------------------------------------------------------------------------------------------

_MODELS = {"pinhole": None, "opencv": RATIONAL[:5], "opencv-rational-prism": PRISM, "opencv_fisheye": FISHEYE,
           "ftheta-backward": FTHETA, "ftheta-forward": FTHETA_FW}


@pytest.mark.parametrize("name", sorted(_MODELS))
def test_unproject_of_project_round_trips(name):
    cam = _camera(_MODELS[name])
    lens = cam.distortion
    top = 60.0 if lens is None or lens.model == "opencv" else lens.max_angle_deg
    q = _directions(5000, top, seed=5)
    if lens is not None and lens.model == "opencv":       # inside the image: the rational model's valid region
        q = q[np.abs(q[:, 0] / q[:, 2]) < 1.25]
    pts = _to_ego(cam, q * 3.0)
    uv, _, front = cam.project(pts)
    assert front.all()
    o, d = cam.pixel_rays(uv)
    err = _angle(d, (pts - o) / np.linalg.norm(pts - o, axis=-1, keepdims=True)).max()
    assert err < 1e-6, err                           # measured: ~1e-15 rad
    # and the other way: project(unproject(uv)) over the whole image (where the lens sees)
    pts, uv = _in_image_points(cam, 3000, seed=6)
    ok = np.isfinite(pts[:, 0])
    assert ok.mean() > 0.7
    back, _, front = cam.project(pts[ok])
    assert front.all()
    assert np.abs(back - uv[ok]).max() < 1e-6


def test_equirectangular_round_trips():
    cam = ring_rig(1, width=256, height=128).cameras[0].replace(model="equirectangular", K=None)
    q = _directions(2000, 179.0, seed=7)
    pts = _to_ego(cam, q * 5.0)
    uv, _, front = cam.project(pts)
    o, d = cam.pixel_rays(uv)
    assert front.all() and _angle(d, q @ cam.rotation.T).max() < 1e-6


def test_pure_maps_invert_each_other():
    rng = np.random.default_rng(8)
    xy = rng.uniform(-1.2, 1.2, (500, 2))
    back, ok = opencv_undistort(opencv_distort(xy, PRISM), PRISM)
    assert ok.all() and np.abs(back - xy).max() < 1e-12
    k = tuple(FISHEYE[k] for k in ("k1", "k2", "k3", "k4"))
    theta = rng.uniform(0, math.radians(100), 500)
    assert np.abs(fisheye_theta(fisheye_theta_d(theta, k), k, math.radians(100)) - theta).max() < 1e-13


def test_beyond_max_angle_is_not_in_front_and_has_no_ray():
    for spec in (FISHEYE, FTHETA):
        cam = _camera(spec)
        amax = cam.distortion.max_angle
        q = np.array([[math.sin(amax - 1e-6), 0, math.cos(amax - 1e-6)], [math.sin(amax + 1e-3), 0,
                                                                              math.cos(amax + 1e-3)]])
        _, z, front = cam.project(_to_ego(cam, q))
        assert front.tolist() == [True, False]
        assert z[0] < 0                              # beyond 90 degrees: in front of the lens, behind its plane
        # the pixel far outside the image circle sees nothing: NaN
        _, d = cam.pixel_rays(np.array([[cam.K[0, 2] + 20 * W, cam.K[1, 2]], [cam.K[0, 2] + 10, cam.K[1, 2]]]))
        assert np.isnan(d[0]).all() and np.isfinite(d[1]).all()
    cam = _camera(RATIONAL)
    assert not cam.project(cam.position - cam.rotation[:, 2])[2]  # behind: z < 0


# -- the camera ---------------------------------------------------------------------------------------------------

def test_camera_lens_properties():
    assert _camera().is_ideal and _camera().lens_model == "pinhole" and _camera().distortion is None
    cam = _camera(RATIONAL[:4])
    assert not cam.is_ideal and cam.lens_model == "opencv" and cam.model == "pinhole"
    assert cam.distortion.opencv_coefficients() == RATIONAL[:4]
    assert _camera(FISHEYE).lens_model == "opencv_fisheye" and _camera(FTHETA).lens_model == "ftheta"
    assert _camera((0.0, 0.0, 0.0, 0.0)).distortion is None              # all zero: no lens, as before
    eq = ring_rig(1).cameras[0].replace(model="equirectangular", K=None)
    assert eq.is_ideal and eq.lens_model == "equirectangular"
    with pytest.raises(CameraError, match="distortion"):
        eq.replace(distortion=FISHEYE)
    # a wide fisheye's field of view comes from its lens: the 100-degree half-angle lens sees more than 180
    wide = _camera(FISHEYE, w=1400, h=1400, k=pinhole_K(300.0, 300.0, 699.5, 699.5))
    assert math.degrees(wide.horizontal_fov) == pytest.approx(200.0)
    assert 100 < math.degrees(_camera(FISHEYE).vertical_fov) < 200


@pytest.mark.parametrize("name", sorted(_MODELS))
def test_resized_camera_maps_pixel_centres(name):
    cam = _camera(_MODELS[name])
    small = cam.resized(320, 320)                    # 1/4 horizontally, 1/3 vertically
    pts, uv = _in_image_points(cam, 200, seed=9)
    ok = np.isfinite(pts[:, 0])
    uv2, _, front = small.project(pts[ok])
    assert front.all()
    np.testing.assert_allclose(uv2[:, 0], 0.25 * (uv[ok, 0] + 0.5) - 0.5, atol=1e-6)
    np.testing.assert_allclose(uv2[:, 1], (uv[ok, 1] + 0.5) / 3 - 0.5, atol=1e-6)
    if cam.distortion is not None and cam.distortion.model != "ftheta":
        assert small.distortion == cam.distortion


# -- rig.json --------------------------------------------------------------------------------------------------

def _cam_dict(distortion, name="CAM_0"):
    return {"name": name, "width": W, "height": H, "K": K.tolist(),
            "cam_to_ego": [[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]],
            "distortion": distortion}


@pytest.mark.parametrize("distortion", [None, list(RATIONAL[:4]), list(RATIONAL[:5]), list(RATIONAL), list(PRISM),
                                        [*PRISM, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]])
def test_list_form_round_trips_byte_identically(tmp_path, distortion):
    doc = {"source": "test", "cameras": [_cam_dict(distortion)]}
    text = json.dumps(doc, indent=1) + "\n"
    (tmp_path / "rig.json").write_text(text)
    rig = load_rig(tmp_path / "rig.json", check_images=False)
    save_rig(rig, tmp_path / "again.json")
    if distortion is not None and not any(distortion):
        assert json.loads((tmp_path / "again.json").read_text())["cameras"][0]["distortion"] is None  # as before
    else:
        assert (tmp_path / "again.json").read_text() == text


@pytest.mark.parametrize("spec", [FISHEYE, FTHETA, FTHETA_FW, {"model": "opencv", "k1": -0.1, "s3": 1e-3}],
                         ids=["fisheye", "ftheta-backward", "ftheta-forward", "opencv-dict"])
def test_dict_form_round_trips(tmp_path, spec):
    rig = Rig.from_dict({"source": "test", "cameras": [_cam_dict(copy.deepcopy(spec))]})
    save_rig(rig, tmp_path / "rig.json")
    again = load_rig(tmp_path / "rig.json", check_images=False)
    assert again.cameras[0].distortion == rig.cameras[0].distortion
    written = json.loads((tmp_path / "rig.json").read_text())["cameras"][0]["distortion"]
    assert written["model"] == spec["model"]
    assert {k: v for k, v in written.items() if k in spec} == {k: (list(v) if isinstance(v, (list, tuple)) else v)
                                                               for k, v in spec.items()}
    save_rig(again, tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "rig.json").read_bytes()


# -- validation -----------------------------------------------------------------------------------------------

_BAD = {
    # name: (distortion value, the error's field)
    "list_short": ([0.1, 0.2], "distortion"),
    "list_nan": ([0.1, float("nan"), 0, 0], "distortion[1]"),
    "list_tilt": ([*PRISM, 0.01, 0.0], "distortion[12]"),
    "list_nested": ([[0.1, 0.2, 0.0, 0.0]], "distortion[0]"),
    "text": ("barrel", "distortion"),
    "no_model": ({"k1": 0.1}, "distortion.model"),
    "bad_model": ({"model": "kannala_brandt"}, "distortion.model"),
    "model_not_text": ({"model": [1]}, "distortion.model"),
    "opencv_text": ({"model": "opencv", "k1": "0.1"}, "distortion.k1"),
    "opencv_inf": ({"model": "opencv", "s2": float("inf")}, "distortion.s2"),
    "opencv_unknown": ({"model": "opencv", "k7": 0.1}, "distortion.k7"),
    "opencv_max_angle": ({"model": "opencv", "max_angle_deg": 80}, "distortion.max_angle_deg"),
    "fisheye_missing_max": ({"model": "opencv_fisheye", "k1": 0.01}, "distortion.max_angle_deg"),
    "fisheye_max_zero": ({**FISHEYE, "max_angle_deg": 0}, "distortion.max_angle_deg"),
    "fisheye_max_181": ({**FISHEYE, "max_angle_deg": 181}, "distortion.max_angle_deg"),
    "fisheye_folds": ({**FISHEYE, "k1": -0.3}, "distortion.max_angle_deg"),
    "fisheye_k4_nan": ({**FISHEYE, "k4": float("nan")}, "distortion.k4"),
    "fisheye_prism": ({**FISHEYE, "s1": 0.001}, "distortion.s1"),
    "ftheta_no_poly": ({"model": "ftheta", "max_angle_deg": 90}, "distortion.pixeldist_to_angle_poly"),
    "ftheta_two_no_ref": ({**FTHETA, "angle_to_pixeldist_poly": [0, 400.0]}, "distortion.reference_poly"),
    "ftheta_bad_ref": ({**FTHETA, "reference_poly": "FORWARD"}, "distortion.reference_poly"),
    "ftheta_ref_missing": ({**FTHETA, "reference_poly": "angle_to_pixeldist"}, "distortion.angle_to_pixeldist_poly"),
    "ftheta_nan": ({**FTHETA, "pixeldist_to_angle_poly": [0, 2e-3, float("nan")]},
                   "distortion.pixeldist_to_angle_poly[2]"),
    "ftheta_constant": ({**FTHETA, "pixeldist_to_angle_poly": [0.1, 2e-3]}, "distortion.pixeldist_to_angle_poly[0]"),
    "ftheta_slope": ({**FTHETA, "pixeldist_to_angle_poly": [0, -2e-3, 1e-6]},
                     "distortion.pixeldist_to_angle_poly[1]"),
    "ftheta_one_coeff": ({**FTHETA_FW, "angle_to_pixeldist_poly": [400.0]}, "distortion.angle_to_pixeldist_poly"),
    "ftheta_17_coeffs": ({**FTHETA, "pixeldist_to_angle_poly": [0, 2e-3] + [0.0] * 15},
                         "distortion.pixeldist_to_angle_poly"),
    "ftheta_not_list": ({**FTHETA, "pixeldist_to_angle_poly": 0.002}, "distortion.pixeldist_to_angle_poly"),
    # r(theta) = 500 theta - 200 theta^3 turns at 52.6 degrees, before max_angle 80
    "ftheta_fw_turns": ({**FTHETA_FW, "angle_to_pixeldist_poly": [0, 500.0, 0, -200.0], "max_angle_deg": 80},
                        "distortion.angle_to_pixeldist_poly"),
    # theta(r) = 0.002 r - 1e-9 r^3 peaks at 62.3 degrees, short of max_angle 90
    "ftheta_bw_short": ({**FTHETA, "pixeldist_to_angle_poly": [0, 2e-3, 0, -1e-9], "max_angle_deg": 90},
                        "distortion.pixeldist_to_angle_poly"),
    "ftheta_missing_max": ({"model": "ftheta", "pixeldist_to_angle_poly": BW}, "distortion.max_angle_deg"),
    "ftheta_cde_len": ({**FTHETA, "linear_cde": [1.0, 0.0]}, "distortion.linear_cde"),
    "ftheta_cde_nan": ({**FTHETA, "linear_cde": [1.0, float("nan"), 0.0]}, "distortion.linear_cde[1]"),
    "ftheta_cde_flip": ({**FTHETA, "linear_cde": [-1.0, 0.0, 0.0]}, "distortion.linear_cde"),
    "ftheta_k1": ({**FTHETA, "k1": 0.1}, "distortion.k1"),
}


@pytest.mark.parametrize("case", sorted(_BAD))
def test_validation_names_the_field(case):
    value, field = _BAD[case]
    with pytest.raises(CameraError) as info:
        Camera.from_dict(_cam_dict(copy.deepcopy(value)))
    assert info.value.field == field, str(info.value)
    assert info.value.where == "camera 'CAM_0'"
    with pytest.raises(RigError, match=re.escape(f"camera 'CAM_1': {field}: ")):
        Rig.from_dict({"cameras": [_cam_dict(None), _cam_dict(copy.deepcopy(value), "CAM_1")]})


def test_lens_errors_are_camera_errors_without_a_camera():
    with pytest.raises(CameraError) as info:
        Lens("opencv_fisheye", (0.1, 0.0, 0.0, 0.0))
    assert (info.value.field, info.value.where) == ("distortion.max_angle_deg", None)
    with pytest.raises(CameraError, match="distortion.pixeldist_to_angle_poly: is not a parameter"):
        Lens("opencv", (0.1, 0.0, 0.0, 0.0), pixeldist_to_angle_poly=(0.0, 1.0))
