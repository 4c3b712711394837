"""Lenses in render requests (issue 28, interfaces): a ViewQuery, a batch item, the GET query, both CLIs and the
Python client state a camera's lens as rig.json writes it (runtime.lenses), and the errors name the lens field in
the transport's own terms."""

from __future__ import annotations

import json

import numpy as np
import pytest
from xyzcyl.clients.client import view_params
from xyzcyl.common.poses import PoseArgError, parse_lens
from xyzcyl.common.wire import ViewError, validated
from xyzcyl.runtime import convert
from xyzcyl.runtime.views import cameras_from_batch, resolve


def _view(**kw):
    """The render camera of a view given as ViewQuery fields (runtime.views.resolve)."""
    return resolve(validated(kw))

FISHEYE = {"model": "opencv_fisheye", "k1": 0.05, "k2": -0.01, "k3": 0.0, "k4": 0.0, "max_angle_deg": 95.0}
AHEAD = [0, 0, 1, 0, -1, 0, 0, 0, 0, -1, 0, 1.6, 0, 0, 0, 1]     # OpenCV camera looking along ego x


def test_spec_with_a_lens_makes_a_lens_camera():
    cam = _view(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=FISHEYE)
    assert cam.lens_model == "opencv_fisheye" and cam.distortion.to_json() == FISHEYE
    assert cam.K[0, 0] == pytest.approx(32.0)           # fov gives the lens's paraxial focal length
    plain = _view(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=[0.1, 0.0, 0.0, 0.0])
    assert plain.lens_model == "opencv"


@pytest.mark.parametrize("spec, field", [
    (dict(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=dict(FISHEYE, k1="x")), "distortion.k1"),
    (dict(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=dict(FISHEYE, max_angle_deg=200)),
     "distortion.max_angle_deg"),
    (dict(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=[0.1, float("nan"), 0, 0]), "distortion[1]"),
    (dict(camera="CAM_FRONT", distortion=FISHEYE), "camera"),   # an input camera takes a lens (issue 35): needs a rig
    (dict(x=0, y=0, z=1, pitch=0, yaw=0, roll=0, fov=90, width=64, height=48, distortion=FISHEYE), "distortion"),
])
def test_lens_errors_name_the_lens_field(spec, field):
    with pytest.raises(ViewError) as e:
        _view(**spec)
    assert e.value.field == field, str(e.value)


def test_batch_items_take_a_lens_and_name_its_fields_by_json_path():
    doc = {"cameras": [{"fov": 90, "cam_to_ego": AHEAD, "width": 64, "height": 48},
                       {"K": [[30, 0, 31.5], [0, 30, 23.5], [0, 0, 1]], "cam_to_ego": AHEAD, "width": 64,
                        "height": 48, "distortion": FISHEYE}]}
    cams = cameras_from_batch(doc)
    assert [c.lens_model for c in cams] == ["pinhole", "opencv_fisheye"]
    doc["cameras"][1]["distortion"] = dict(FISHEYE, k2=None, k5=1.0)
    with pytest.raises(ViewError) as e:
        cameras_from_batch(doc)
    assert e.value.field.startswith("cameras[1].distortion"), str(e.value)


def test_a_lens_is_part_of_the_request_key():
    from xyzcyl.runtime.views import ViewRequest

    a = ViewRequest(_view(cam_to_ego=AHEAD, fov=90, width=64, height=48))
    b = ViewRequest(_view(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=FISHEYE))
    assert a.description()["distortion"] is None and b.description()["distortion"] == FISHEYE
    assert a.key() != b.key()


def test_nerfstudio_fisheye_camera_path_round_trips():
    doc = {"render_width": 64, "render_height": 48, "camera_type": "fisheye",
           "camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 70.0}]}
    cams = convert.cameras_from_nerfstudio_path(doc)
    lens = cams[0].distortion.to_json()
    assert lens["model"] == "opencv_fisheye" and lens["max_angle_deg"] == 180.0
    assert all(lens[k] == 0.0 for k in ("k1", "k2", "k3", "k4"))           # nerfstudio's equidistant fisheye
    back = convert.cameras_to_nerfstudio_path(cams)
    assert back["camera_type"] == "fisheye" and back["camera_path"][0]["fov"] == pytest.approx(70.0)
    # a lens nerfstudio's camera path cannot express is refused, naming the field
    other = _view(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=FISHEYE)
    with pytest.raises(convert.ConversionError) as e:
        convert.cameras_to_nerfstudio_path([other])
    assert e.value.field == "distortion"


def test_client_sends_the_lens_as_json(tmp_path):
    p = view_params({"cam_to_ego": AHEAD, "fov": 90, "distortion": FISHEYE}, 64, 48)
    assert json.loads(p["distortion"]) == FISHEYE
    cam = _view(cam_to_ego=AHEAD, fov=90, width=64, height=48, distortion=FISHEYE)
    assert json.loads(view_params(cam)["distortion"]) == FISHEYE       # a runtime Camera's Lens: its to_json()


def test_parse_lens_reads_json_text_files_and_rig_entries(tmp_path):
    assert parse_lens(json.dumps(FISHEYE)) == FISHEYE
    assert parse_lens("[0.1, 0, 0, 0]") == [0.1, 0, 0, 0]
    (tmp_path / "lens.json").write_text(json.dumps({"name": "CAM", "distortion": FISHEYE}))
    assert parse_lens(str(tmp_path / "lens.json")) == FISHEYE
    for bad in ("{nope", "3", str(tmp_path / "missing.json")):
        with pytest.raises(PoseArgError) as e:
            parse_lens(bad)
        assert e.value.field == "--distortion"


def test_nerfstudio_opencv_fisheye_transforms_round_trip():
    """transforms.json OPENCV_FISHEYE (k1..k4) <-> an opencv_fisheye lens; nerfstudio has no max angle, so the
    reader takes the widest the coefficients allow (up to 180 degrees)."""
    frame = {"file_path": "images/f.png", "camera_model": "OPENCV_FISHEYE", "fl_x": 300.0, "fl_y": 300.0,
             "cx": 640.0, "cy": 480.0, "w": 1280, "h": 960, "k1": 0.02, "k2": -0.003, "k3": 0.0, "k4": 0.0,
             "transform_matrix": np.eye(4).tolist()}
    rig = convert.rig_from_nerfstudio({"frames": [frame]})
    cam = rig.cameras[0]
    lens = cam.distortion.to_json()
    assert cam.lens_model == "opencv_fisheye" and (lens["k1"], lens["k2"]) == (0.02, -0.003)
    assert 90.0 < lens["max_angle_deg"] <= 180.0
    back = convert.rig_to_nerfstudio(rig)["frames"][0]
    assert back["camera_model"] == "OPENCV_FISHEYE"
    assert {k: back[k] for k in ("k1", "k2", "k3", "k4")} == {"k1": 0.02, "k2": -0.003, "k3": 0.0, "k4": 0.0}
    assert (back["cx"], back["cy"]) == (640.0, 480.0)
    strong = dict(frame, k1=-0.3)            # theta_d turns back well before 180 degrees: max angle just under it
    turned = convert.rig_from_nerfstudio({"frames": [strong]}).cameras[0].distortion.to_json()["max_angle_deg"]
    assert turned < 90.0
