"""`xyzcyl client` end to end against a real `xyzcyl serve` subprocess on a free loopback port (issue 13, Tests):
reconstruct the example rig (the console script, as a user runs it), render a view to PNG, download the Gaussians
as PLY, render a camera path to a folder, and the error line of an unknown scene. The other calls run the CLI's
main() in process (same code, no interpreter start-up)."""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from xyzcyl.testing import EXAMPLE, REPO
from xyzcyl.testing.serve import XYZCYL, serve

httpx = pytest.importorskip("httpx")
pytest.importorskip("uvicorn")

READY_S = 60.0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    assert XYZCYL.is_file(), f"{XYZCYL} not installed (pip install -e .)"
    tmp = tmp_path_factory.mktemp("serve")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with serve(tmp / "store", tmp / "serve.log", ["--ort-threads", "1"], ready_s=READY_S, env=env, cwd=tmp) as s:
        yield s.url


def xyzcyl(*args: str, capsys) -> tuple[int, str, str]:
    from xyzcyl import cli

    capsys.readouterr()
    rc = cli.main(list(args))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.slow
def test_cli_reconstruct_render_gaussians_path(server, tmp_path, capsys, monkeypatch):
    env = {**os.environ, "XYZCYL_SERVER": server}
    env.pop("XYZCYL_API_KEY", None)
    done = subprocess.run([str(XYZCYL), "client", "reconstruct", str(EXAMPLE / "rig.json"), "--wait", "120"],
                          check=False, capture_output=True, text=True, env=env, timeout=180)
    assert done.returncode == 0, done.stderr
    sid = done.stdout.strip()
    assert len(sid) == 22, done.stdout
    assert f"scene {sid} ready" in done.stderr

    monkeypatch.setenv("XYZCYL_SERVER", server)
    monkeypatch.delenv("XYZCYL_API_KEY", raising=False)
    rc, out, err = xyzcyl("client", "render", sid, "--camera", "CAM_FRONT", "--width", "400", "--out",
                          str(tmp_path / "front.png"), capsys=capsys)
    assert rc == 0, err
    import cv2

    front = cv2.imread(str(tmp_path / "front.png"))
    assert front.shape == (225, 400, 3) and front.std() > 5

    rc, _, err = xyzcyl("client", "render", sid, "--carla", "5", "0", "1.6", "0", "0", "0", "--fov", "90",
                        "--width", "320", "--height", "240", "--output", "depth", "--out",
                        str(tmp_path / "ahead.exr"), "--quiet", "--server", server, capsys=capsys)
    assert rc == 0 and err == ""
    assert (tmp_path / "ahead.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"

    rc, _, err = xyzcyl("client", "gaussians", sid, "--out", str(tmp_path / "scene.ply"), "-q", capsys=capsys)
    assert rc == 0, err
    ply = (tmp_path / "scene.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0\n")

    cam = json.loads((EXAMPLE / "rig.json").read_text())["cameras"][0]
    cameras = [{"fov": 80.0, "cam_to_ego": cam["cam_to_ego"], "width": 160, "height": 90},
               {"camera": "CAM_BACK", "width": 160}]
    (tmp_path / "cams.json").write_text(json.dumps({"cameras": cameras, "fps": 5}))
    rc, _, err = xyzcyl("client", "path", sid, str(tmp_path / "cams.json"), "--out", str(tmp_path / "frames"),
                        "--format", "jpeg", "--video", str(tmp_path / "path.mp4"), capsys=capsys)
    assert rc == 0, err
    video = cv2.VideoCapture(str(tmp_path / "path.mp4"))
    assert (video.get(cv2.CAP_PROP_FRAME_COUNT), video.get(cv2.CAP_PROP_FPS)) == (2, 5)     # the file's fps
    video.release()
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_00000.jpg", "frame_00001.jpg",
                                                                      "index.json"]
    index = json.loads((tmp_path / "frames" / "index.json").read_text())
    assert [f["width"] for f in index["frames"]] == [160, 160] and index["format"] == "jpeg"

    rc, out, err = xyzcyl("client", "scenes", capsys=capsys)
    assert rc == 0 and out.startswith(sid)
    n = len(out.splitlines())
    assert err.strip().splitlines()[-1] == (f"{n} scene" if n == 1 else f"{n} scenes")   # stderr: the count

    rc, out, err = xyzcyl("client", "render", "AAAAAAAAAAAAAAAAAAAAAA", "--camera", "CAM_FRONT", "--out",
                          str(tmp_path / "x.png"), capsys=capsys)
    assert rc == 2 and out == ""
    assert err.strip() == "xyzcyl client: id: no scene 'AAAAAAAAAAAAAAAAAAAAAA' [404 not_found]"
    assert "Traceback" not in err and not (tmp_path / "x.png").exists()

    rc, _, err = xyzcyl("client", "delete", sid, capsys=capsys)
    assert rc == 0, err
    rc, _, err = xyzcyl("client", "scene", sid, capsys=capsys)
    assert rc == 2 and "[404 not_found]" in err


@pytest.mark.parametrize("flags,named", [(["--detail-stride", "0"], ["--detail-stride", "1..16"]),
                                         (["--detail-stride", "17"], ["--detail-stride", "1..16"]),
                                         (["--no-detail", "--detail-stride", "4"], ["--no-detail", "--detail-stride"])])
def test_client_reconstruct_detail_flags_refused_before_connecting(flags, named, capsys):
    """Port 9 (discard) is not listening: a request would answer with a connection error, not with the flag."""
    rc, out, err = xyzcyl("client", "reconstruct", str(EXAMPLE / "rig.json"), "--server", "http://127.0.0.1:9",
                          *flags, capsys=capsys)
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert err.startswith("xyzcyl client: ") and all(n in err for n in named) and "connection" not in err, err


def test_client_reconstruct_passes_the_detail_flags(monkeypatch, capsys):
    from xyzcyl.clients.client import Client, SceneInfo

    calls = []

    def fake(self, rig, **kw):
        calls.append(kw)
        stride = kw["detail_stride"] if kw["detail"] else None
        return SceneInfo.from_json({"id": "s" * 22, "state": "ready", "gaussians": 10, "counts": {"detail": 7},
                                    "detail": {"enabled": kw["detail"], "stride": stride}, "timings": {"total": 1.0},
                                    "created": "2026-01-01T00:00:00+00:00", "updated": "2026-01-01T00:00:01+00:00",
                                    "cameras": [], "links": {}})

    monkeypatch.setattr(Client, "reconstruct", fake)
    rig = str(EXAMPLE / "rig.json")
    rc, out, err = xyzcyl("client", "reconstruct", rig, "--detail-stride", "4", "--wait", capsys=capsys)
    assert rc == 0 and out.strip() == "s" * 22 and "10 Gaussians (7 detail, stride 4)" in err, err
    assert xyzcyl("client", "reconstruct", rig, "--no-detail", capsys=capsys)[0] == 0
    assert xyzcyl("client", "reconstruct", rig, capsys=capsys)[0] == 0
    assert [(k["detail_stride"], k["detail"]) for k in calls] == [(4, True), (None, False), (None, True)]


def _example(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"example_{name}", REPO / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("name", ["carla_trajectory", "nerfstudio_camera_path"])
def test_examples_have_help(name, capsys):
    with pytest.raises(SystemExit) as e:
        _example(name).main(["--help"])
    assert e.value.code == 0 and "--server" in capsys.readouterr().out


def test_nerfstudio_example_poses_are_the_runtime_convention():
    import numpy as np
    from xyzcyl.runtime.convert import cameras_from_nerfstudio_path
    from xyzcyl.runtime.rig import look_rotation

    ns = _example("nerfstudio_camera_path")
    doc = ns.camera_path(ns.dolly(10.0, 1.6, 3), 80, 45, 50.0, 12.0)
    for k, cam in enumerate(cameras_from_nerfstudio_path(doc)):      # the server's reader of the file
        expected = look_rotation(0.0, -np.arctan2(0.4, 10.0))         # ego forward, 0.4 m down over 10 m
        np.testing.assert_allclose(cam.rotation, expected, atol=1e-12)
        np.testing.assert_allclose(cam.position, [5.0 * k, 0.0, 1.6], atol=1e-12)
