"""Rig I/O, validation and camera projection."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from xyzcyl.runtime.rig import Rig, RigError, load_rig, read_depth, read_image, ring_rig, save_rig


def _cam_dict(name="CAM_A", w=64, h=48, image=None):
    return {
        "name": name,
        "image": image,
        "width": w,
        "height": h,
        "K": [[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]],
        "cam_to_ego": [[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0, 0, 0, 1]],
        "distortion": None,
        "timestamp_s": 12.5,
    }


def _rig_dict(n=2):
    return {"source": "test", "cameras": [_cam_dict(f"CAM_{k}") for k in range(n)]}


def _set(d, path, value):
    *head, last = path
    for key in head:
        d = d[key]
    d[last] = value


# Each case: (mutation of a 2-camera rig dict, substrings the error message must contain).
_BAD = {
    "K_nan": (lambda d: _set(d, ["cameras", 0, "K", 0, 2], float("nan")), ["CAM_0", "K[0][2]", "finite"]),
    "pose_inf": (lambda d: _set(d, ["cameras", 1, "cam_to_ego", 0, 3], float("inf")),
                 ["CAM_1", "cam_to_ego: entry [0][3]", "finite"]),
    "K_skew": (lambda d: _set(d, ["cameras", 0, "K", 0, 1], 0.5), ["CAM_0", "K[0][1]"]),
    "K_10": (lambda d: _set(d, ["cameras", 0, "K", 1, 0], 1.0), ["CAM_0", "K[1][0]"]),
    "K_row2": (lambda d: _set(d, ["cameras", 0, "K", 2, 0], 1e-3), ["CAM_0", "K[2][0]"]),
    "K_22": (lambda d: _set(d, ["cameras", 0, "K", 2, 2], 2.0), ["CAM_0", "K[2][2]"]),
    "fx_neg": (lambda d: _set(d, ["cameras", 0, "K", 0, 0], -50.0), ["CAM_0", "K[0][0]", "fx"]),
    "fy_zero": (lambda d: _set(d, ["cameras", 1, "K", 1, 1], 0.0), ["CAM_1", "K[1][1]", "fy"]),
    "K_shape": (lambda d: _set(d, ["cameras", 0, "K"], [[1, 0], [0, 1]]), ["CAM_0", "K", "3x3"]),
    "K_text": (lambda d: _set(d, ["cameras", 0, "K"], "eye"), ["CAM_0", "K", "numbers"]),
    "K_missing": (lambda d: d["cameras"][0].pop("K"), ["CAM_0", "K", "missing"]),
    "not_ortho": (lambda d: _set(d, ["cameras", 0, "cam_to_ego", 0, 2], 1.01), ["CAM_0", "cam_to_ego", "orthonormal"]),
    "reflection": (lambda d: _set(d, ["cameras", 0, "cam_to_ego", 1, 0], 1.0), ["CAM_0", "cam_to_ego", "det"]),
    "bottom_row": (lambda d: _set(d, ["cameras", 0, "cam_to_ego", 3, 0], 0.1), ["CAM_0", "cam_to_ego", "bottom row"]),
    "pose_shape": (lambda d: _set(d, ["cameras", 0, "cam_to_ego"], np.eye(3).tolist()), ["CAM_0", "cam_to_ego", "[4, 4]"]),
    "width_zero": (lambda d: _set(d, ["cameras", 0, "width"], 0), ["CAM_0", "width"]),
    "height_big": (lambda d: _set(d, ["cameras", 1, "height"], 16385), ["CAM_1", "height"]),
    "width_float": (lambda d: _set(d, ["cameras", 0, "width"], 64.5), ["CAM_0", "width", "integer"]),
    "width_nan": (lambda d: _set(d, ["cameras", 0, "width"], float("nan")), ["CAM_0", "width"]),
    "duplicate": (lambda d: _set(d, ["cameras", 1, "name"], "CAM_0"), ["CAM_0", "name", "duplicate"]),
    "no_cameras": (lambda d: _set(d, ["cameras"], []), ["rig", "cameras", "1..16"]),
    "too_many": (lambda d: _set(d, ["cameras"], [_cam_dict(f"C{k}") for k in range(17)]), ["rig", "cameras", "17"]),
    "no_name": (lambda d: d["cameras"][1].pop("name"), ["camera #1", "name"]),
    "model": (lambda d: _set(d, ["cameras", 0, "model"], "fisheye"), ["CAM_0", "model"]),
    "distortion_len": (lambda d: _set(d, ["cameras", 0, "distortion"], [0.1, 0.2]), ["CAM_0", "distortion"]),
    "distortion_nan": (lambda d: _set(d, ["cameras", 0, "distortion"], [0.1, float("nan"), 0, 0]),
                       ["CAM_0", "distortion[1]", "finite"]),
}


@pytest.mark.parametrize("case", sorted(_BAD))
def test_validation_names_camera_and_field(case):
    d = _rig_dict()
    mutate, needles = _BAD[case]
    mutate(d)
    with pytest.raises(RigError) as info:
        Rig.from_dict(d)
    for needle in needles:
        assert needle in str(info.value), (case, str(info.value))


def test_valid_rig_round_trips_with_extras(tmp_path):
    d = _rig_dict(3)
    d["cameras"][2]["model"] = "pinhole"
    d["cameras"][1]["depth"] = "d.exr"
    rig = Rig.from_dict(d)
    out = rig.to_dict()
    assert out["source"] == "test" and out["cameras"][0]["timestamp_s"] == 12.5
    assert out["cameras"][1]["depth"] == "d.exr"
    again = Rig.from_dict(json.loads(json.dumps(out)))
    for a, b in zip(rig.cameras, again.cameras):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.cam_to_ego, b.cam_to_ego)
    save_rig(rig, tmp_path / "rig.json")
    assert load_rig(tmp_path / "rig.json", check_images=False).to_dict() == out


def test_arrays_are_read_only():
    cam = ring_rig(1).cameras[0]
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0


def _write_png(path, w, h, bgr=(0, 0, 255)):
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = bgr
    assert cv2.imwrite(str(path), img)


def test_image_checks(tmp_path):
    d = _rig_dict(1)
    d["cameras"][0]["image"] = "a.png"
    (tmp_path / "rig.json").write_text(json.dumps(d))
    with pytest.raises(RigError, match=r"camera 'CAM_0': image: file .* does not exist"):
        load_rig(tmp_path / "rig.json")
    _write_png(tmp_path / "a.png", 65, 48)
    with pytest.raises(RigError, match=r"camera 'CAM_0': image: 'a.png' is 65x48, but width x height is 64x48"):
        load_rig(tmp_path / "rig.json")
    (tmp_path / "a.png").write_bytes(b"not an image")
    with pytest.raises(RigError, match=r"camera 'CAM_0': image: cannot read"):
        load_rig(tmp_path / "rig.json")
    _write_png(tmp_path / "a.png", 64, 48, bgr=(0, 0, 255))  # pure red in BGR
    rig = load_rig(tmp_path / "rig.json")
    (img,) = rig.load_images()
    assert img.dtype == np.float32 and img.shape == (48, 64, 3)
    np.testing.assert_array_equal(img[0, 0], [1.0, 0.0, 0.0])  # RGB order


def test_load_rig_bad_json(tmp_path):
    (tmp_path / "rig.json").write_text("{")
    with pytest.raises(RigError, match="rig: .* not valid JSON"):
        load_rig(tmp_path / "rig.json")
    with pytest.raises(RigError, match="rig: cannot read"):
        load_rig(tmp_path / "missing.json")


@pytest.mark.parametrize("distortion", [None, (0.1, -0.05, 0.001, -0.002), (0.1, -0.05, 0.001, -0.002, 0.01)])
def test_project_matches_cv2(distortion):
    rng = np.random.default_rng(0)
    rig = ring_rig(3, hfov_deg=80, width=320, height=200)
    for cam in rig.cameras:
        cam = cam.replace(distortion=distortion)
        pts_cam = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), rng.uniform(2, 30, 50)])
        pts_ego = pts_cam @ cam.rotation.T + cam.position
        uv, z, in_front = cam.project(pts_ego)
        E = cam.ego_to_cam
        rvec, _ = cv2.Rodrigues(E[:3, :3])
        ref, _ = cv2.projectPoints(pts_ego.reshape(-1, 1, 3), rvec, E[:3, 3], cam.K,
                                   None if distortion is None else np.asarray(distortion))
        # 1e-6 px: both are float64 evaluations of the same formula; differences are round-off only.
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
        np.testing.assert_allclose(z, pts_cam[:, 2], atol=1e-9)
        assert in_front.all()
        behind = cam.project(cam.position - cam.rotation[:, 2])[2]
        assert not behind


@pytest.mark.parametrize("model", ["pinhole", "distorted", "equirectangular"])
def test_pixel_rays_invert_project(model):
    cam = ring_rig(2, width=120, height=80).cameras[1]
    if model == "distorted":
        cam = cam.replace(distortion=(-0.1, 0.02, 0.0005, 0.0003))
    if model == "equirectangular":
        cam = cam.replace(model="equirectangular", K=None)
    rng = np.random.default_rng(1)
    uv = np.column_stack([rng.uniform(-0.5, cam.width - 0.5, 200), rng.uniform(-0.5, cam.height - 0.5, 200)])
    o, d = cam.pixel_rays(uv)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    back, _, ok = cam.project(o + 7.0 * d)
    assert ok.all()
    # 1e-8 px: the lens is inverted to round-off (runtime.lenses), the pinhole and equirectangular exactly
    np.testing.assert_allclose(back, uv, atol=1e-8)
    _, full_d = cam.pixel_rays()
    assert full_d.shape == (cam.height, cam.width, 3)


def test_equirectangular_convention():
    cam = ring_rig(1, width=360, height=180).cameras[0].replace(model="equirectangular", K=None)
    c = cam.position
    fwd, right, up = cam.rotation[:, 2], cam.rotation[:, 0], -cam.rotation[:, 1]
    uv = cam.project(np.stack([c + fwd, c + right, c - fwd + 1e-9 * right, c + up]))[0]
    # forward -> centre column (W-1)/2, middle row (H-1)/2; right -> +90 deg -> 3/4 of the width;
    # behind -> right edge W-1/2; zenith -> top edge -1/2.
    np.testing.assert_allclose(uv, [[179.5, 89.5], [269.5, 89.5], [359.5, 89.5], [uv[3, 0], -0.5]], atol=1e-6)
    assert cam.vertical_fov == pytest.approx(math.pi)


def test_real_rigs_load(real_data):
    for folder in ("nuscenes_ca9a282c", "pandaset_002_00"):
        rig = load_rig(real_data / folder / "rig.json")
        assert len(rig) == 6
        d = rig.to_dict()
        assert d["cameras"][0]["timestamp_s"] == rig.cameras[0].extra["timestamp_s"]
        again = Rig.from_dict(copy.deepcopy(d))
        np.testing.assert_array_equal(again.cameras[3].cam_to_ego, rig.cameras[3].cam_to_ego)


def test_ring_rig_geometry():
    rig = ring_rig(4, ring_radius=0.5, mount_height=1.5)
    # camera 1 looks clockwise of camera 0: ego -y (right)
    np.testing.assert_allclose(rig.cameras[1].rotation[:, 2], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(rig.cameras[1].position, [0, -0.5, 1.5], atol=1e-12)
    for cam in rig.cameras:
        np.testing.assert_allclose(cam.rotation[:, 1], [0, 0, -1], atol=1e-12)  # image down = ego down


def test_integer_files_unscaled_and_16bit_depth_in_millimetres(tmp_path):
    """Regression: read_image(scale=False) returned 8/16-bit values scaled to 0..1 (OpenImageIO's Python
    read_image converts to float unless given the file's type), so a 16-bit depth PNG of 5000 mm read as 7.6e-5 m."""
    import cv2

    mm = np.array([[0, 1, 5000], [65535, 1234, 80000 // 2]], np.uint16)
    cv2.imwrite(str(tmp_path / "d16.png"), mm)
    np.testing.assert_allclose(read_depth(tmp_path / "d16.png", "depth"), mm.astype(np.float32) * 0.001, rtol=1e-6)
    cls = np.array([[0, 10, 255]], np.uint8)
    cv2.imwrite(str(tmp_path / "s8.png"), cls)
    np.testing.assert_array_equal(read_image(tmp_path / "s8.png", "s", channels=1, scale=False)[..., 0], cls)
    np.testing.assert_allclose(read_image(tmp_path / "s8.png", "s", channels=1)[..., 0], cls / 255.0, rtol=1e-6)


def test_image_formats_and_depth(tmp_path):
    import OpenImageIO as oiio

    d = _rig_dict(1)
    d["cameras"][0].update(image="a16.png", depth="d.exr")
    img16 = np.zeros((48, 64, 3), np.uint16)
    img16[..., 2] = 65535  # blue
    out = oiio.ImageOutput.create(str(tmp_path / "a16.png"))
    out.open(str(tmp_path / "a16.png"), oiio.ImageSpec(64, 48, 3, "uint16"))
    out.write_image(img16)
    out.close()
    depth = np.linspace(1, 80, 48 * 64, dtype=np.float32).reshape(48, 64)
    out = oiio.ImageOutput.create(str(tmp_path / "d.exr"))
    out.open(str(tmp_path / "d.exr"), oiio.ImageSpec(64, 48, 1, "float"))
    out.write_image(depth[..., None])  # [H, W, 1]: OIIO misreads a 2-D array
    out.close()
    (tmp_path / "rig.json").write_text(json.dumps(d))
    rig = load_rig(tmp_path / "rig.json")
    np.testing.assert_array_equal(rig.load_images()[0][5, 5], [0, 0, 1])
    np.testing.assert_array_equal(rig.load_depths()[0], depth)  # EXR float32 is lossless
    depth[3, 3] = np.nan
    out = oiio.ImageOutput.create(str(tmp_path / "d.exr"))
    out.open(str(tmp_path / "d.exr"), oiio.ImageSpec(64, 48, 1, "float"))
    out.write_image(depth[..., None])  # [H, W, 1]: OIIO misreads a 2-D array
    out.close()
    with pytest.raises(RigError, match="camera 'CAM_0': depth: has non-finite"):
        rig.load_depths()


def test_check_arrays():
    rig = ring_rig(2, width=8, height=6)
    rig.check_arrays([np.zeros((6, 8, 3), np.float32), np.zeros((6, 8), np.uint8)])
    with pytest.raises(RigError, match="rig: images: need 2"):
        rig.check_arrays([np.zeros((6, 8, 3))])
    with pytest.raises(RigError, match=r"camera 'cam1': image: has shape \[8, 6, 3\]"):
        rig.check_arrays([np.zeros((6, 8, 3)), np.zeros((8, 6, 3))])
    bad = np.zeros((6, 8), np.float32)
    bad[1, 1] = np.inf
    with pytest.raises(RigError, match="camera 'cam0': depth: has non-finite"):
        rig.check_arrays([bad, bad], what="depth")


def test_clockwise_order(real_data):
    rig = ring_rig(6, clockwise=False)  # counter-clockwise ring: cam0 front, cam1 front-left, ...
    assert rig.clockwise_order() == [0, 5, 4, 3, 2, 1]
    again = rig.reordered(rig.clockwise_order())
    assert again.names == ["cam0", "cam5", "cam4", "cam3", "cam2", "cam1"]
    with pytest.raises(RigError, match="permutation"):
        rig.reordered([0, 0, 1, 2, 3, 4])
    nus = load_rig(real_data / "nuscenes_ca9a282c" / "rig.json", check_images=False)
    assert nus.clockwise_order() == list(range(6))  # the sample is already listed clockwise
    # PandaSet's front camera looks slightly left of forward (azimuth > 0): it still comes first
    pan = load_rig(real_data / "pandaset_002_00" / "rig.json", check_images=False)
    assert pan.clockwise_order() == list(range(6))
    assert pan.reordered([3, 4, 5, 0, 1, 2]).clockwise_order() == [3, 4, 5, 0, 1, 2]


@pytest.mark.parametrize("distortion", [None, (0.1, -0.05, 0.001, 0.002, 0.01)])
def test_resized_camera_maps_pixel_centres(distortion):
    cam = ring_rig(1, width=160, height=90).cameras[0]
    cam = type(cam)(name="c", width=160, height=90, K=cam.K, cam_to_ego=cam.cam_to_ego, distortion=distortion)
    small = cam.resized(40, 30)                  # s = 1/4 horizontally, 1/3 vertically
    o, d = cam.pixel_rays(np.array([[10.0, 20.0], [80.0, 45.0], [150.0, 3.0]]))
    pts = o + 7.0 * d
    uv, _, _ = cam.project(pts)
    uv2, _, _ = small.project(pts)
    # u -> s (u + 1/2) - 1/2: exact up to float64 round-off of the (un)distortion iterations
    np.testing.assert_allclose(uv2[:, 0], 0.25 * (uv[:, 0] + 0.5) - 0.5, atol=1e-6)
    np.testing.assert_allclose(uv2[:, 1], (uv[:, 1] + 0.5) / 3 - 0.5, atol=1e-6)
    assert small.distortion == cam.distortion and small.image is None


def test_resized_camera_matches_cv2_area_resampling():
    cam = ring_rig(1, width=8, height=6).cameras[0]
    img = np.zeros((6, 8), np.float32)
    img[2:4, 4:6] = 1.0                          # a 2x2 block centred on pixel coordinates (4.5, 2.5)
    small = cv2.resize(img, (4, 3), interpolation=cv2.INTER_AREA)
    v, u = np.unravel_index(np.argmax(small), small.shape)
    half = cam.resized(4, 3)
    o, d = cam.pixel_rays(np.array([[4.5, 2.5]]))
    uv, _, _ = half.project(o + 5.0 * d)
    np.testing.assert_allclose(uv[0], [u, v], atol=1e-9)   # the block lands exactly on one output pixel


# -- issue 27: cut or corrupt images, plain numbers in messages --------------------------------------------------

def _image_rig(tmp_path, suffix: str, n: int = 2) -> Path:
    """A rig of ``n`` 64x48 cameras whose images are real-looking (noise) files of type ``suffix``."""
    d = _rig_dict(n)
    rng = np.random.default_rng(0)
    for k, c in enumerate(d["cameras"]):
        c["image"] = f"cam{k}{suffix}"
        assert cv2.imwrite(str(tmp_path / c["image"]), rng.integers(0, 255, (48, 64, 3)).astype(np.uint8))
    (tmp_path / "rig.json").write_text(json.dumps(d))
    return tmp_path / "rig.json"


_CUTS = {
    # case: (image type, damage to the file's bytes, substring of the reason)
    "jpeg cut": (".jpg", lambda b: b[: len(b) * 2 // 3], "ends before its end-of-image marker"),
    "jpeg with FF bytes inside": (".jpg", lambda b: b[:2000] + b"\xff" * 100 + b[2100:], "Corrupt JPEG data"),
    "jpeg without its end marker": (".jpg", lambda b: b[:-2], "ends before its end-of-image marker"),
    "png cut": (".png", lambda b: b[: len(b) // 2], "ends inside its IDAT chunk"),
    "png without IEND": (".png", lambda b: b[:-12], "ends before its IEND chunk"),
    "png bit flip": (".png", lambda b: b[:200] + bytes([b[200] ^ 0xFF]) + b[201:], "IDAT chunk fails its CRC"),
}


@pytest.mark.parametrize("case", list(_CUTS))
def test_cut_or_corrupt_image_is_refused_naming_the_camera(tmp_path, capfd, case):
    """Regression (issue 27, defects 1 and 5): a cut JPEG decoded without an error (libjpeg fills the rest with grey
    and only warns), a cut PNG's message ended in '()' (the global OpenImageIO error, not the reader's) and libpng
    printed a stray 'libpng error: ...' line. Now: RigError naming the camera and why, one line, nothing printed."""
    suffix, damage, reason = _CUTS[case]
    rig_json = _image_rig(tmp_path, suffix)
    f = tmp_path / f"cam1{suffix}"
    f.write_bytes(damage(f.read_bytes()))
    with pytest.raises(RigError) as info:
        load_rig(rig_json).load_images()
    msg = str(info.value)
    assert msg.startswith("camera 'CAM_1': image: ") and "cut short or corrupt" in msg and reason in msg, msg
    assert "\n" not in msg and "()" not in msg and '("' not in msg, msg
    out, err = capfd.readouterr()
    assert "libpng" not in out + err, err


def test_image_with_bytes_after_its_end_is_accepted(tmp_path):
    """The decoder decides (not a look at the last bytes): data after a JPEG's end marker (some cameras append
    a trailer) and after a PNG's IEND are not damage."""
    for suffix in (".jpg", ".png"):
        rig_json = _image_rig(tmp_path, suffix, n=1)
        f = tmp_path / f"cam0{suffix}"
        f.write_bytes(f.read_bytes() + b"\x00trailer" * 100)
        (img,) = load_rig(rig_json).load_images()
        assert img.shape == (48, 64, 3)


def test_jpeg_metadata_warning_is_accepted(tmp_path):
    """libjpeg's warnings about metadata (here an unknown JFIF revision, which some cameras write) reach us as
    decoder errors too, but the pixels are whole: accepted, unlike the warnings about damaged data."""
    rig_json = _image_rig(tmp_path, ".jpg", n=1)
    (want,) = load_rig(rig_json).load_images()
    f = tmp_path / "cam0.jpg"
    b = bytearray(f.read_bytes())
    i = b.find(b"JFIF\x00")
    assert i > 0
    b[i + 5] = 3                      # JFIF major version 3: "Warning: unknown JFIF revision number 3.01"
    f.write_bytes(bytes(b))
    (img,) = load_rig(rig_json).load_images()
    np.testing.assert_array_equal(img, want)


def test_unreadable_image_label_keeps_paths_out(tmp_path):
    """``label`` names the file instead of its path (the server's store paths never reach a message), and the
    decoder's own mention of the file ('("<path>")') is dropped."""
    from xyzcyl.runtime.rig import image_size, verify_image

    p = tmp_path / "upload.jpg"
    ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (48, 64, 3)).astype(np.uint8))
    assert ok
    p.write_bytes(buf.tobytes()[:2000] + b"\xff" * 100 + buf.tobytes()[2100:])
    assert image_size(p, "part 'CAM_0'", label="the image") == (64, 48)      # the header and the end are whole
    with pytest.raises(RigError) as info:
        verify_image(p, "part 'CAM_0'", label="the image")
    assert str(info.value).startswith("part 'CAM_0': the image is cut short or corrupt (JPEG error: Corrupt JPEG "
                                      "data"), str(info.value)
    assert str(tmp_path) not in str(info.value) and "upload.jpg" not in str(info.value)
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 8)
    with pytest.raises(RigError) as info:
        image_size(p, "part 'CAM_0'", label="the image")
    msg = str(info.value)
    assert msg.startswith("part 'CAM_0': the image is cut short or corrupt") and str(tmp_path) not in msg, msg
    assert msg.count("CAM_0") == 1


def test_numbers_in_messages_are_plain():
    """Regression (issue 27, defect 5): numpy 2 scalars showed as 'np.float64(-633.0)' in validation messages."""
    d = _rig_dict(1)
    d["cameras"][0]["K"][0][0] = -633.0
    with pytest.raises(RigError, match=r"\(got -633\.0\)$"):
        Rig.from_dict(d)
    d = _rig_dict(1)
    d["cameras"][0]["K"][1][0] = 0.5
    with pytest.raises(RigError, match=r"K\[1\]\[0\]: must be 0 \(got 0\.5\)$"):
        Rig.from_dict(d)
    cam = ring_rig(1).cameras[0]
    with pytest.raises(RigError, match=r"width: must be an integer in 1\.\.16384 \(got 64\.5\)$"):
        cam.replace(width=np.float64(64.5))
    with pytest.raises(RigError) as info:
        cam.replace(K=np.diag([np.float32(-2.0), 1.0, 1.0]))
    assert "np." not in str(info.value) and "(got -2.0)" in str(info.value), str(info.value)


def test_images_decoded_in_their_own_type_convert_to_what_the_float_reader_gives(tmp_path):
    """Rig.load_images(native=True) keeps each file's type (8/16-bit, half/float EXR; grey replicated, alpha
    dropped) and runtime.inference.rgb_images converts those once: the same float32 0..1 RGB, bit for bit, as
    as_rgb of the float images read_image makes (the path every keyframe took before), for every kind of file."""
    import OpenImageIO as oiio
    from xyzcyl.runtime.inference import as_rgb, rgb_images

    rng = np.random.default_rng(3)
    files = {"rgb8.png": ("uint8", 3), "grey8.png": ("uint8", 1), "rgba8.png": ("uint8", 4),
             "rgb16.png": ("uint16", 3), "half.exr": ("half", 3), "float.exr": ("float", 3)}
    d = _rig_dict(len(files))
    for cam, (name, (kind, channels)) in zip(d["cameras"], files.items()):
        cam["image"] = name
        if kind in ("uint8", "uint16"):
            a = rng.integers(0, np.iinfo(kind).max + 1, (48, 64, channels)).astype(kind)
        else:                                   # float files: out of 0..1 too (as_rgb clips those)
            a = rng.uniform(-0.5, 1.5, (48, 64, channels)).astype(np.float32)
        out = oiio.ImageOutput.create(str(tmp_path / name))
        out.open(str(tmp_path / name), oiio.ImageSpec(64, 48, channels, kind))
        out.write_image(a)
        out.close()
    (tmp_path / "rig.json").write_text(json.dumps(d))
    rig = load_rig(tmp_path / "rig.json")
    native = rig.load_images(native=True)
    assert [a.dtype.name for a in native] == ["uint8", "uint8", "uint8", "uint16", "float16", "float32"]
    assert all(a.shape == (48, 64, 3) for a in native)
    want = [as_rgb(img, cam) for img, cam in zip(rig.load_images(), rig.cameras)]
    for threads in (1, 2):
        got = rgb_images(rig, threads)
        for g, w in zip(got, want):
            assert g.dtype == np.float32 and g.flags.c_contiguous and 0 <= g.min() and g.max() <= 1
            np.testing.assert_array_equal(g, w)
    # a file of another size than the rig says is refused the same way both ways, naming the camera
    d["cameras"][0]["width"] = 65
    (tmp_path / "rig.json").write_text(json.dumps(d))
    for native in (False, True):
        with pytest.raises(RigError, match="is 64x48, but width x height is 65x48"):
            load_rig(tmp_path / "rig.json").load_images(native=native)
