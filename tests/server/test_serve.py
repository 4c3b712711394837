"""`xyzcyl serve` as a real subprocess on a free loopback port (issue 12, Tests): post the example rig, render a
view, stop the server with SIGTERM (exit status 0), start it again on the same store and render the same view:
the scene is served again and the PNG is byte-identical."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from xyzcyl.testing.rigs import rig_files
from xyzcyl.testing.serve import XYZCYL, serve

httpx = pytest.importorskip("httpx")


def render_front(client, sid: str) -> bytes:
    r = client.get(f"/v1/scenes/{sid}/render", params={"camera": "CAM_FRONT"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    assert "server" not in r.headers
    assert r.content.startswith(b"\x89PNG\r\n\x1a\n")
    return r.content


@pytest.mark.slow
def test_serve_subprocess_restart_same_bytes(tmp_path):
    assert XYZCYL.is_file(), f"{XYZCYL} not installed (pip install -e .)"
    store = tmp_path / "store"
    log = tmp_path / "serve.log"
    server = None
    try:
        with serve(store, log) as server:
            server.wait_ready()
            with httpx.Client(base_url=server.url, timeout=90.0) as c:
                r = c.get("/v2/health/live")
                assert r.status_code == 200 and "server" not in r.headers
                r = c.post("/v1/scenes", params={"wait": 60}, files=rig_files())
                assert r.status_code == 201, r.text
                assert "server" not in r.headers
                sid = r.json()["id"]
                assert r.json()["state"] == "ready"
                assert r.headers["location"] == f"/v1/scenes/{sid}"
                first = render_front(c, sid)
            server.stop()

        with serve(store, log) as server:
            server.wait_ready()
            with httpx.Client(base_url=server.url, timeout=90.0) as c:
                r = c.get(f"/v1/scenes/{sid}")
                assert r.status_code == 200, r.text
                assert r.json()["state"] == "ready"
                assert "server" not in r.headers
                again = render_front(c, sid)
            assert again == first
            server.stop()
    except BaseException:
        if log.is_file():
            sys.stderr.write(f"--- xyzcyl serve output ({log}) ---\n{log.read_text(errors='replace')[-8000:]}\n")
        raise


@pytest.mark.slow
def test_serve_under_numbas_workqueue_layer_renders_side_by_side_requests_one_at_a_time(tmp_path):
    """Where numba has only its workqueue layer (no libgomp, no TBB: a slim container), two renders whose kernels
    ran at once aborted the whole server ("Numba workqueue threading layer is terminating: Concurrent access has
    been detected"; eight renders at once against the tree before: no answer to any, the process gone). Now the
    render pool has one thread there, says so, and answers every request."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    log = tmp_path / "serve.log"
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue", "XYZCYL_RENDER_THREADS": "2"}
    try:
        with serve(tmp_path / "store", log, env=env) as server:
            server.wait_ready()
            with httpx.Client(base_url=server.url, timeout=120.0) as c:
                r = c.post("/v1/scenes", params={"wait": 90}, files=rig_files())
                assert r.status_code == 201, r.text
                sid = r.json()["id"]
                cams = ["CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT", "CAM_BACK_LEFT"] * 2

                def get(cam: str) -> int:
                    return c.get(f"/v1/scenes/{sid}/render", params={"camera": cam, "width": 800}).status_code

                with ThreadPoolExecutor(len(cams)) as pool:
                    assert list(pool.map(get, cams)) == [200] * len(cams)
            assert server.stop() == 0
        assert "render_threads 2 -> 1" in log.read_text()
    except BaseException:
        if log.is_file():
            sys.stderr.write(f"--- xyzcyl serve output ({log}) ---\n{log.read_text(errors='replace')[-8000:]}\n")
        raise


def test_print_settings_shows_the_resolved_model(tmp_path, monkeypatch, capsys):
    """--print-settings names the model folder the server would load, not `null` (issue 27, defect 7): the shipped
    one by default, $XYZCYL_MODEL or --model (absolute) when given."""
    pytest.importorskip("pydantic_settings")
    from xyzcyl import cli
    from xyzcyl.runtime.inference import default_model_dir

    monkeypatch.delenv("XYZCYL_MODEL", raising=False)

    def shown(*argv) -> dict:
        capsys.readouterr()
        assert cli.main(["serve", "--print-settings", *argv]) == 0
        return json.loads(capsys.readouterr().out)

    default = shown()["model"]
    assert default == str(default_model_dir().resolve()) and (Path(default) / "model.json").is_file()
    monkeypatch.chdir(tmp_path)
    assert shown("--model", "m")["model"] == str(tmp_path / "m")
    monkeypatch.setenv("XYZCYL_MODEL", str(tmp_path / "env"))
    assert shown()["model"] == str(tmp_path / "env")


def test_grpc_port_setting_is_typed_and_checked(monkeypatch, capsys):
    """--grpc-port (issue 29): off by default, an int, in 0..65535, not the HTTP port; refusals exit 2 naming
    the flag; --help says what it is."""
    pytest.importorskip("pydantic_settings")
    from xyzcyl import cli

    monkeypatch.delenv("XYZCYL_GRPC_PORT", raising=False)
    for argv, want in (((), None), (("--grpc-port", "50051"), 50051), (("--grpc-port", "0"), 0)):
        capsys.readouterr()
        assert cli.main(["serve", "--print-settings", *argv]) == 0
        assert json.loads(capsys.readouterr().out)["grpc_port"] == want
    for argv, words in ((("--grpc-port", "8000"), "is the HTTP port too"), (("--grpc-port", "70000"), "65535"),
                        (("--grpc-port", "x"), "integer")):
        capsys.readouterr()
        assert cli.main(["serve", "--print-settings", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("xyzcyl serve: --grpc-port: ") and words in err, err
    with pytest.raises(SystemExit):
        cli.main(["serve", "--help"])
    assert "SensorsimService" in capsys.readouterr().out
