"""Property tests (hypothesis) of the parsers and converters at the service's boundary: rig JSON, CARLA / OpenCV /
OpenGL poses, PLY and .splat readers on mutated files, image headers. Every bad input must end in the module's own
error type (RigError, GaussianError, ViewError), never another exception or a hang; round trips must hold.
Example counts are kept small for CI (docs/reliability.md: the long run raises them with HYPOTHESIS_PROFILE=long)."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from xyzcyl.runtime.convert import (
    camera_from_carla,
    camera_to_carla,
    cameras_from_nerfstudio_path,
    cameras_to_nerfstudio_path,
    rig_from_nerfstudio,
    rig_to_nerfstudio,
)
from xyzcyl.runtime.render import GaussianError, Gaussians
from xyzcyl.runtime.rig import Camera, Rig, RigError, image_size, look_rotation
from xyzcyl.runtime.views import ViewError, cameras_from_batch

settings.register_profile("ci", max_examples=60, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("long", max_examples=2000, deadline=5000, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

EXAMPLE_RIG = Path(__file__).resolve().parents[2] / "examples" / "synth_nuscenes" / "rig.json"

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**12, 10**12) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5),
    max_leaves=30)


def _example_doc() -> dict:
    return json.loads(EXAMPLE_RIG.read_text())


# ------------------------------------------------------------------------------------------------ rig JSON

@given(json_values)
def test_arbitrary_json_is_a_rig_or_a_rig_error(doc):
    try:
        Rig.from_dict(doc)
    except RigError:
        pass


_CAMERA_KEYS = ("name", "width", "height", "K", "cam_to_ego", "model", "distortion", "image", "depth")


@given(st.integers(0, 5), st.sampled_from(_CAMERA_KEYS), json_values)
def test_a_mutated_camera_field_is_accepted_or_a_rig_error_naming_the_camera(index, key, value):
    doc = _example_doc()
    cam = doc["cameras"][index]
    cam[key] = value
    try:
        rig = Rig.from_dict(doc)
    except RigError as e:
        # the message names the camera (by name, or by index when the name itself is bad)
        assert (isinstance(cam.get("name"), str) and cam["name"] and cam["name"] in str(e)) or f"{index}" in str(e) \
            or "name" in str(e), str(e)
        return
    assert len(rig) == 6


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=0, max_size=20))
def test_pose_numbers_are_accepted_only_as_a_rigid_transform(flat):
    doc = _example_doc()
    doc["cameras"][0]["cam_to_ego"] = flat
    try:
        rig = Rig.from_dict(doc)
    except RigError:
        return
    T = rig.cameras[0].cam_to_ego
    R = T[:3, :3]
    assert np.all(np.isfinite(T)) and np.allclose(R.T @ R, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0


# ------------------------------------------------------------------------------------------------ poses

angles = st.floats(-179.0, 179.0, allow_nan=False)


@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-5, 5), st.floats(-85.0, 85.0), angles, angles,
       st.floats(5.0, 170.0), st.integers(16, 4000), st.integers(16, 4000))
def test_carla_round_trip(x, y, z, pitch, yaw, roll, fov, w, h):
    sensor = {"transform": {"location": {"x": x, "y": y, "z": z},
                            "rotation": {"pitch": pitch, "yaw": yaw, "roll": roll}},
              "fov": fov, "image_size_x": w, "image_size_y": h}
    cam = camera_from_carla(sensor, name="c")
    back = camera_to_carla(cam)
    again = camera_from_carla(back, name="c")
    # 1e-9 relative: float64 trigonometry of the same angles, a few ulp per operation
    np.testing.assert_allclose(again.cam_to_ego, cam.cam_to_ego, atol=1e-9)
    np.testing.assert_allclose(again.K, cam.K, rtol=1e-9)
    loc = back["transform"]["location"]
    assert math.isclose(loc["x"], x, abs_tol=1e-9) and math.isclose(loc["y"], y, abs_tol=1e-9)
    assert math.isclose(back["fov"], fov, rel_tol=1e-9)


def _camera(yaw, pitch, pos, w, h, f, name="c") -> Camera:
    T = np.eye(4)
    T[:3, :3] = look_rotation(yaw, pitch)
    T[:3, 3] = pos
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return Camera(name=name, width=w, height=h, K=K, cam_to_ego=T)


cameras = st.builds(_camera, st.floats(-3.1, 3.1), st.floats(-1.2, 1.2),
                    st.tuples(st.floats(-20, 20), st.floats(-20, 20), st.floats(-2, 5)),
                    st.integers(8, 2000), st.integers(8, 2000), st.floats(10.0, 3000.0))


@given(st.lists(cameras, min_size=1, max_size=4))
def test_nerfstudio_opengl_round_trip(cams):
    rig = Rig(cameras=tuple(c.replace(name=f"cam{i}", image=f"cam{i}.png") for i, c in enumerate(cams)))
    back = rig_from_nerfstudio(rig_to_nerfstudio(rig))
    for a, b in zip(rig.cameras, back.cameras):
        # 1e-9: the OpenGL flip is exact; only float64 rounding of K's half-pixel shift remains
        np.testing.assert_allclose(b.cam_to_ego, a.cam_to_ego, atol=1e-9)
        np.testing.assert_allclose(b.K, a.K, atol=1e-9)


@given(st.lists(cameras, min_size=1, max_size=4), st.integers(8, 2000), st.integers(8, 2000))
def test_camera_path_round_trip(cams, w, h):
    same = [c.resized(w, h) for c in cams]
    same = [c.replace(K=np.array([[c.K[0, 0], 0, (w - 1) / 2], [0, c.K[0, 0], (h - 1) / 2], [0, 0, 1.0]]))
            for c in same]
    back = cameras_from_nerfstudio_path(cameras_to_nerfstudio_path(same))
    for a, b in zip(same, back):
        np.testing.assert_allclose(b.cam_to_ego, a.cam_to_ego, atol=1e-9)   # as above
        np.testing.assert_allclose(b.K, a.K, rtol=1e-9)


@given(json_values)
def test_render_batches_are_cameras_or_a_view_error(doc):
    try:
        cams = cameras_from_batch(doc if isinstance(doc, dict) else {"cameras": doc}, max_frames=10)
    except ViewError as e:
        assert e.field
        return
    assert 0 < len(cams) <= 10


# ------------------------------------------------------------------------------------------------ PLY and .splat

def _gaussians(n: int = 20, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(means=rng.normal(size=(n, 3)).astype(np.float32),
                     quats=rng.normal(size=(n, 4)).astype(np.float32),
                     log_scales=rng.normal(-2, 0.5, size=(n, 3)).astype(np.float32),
                     opacity_logits=rng.normal(size=n).astype(np.float32),
                     sh=rng.normal(size=(n, 1, 3)).astype(np.float32))


@pytest.fixture(scope="module")
def ply_bytes() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "g.ply"
        _gaussians().save_ply(p)
        return p.read_bytes()


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_ply_is_read_or_refused_with_a_gaussian_error(ply_bytes, data, tmp_path):
    b = bytearray(ply_bytes)
    kind = data.draw(st.sampled_from(["flip", "truncate", "header", "count"]))
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
    elif kind == "truncate":
        b = b[:data.draw(st.integers(0, len(b) - 1))]
    elif kind == "header":
        end = bytes(b).index(b"end_header")
        b[data.draw(st.integers(0, end))] = data.draw(st.sampled_from(list(b" \n\x00abc1-")))
    else:
        n = data.draw(st.sampled_from([0, 19, 21, 10**9, 2**31, 2**64]))
        b = bytearray(bytes(b).replace(b"element vertex 20", f"element vertex {n}".encode(), 1))
    p = tmp_path / "m.ply"
    p.write_bytes(bytes(b))
    try:
        g = Gaussians.load_ply(p)
    except GaussianError:
        return
    assert np.all(np.isfinite(g.means))


def test_ply_header_naming_a_property_twice_is_refused_naming_it(tmp_path, ply_bytes):
    """The case the mutation test above found (a header byte turned 'rot_2' into a second 'rot_1'): a GaussianError
    naming the property, not numpy's ValueError from the record type."""
    p = tmp_path / "twice.ply"
    p.write_bytes(ply_bytes.replace(b"property float rot_2\n", b"property float rot_1\n", 1))
    with pytest.raises(GaussianError) as e:
        Gaussians.load_ply(p)
    assert e.value.field == "rot_1" and "twice" in str(e.value)


def test_ply_header_claiming_a_billion_vertices_is_refused_before_reading(tmp_path, ply_bytes):
    p = tmp_path / "huge.ply"
    p.write_bytes(ply_bytes.replace(b"element vertex 20", b"element vertex 1000000000", 1))
    with pytest.raises(GaussianError, match="1000000000"):
        Gaussians.load_ply(p)


def test_splat_round_trip_within_the_format_quantisation():
    g = _gaussians(50)
    back = Gaussians.from_splat_bytes(g.splat_bytes())
    order = np.argsort(-np.exp(g.log_scales.sum(1)) / (1 + np.exp(-g.opacity_logits)), kind="stable")
    np.testing.assert_array_equal(back.means, g.means[order])                 # float32 stored as is
    np.testing.assert_allclose(back.log_scales, g.log_scales[order], atol=1e-6)   # exp/log in float32
    colour = np.clip(0.5 + 0.28209479177387814 * g.sh[order, 0], 0, 1)
    # 1/255: colours are truncated to 8 bits
    np.testing.assert_allclose(0.5 + 0.28209479177387814 * back.sh[:, 0], colour, atol=1.0 / 255 + 1e-6)


@given(st.binary(max_size=400))
def test_arbitrary_splat_bytes_are_read_or_refused(data):
    try:
        g = Gaussians.from_splat_bytes(data)
    except GaussianError:
        return
    assert len(g) == len(data) // 32


# ------------------------------------------------------------------------------------------------ image headers

def _png(w: int, h: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.zeros((h, w, 3), np.uint8))
    assert ok
    return buf.tobytes()


def _with_ihdr_size(png: bytes, w: int, h: int) -> bytes:
    """The same PNG whose IHDR claims w x h (CRC fixed so readers trust the header)."""
    import struct
    import zlib

    ihdr = png[12:16] + struct.pack(">II", w, h) + png[24:29]
    return png[:8] + png[8:12] + ihdr + struct.pack(">I", zlib.crc32(ihdr) & 0xFFFFFFFF) + png[33:]


def test_decompression_bomb_header_is_refused_without_decoding(tmp_path):
    """A 86-byte PNG whose header claims 30000x30000: OpenImageIO's own guard refuses it at open (header vs file
    size), so image_size raises RigError at once; a plausible large header is reported as is (the server then
    compares it with max_image_pixels before any decoding)."""
    p = tmp_path / "bomb.png"
    p.write_bytes(_with_ihdr_size(_png(8, 8), 30000, 30000))
    with pytest.raises(RigError, match="header"):      # refused from the header, nothing decoded
        image_size(p, "part")
    q = tmp_path / "honest.png"
    q.write_bytes(_with_ihdr_size(_png(8, 8), 9, 8))
    assert image_size(q, "part") == (9, 8)


@given(data=st.data())
@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_mutated_image_headers_give_a_size_or_a_rig_error(data, tmp_path):
    b = bytearray(_png(16, 12) if data.draw(st.booleans()) else _jpeg(16, 12))
    for _ in range(data.draw(st.integers(1, 6))):
        b[data.draw(st.integers(0, min(len(b) - 1, 60)))] = data.draw(st.integers(0, 255))
    p = tmp_path / "m.img"
    p.write_bytes(bytes(b))
    try:
        w, h = image_size(p, "part")
    except RigError:
        return
    assert w >= 0 and h >= 0


def _jpeg(w: int, h: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.zeros((h, w, 3), np.uint8))
    assert ok
    return buf.tobytes()



