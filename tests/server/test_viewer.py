"""GET /v1/scenes/{id}/viewer without a browser (tests/server/test_viewer_browser.py has the browser): the page and
the JSON it is given, its errors (a page for a browser, the error body for others), the npm modules' files and the
answer where they are missing, and `xyzcyl view`'s refusals. The app runs without its lifespan (no worker
processes) over a store that `xyzcyl view` made (server/commands/view.py: the scene folder linked in)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from xyzcyl.testing import EXAMPLE_RIG, REPO

SID_MISSING = "A" * 22


def _ground_scene(folder, drive=None, actors=None):
    from xyzcyl.runtime.render import Gaussians
    from xyzcyl.runtime.rig import load_rig
    from xyzcyl.runtime.scene import Scene

    x, y = np.meshgrid(np.arange(2.0, 20.0, 1.0), np.arange(-5.0, 5.0, 1.0), indexing="ij")
    means = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1).astype(np.float32)
    n = len(means)
    g = Gaussians(means, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full((n, 3), -1.0, np.float32),
                  np.full(n, 3.0, np.float32), np.zeros((n, 1, 3), np.float32))
    Scene(gaussians=g, background=None, rig=load_rig(EXAMPLE_RIG), drive=drive, actors=actors).save(folder)
    return folder


def _app(tmp_path, **settings):
    from xyzcyl.server import Settings, create_app
    from xyzcyl.server.commands.view import store_with_scene

    root = tmp_path / "store"
    sid = store_with_scene(_ground_scene(tmp_path / "scene"), root)
    app = create_app(Settings(store=str(root), **settings))
    app.state.service.store.open()          # what the lifespan does first (the rest: worker processes, not needed)
    return TestClient(app), sid


def _fake_modules(folder):
    """A node_modules folder with every file the page imports (empty): the page tests do not need npm."""
    from xyzcyl.server.viewer import PACKAGES

    for _, pkg, files in PACKAGES:
        for f in files:
            (folder / pkg / f).parent.mkdir(parents=True, exist_ok=True)
            (folder / pkg / f).write_text("// test\n")
    return folder


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("viewer")
    return _app(tmp, viewer_modules=_fake_modules(tmp / "node_modules"))


def _data(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="xyzcyl-scene">(.*?)</script>', html, re.S)
    assert m is not None, html[:500]
    return json.loads(m.group(1))


def test_the_page_and_its_data(viewer):
    from xyzcyl.runtime.rig import load_rig

    client, sid = viewer
    r = client.get(f"/v1/scenes/{sid}/viewer?camera=CAM_BACK&width=400")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    # the modules come from this server (the importmap), no other host is named
    assert '"three": "/viewer/modules/three/build/three.module.js"' in r.text
    assert '"@sparkjsdev/spark": "/viewer/modules/spark/spark.module.js"' in r.text
    assert "http:" not in r.text and "https:" not in r.text and re.search(r"[\"']//", r.text) is None
    d = _data(r.text)
    rig = load_rig(EXAMPLE_RIG)
    assert [c["name"] for c in d["cameras"]] == rig.names
    back = d["cameras"][rig.names.index("CAM_BACK")]
    np.testing.assert_allclose(back["cam_to_ego"], rig.camera("CAM_BACK").cam_to_ego)
    np.testing.assert_allclose(back["K"], rig.camera("CAM_BACK").K)
    assert d["view"] == {"camera": "CAM_BACK", "width": 400, "height": 225}      # height from the aspect ratio
    assert [s["format"] for s in d["splats"]] == ["spz", "ply"]
    assert d["splats"][1]["url"] == f"/v1/scenes/{sid}/gaussians?format=ply"
    assert d["trajectory"] == [[0.0, 0.0, 0.0]] and d["actors"] is False        # one rig: one frame, no actors
    # the files it loads are served
    assert client.get("/viewer/web/viewer.js").status_code == 200
    # the default view: the first camera, fitted to the window
    assert _data(client.get(f"/v1/scenes/{sid}/viewer").text)["view"] == {"camera": rig.names[0], "width": None,
                                                                          "height": None}


@pytest.mark.skipif(not (REPO / "node_modules" / "three").is_dir(), reason="npm ci has not been run")
def test_the_npm_modules_are_served(tmp_path):
    client, sid = _app(tmp_path, viewer_modules=REPO / "node_modules")
    assert client.get(f"/v1/scenes/{sid}/viewer").status_code == 200
    for path in ("/viewer/modules/three/build/three.module.js", "/viewer/modules/three/build/three.core.js",
                 "/viewer/modules/three/examples/jsm/controls/OrbitControls.js",
                 "/viewer/modules/spark/spark.module.js"):
        r = client.get(path)
        assert r.status_code == 200 and "javascript" in r.headers["content-type"], path
    assert client.get("/viewer/modules/three/../../package.json").status_code == 404


def test_errors_are_a_page_for_a_browser_and_the_error_body_for_others(viewer):
    client, sid = viewer
    r = client.get(f"/v1/scenes/{SID_MISSING}/viewer")
    assert r.status_code == 404 and r.json()["error"]["field"] == "id"
    r = client.get(f"/v1/scenes/{SID_MISSING}/viewer", headers={"Accept": "text/html,*/*"})
    assert r.status_code == 404 and r.headers["content-type"].startswith("text/html")
    assert 'role="alert"' in r.text and f"no scene &#x27;{SID_MISSING}&#x27;" in r.text
    r = client.get(f"/v1/scenes/{sid}/viewer?camera=NOPE")
    e = r.json()["error"]
    assert r.status_code == 422 and e["field"] == "camera" and "CAM_FRONT" in e["message"]
    r = client.get(f"/v1/scenes/{sid}/viewer?camera=CAM_FRONT&widht=3")
    assert r.status_code == 422 and r.json()["error"]["field"] == "widht"
    r = client.get(f"/v1/scenes/{sid}/viewer?width=20000")
    assert r.status_code == 422 and r.json()["error"]["field"] == "width"


def test_without_the_npm_modules_the_page_says_how_to_install_them(tmp_path):
    client, sid = _app(tmp_path, viewer_modules=tmp_path / "nowhere")
    r = client.get(f"/v1/scenes/{sid}/viewer")
    e = r.json()["error"]
    assert r.status_code == 503 and e["code"] == "viewer_not_installed" and "npm ci" in e["message"]
    assert client.get("/viewer/modules/three/build/three.module.js").status_code == 404


def test_a_drive_gives_its_trajectory_in_the_scenes_frame(tmp_path):
    from xyzcyl.runtime.scene import Scene
    from xyzcyl.server.viewer import scene_data
    from xyzcyl.testing.drives import pose

    E0 = np.array(pose(50.0, 20.0, 90.0))                # the first frame's ego -> world
    drive = {"frames": 2, "keyframes": [0], "timestamp_s": 100.0, "times_s": [0.0, 0.4], "ego_to_world": E0.tolist(),
             "trajectory": [pose(0.0, 0.0, 0.0), pose(3.0, 1.0, 10.0)], "tracks": 0}
    d = scene_data(Scene.load(_ground_scene(tmp_path / "drive", drive=drive)))
    np.testing.assert_allclose(d["trajectory"], [[0, 0, 0], [3, 1, 0]], atol=1e-9)
    assert d["times"] == [100.0, 100.4] and d["time"]["start"] == 100.0 and d["time"]["end"] == 100.4
    assert d["actors"] is False


def test_view_refuses_what_is_not_a_scene(tmp_path, capsys):
    from xyzcyl.cli import main

    assert main(["view", str(tmp_path)]) == 2
    assert "is not a scene folder (no scene.json there)" in capsys.readouterr().err
    scene = _ground_scene(tmp_path / "scene")
    assert main(["view", str(scene), "--camera", "CAM_NOPE"]) == 2
    assert "--camera: no camera 'CAM_NOPE' in the scene's rig (cameras: CAM_FRONT," in capsys.readouterr().err
    assert main(["view", str(scene), "--port", "70000"]) == 2
    assert "--port: 70000 is not a TCP port" in capsys.readouterr().err
