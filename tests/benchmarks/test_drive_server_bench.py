"""benchmarks/drive_server_bench.py asks the service for the views drive_bench's render case draws: the same poses
(the scene's frame), intrinsics and times, in GET query parameters the service accepts."""

from __future__ import annotations

import dataclasses

import drive_server_bench as B  # benchmarks/drive_server_bench.py (pyproject.toml: pytest's pythonpath)
import numpy as np
from xyzcyl.common.wire import validated
from xyzcyl.runtime.drive import load_drive
from xyzcyl.runtime.views import request


def test_the_views_are_the_render_cases_as_query_parameters(real_data):
    drive_json = real_data / "pandaset_002_drive" / "drive.json"
    views = B.places(drive_json, 2, 1600, 900)
    assert len(views) == 60                             # 10 keyframes' 6 cameras
    d = load_drive(drive_json)
    # the 8th view: the second place, frame 4 (every 2nd of the 20 keyframes, frames 0, 2, 4, ...), its 2nd camera,
    # halfway to the next keyframe's (frame 6's) time
    cam = d.frames[4].rig.cameras[1].resized(1600, 900)
    want = dataclasses.replace(cam, cam_to_ego=d.relative(4) @ np.asarray(cam.cam_to_ego))
    got = request(validated({**views[7], "format": "png"})).camera
    assert (got.width, got.height) == (1600, 900)
    np.testing.assert_allclose(got.cam_to_ego, want.cam_to_ego, atol=1e-6)     # metres: 9 significant digits
    np.testing.assert_allclose(got.K, want.K, rtol=1e-8)
    assert abs(float(views[7]["time"]) - 0.5 * (d.frames[4].timestamp_s + d.frames[6].timestamp_s)) < 1e-6
