"""`xyzcyl render`: PNG / EXR outputs and user-input errors (exit 2, one line naming the field)."""

from __future__ import annotations

import numpy as np
import pytest
from render_scenes import random_gaussians
from xyzcyl import cli
from xyzcyl.runtime.camera import Camera
from xyzcyl.runtime.render import Gaussians, render

EYE = [str(v) for v in np.eye(4).ravel()]


@pytest.fixture
def ply(tmp_path):
    g = random_gaussians(np.random.default_rng(0), 150, degree=1)
    path = tmp_path / "g.ply"
    g.save_ply(path)
    return path


def _argv(ply, out, *extra):
    return ["render", str(ply), "--width", "48", "--height", "32", "--K", "40", "40", "23.5", "15.5",
            "--cam-to-world", *EYE, "--out", str(out), *extra]


def test_png_and_exr(ply, tmp_path):
    import cv2
    import OpenImageIO as oiio

    assert cli.main(_argv(ply, tmp_path / "a.png", "--background", "0.1", "0.2", "0.3")) == 0
    assert cli.main(_argv(ply, tmp_path / "a.exr", "--background", "0.1", "0.2", "0.3")) == 0
    cam = Camera(K=np.array([[40, 0, 23.5], [0, 40, 15.5], [0, 0, 1.0]]), cam_to_ego=np.eye(4), width=48, height=32)
    ref = render(Gaussians.load_ply(ply), cam, (0.1, 0.2, 0.3))
    png = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert png.shape == (32, 48, 3) and png.dtype == np.uint8
    assert np.abs(png.astype(np.float64) - np.clip(ref.rgb, 0, 1) * 255).max() <= 0.5 + 1e-3  # rounding only
    inp = oiio.ImageInput.open(str(tmp_path / "a.exr"))
    assert inp.spec().channelnames == ("R", "G", "B", "A", "Z")
    exr = inp.read_image(oiio.FLOAT)
    inp.close()
    assert np.array_equal(exr, np.dstack([ref.rgb, ref.alpha, ref.depth]))  # float32 stored exactly


@pytest.mark.parametrize("out, output", [("d.png", "depth"), ("a.jpg", "alpha"), ("c.jpg", "rgb"), ("z.exr", "depth")])
def test_every_output_is_the_services_encoding(ply, tmp_path, out, output):
    """One encoder for the CLI and HTTP (issue 27, house 2): `xyzcyl render --output X --out F` writes exactly the
    bytes runtime.views.encode_view gives the service for the same view (16-bit depth PNG and JPEG included)."""
    from xyzcyl.runtime.views import ViewRequest, camera_from_opencv, encode_view

    assert cli.main(_argv(ply, tmp_path / out, "--output", output, "--quality", "80")) == 0
    cam = camera_from_opencv(np.eye(4), 48, 32, fx=40, fy=40, cx=23.5, cy=15.5)
    req = ViewRequest(cam, output, {"png": "png", "jpg": "jpeg", "exr": "exr"}[out.split(".")[1]], 80)
    ref = render(Gaussians.load_ply(ply), cam)
    assert (tmp_path / out).read_bytes() == encode_view(ref.rgb, ref.depth, ref.alpha, req)


def test_fov_flag_is_the_services_fov(ply, tmp_path):
    """--fov resolves through the same ViewQuery as the query's fov (horizontal degrees, centred principal point)."""
    from xyzcyl.runtime.views import camera_from_opencv

    argv = ["render", str(ply), "--width", "48", "--height", "32", "--fov", "62", "--cam-to-world", *EYE,
            "--out", str(tmp_path / "f.exr")]
    assert cli.main(argv) == 0
    ref = render(Gaussians.load_ply(ply), camera_from_opencv(np.eye(4), 48, 32, fov=62))
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(tmp_path / "f.exr"))
    exr = inp.read_image(oiio.FLOAT)
    inp.close()
    assert np.array_equal(exr[..., :3], ref.rgb)


def test_distortion_flag_renders_the_lens(ply, tmp_path):
    """--distortion (issue 28): a lens as rig.json writes it, JSON text or a .json file, rendered as the runtime
    renders that lens camera; a bad lens field is named under the flag."""
    import json

    import OpenImageIO as oiio
    from xyzcyl.common.wire import validated
    from xyzcyl.runtime.views import resolve

    lens = {"model": "opencv_fisheye", "k1": 0.03, "k2": 0.0, "k3": 0.0, "k4": 0.0, "max_angle_deg": 95.0}
    (tmp_path / "lens.json").write_text(json.dumps({"name": "CAM", "distortion": lens}))
    for value in (json.dumps(lens), str(tmp_path / "lens.json")):
        argv = ["render", str(ply), "--width", "48", "--height", "32", "--K", "20", "20", "23.5", "15.5",
                "--distortion", value, "--cam-to-world", *EYE, "--out", str(tmp_path / "l.exr")]
        assert cli.main(argv) == 0
        inp = oiio.ImageInput.open(str(tmp_path / "l.exr"))
        exr = inp.read_image(oiio.FLOAT)
        inp.close()
        cam = resolve(validated(dict(cam_to_ego=np.eye(4), fx=20, fy=20, cx=23.5, cy=15.5, width=48, height=32,
                                     distortion=lens)))
        ref = render(Gaussians.load_ply(ply), cam)
        assert np.array_equal(exr[..., :3], ref.rgb)
    bad = ["render", str(ply), "--width", "48", "--height", "32", "--fov", "90", "--distortion",
           json.dumps(dict(lens, max_angle_deg=200)), "--cam-to-world", *EYE, "--out", str(tmp_path / "b.png")]
    assert cli.main(bad) == 2


def test_equirect(ply, tmp_path):
    argv = ["render", str(ply), "--width", "64", "--height", "32", "--cam-to-world", *EYE,
            "--out", str(tmp_path / "p.png"), "--equirect"]
    assert cli.main(argv) == 0


@pytest.mark.parametrize("change, field", [
    (("--out", "x.bmp"), "--out"),
    (("--K", "-1", "40", "1", "1"), "--K"),
    (("--width", "0"), "--width"),
    (("--cam-to-world", *(["2"] + EYE[1:])), "--cam-to-world"),
    (("--max-points", "3"), "PLY"),
])
def test_user_errors_exit_2_naming_the_field(ply, tmp_path, capsys, change, field):
    argv = _argv(ply, tmp_path / "a.png")
    flag = change[0]
    i = argv.index(flag) if flag in argv else len(argv)
    n = {"--out": 1, "--K": 4, "--width": 1, "--cam-to-world": 16}.get(flag, 0)
    value = list(change[1:])
    if flag == "--out":
        value = [str(tmp_path / value[0])]
    argv = argv[:i] + [flag, *value] + argv[i + 1 + n:]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"xyzcyl render: {field}")


def test_missing_ply(tmp_path, capsys):
    assert cli.main(_argv(tmp_path / "nope.ply", tmp_path / "a.png")) == 2
    assert "PLY" in capsys.readouterr().err
