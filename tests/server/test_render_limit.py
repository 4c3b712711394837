"""One render limit, one message, checked before anything is allocated (issue 35 item 6: the CLI took 1..16384 a
side with no pixel cap, so 16384x16384 died in numpy's allocator; GET said <= 32768 while the server's limit was
8192; the batch said 1..16384). runtime.camera.check_render_size is the rule: 16384 pixels a side and 16777216 in
all, the same for the library's render, `xyzcyl render`, GET, the batch and gRPC (a server may lower it)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from api_helpers import err, url
from xyzcyl import cli
from xyzcyl.common.wire import ViewError, validated
from xyzcyl.runtime.camera import Camera, CameraError, render_limit
from xyzcyl.runtime.render import Gaussians, render
from xyzcyl.runtime.views import request

LIMIT = render_limit()        # "the render limit (16384 pixels a side, 16777216 pixels in all)"
_C2E = "0,0,1,1.5,-1,0,0,0,0,-1,0,1.6,0,0,0,1"


def test_the_library_render_refuses_before_allocating():
    cam = Camera(K=np.array([[8000.0, 0, 8191.5], [0, 8000.0, 8191.5], [0, 0, 1]]), cam_to_ego=np.eye(4),
                 width=16384, height=16384)
    t0 = time.perf_counter()
    with pytest.raises(CameraError, match="over the render limit") as e:
        render(Gaussians.empty(), cam)
    assert e.value.field == "width" and time.perf_counter() - t0 < 1.0     # no 10 GB of buffers first


@pytest.mark.parametrize("w, h, field", [(20000, 100, "width"), (100, 20000, "height"), (8000, 8000, "width")])
def test_a_view_spec_names_the_limit(w, h, field):
    with pytest.raises(ViewError) as e:
        request(validated(dict(cam_to_ego=np.eye(4), fov=60, width=w, height=h)))
    assert e.value.field == field and LIMIT in str(e.value)


def test_the_cli_refuses_with_the_same_words(tmp_path, capsys):
    ply = tmp_path / "g.ply"
    Gaussians(np.zeros((1, 3), np.float32), np.array([[1, 0, 0, 0]], np.float32), np.zeros((1, 3), np.float32),
              np.zeros(1, np.float32), np.zeros((1, 1, 3), np.float32)).save_ply(ply)
    code = cli.main(["render", str(ply), "--width", "16384", "--height", "16384", "--fov", "60",
                     "--cam-to-world", *_C2E.split(","), "--out", str(tmp_path / "v.png")])
    err_text = capsys.readouterr().err
    assert code == 2 and LIMIT in err_text and "Traceback" not in err_text and len(err_text.strip().splitlines()) == 1


@pytest.mark.parametrize("query, field", [(f"cam_to_ego={_C2E}&fov=60&width=17000&height=100", "width"),
                                          (f"cam_to_ego={_C2E}&fov=60&width=4097&height=4096", "width")])
def test_get_and_batch_answer_with_the_same_words(client, env, query, field):
    e = err(client.get(url(env, f"/render?{query}")), 422, code="invalid")
    assert e["field"] == field and LIMIT in e["message"], e
    w, h = (int(kv.split("=")[1]) for kv in query.split("&")[-2:])
    batch = {"cameras": [{"fov": 60, "cam_to_ego": [float(v) for v in _C2E.split(",")], "width": w, "height": h}]}
    e = err(client.post(url(env, "/render"), json=batch), 422, code="invalid")
    assert LIMIT in e["message"], e


def test_the_openapi_document_states_the_limit(client):
    params = {p["name"]: p for p in client.get("/openapi.json").json()["paths"]["/v1/scenes/{scene_id}/render"]
              ["get"]["parameters"]}
    assert LIMIT in params["width"]["description"] and "maximum" not in params["width"]["schema"]
