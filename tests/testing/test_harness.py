"""xyzcyl.testing's `xyzcyl serve` harness (testing/serve.py): a server on a free loopback port answers
/v2/health/ready, stops on SIGTERM with status 0, and leaves its port free; a server that cannot start is reported
at once with its log; the multipart builder's parts are what POST /v1/scenes takes."""

from __future__ import annotations

import socket
import time

import pytest
from xyzcyl.testing.serve import XYZCYL, ServeError, Server, free_port, serve

httpx = pytest.importorskip("httpx")
pytest.importorskip("uvicorn")


def _port_is_free(port: int) -> bool:
    """Nothing listens on 127.0.0.1:port and a new server could listen there (SO_REUSEADDR, as uvicorn binds)."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=2.0).close()
        return False
    except ConnectionRefusedError:
        pass
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            return False
    return True


def test_free_port_is_free():
    assert _port_is_free(free_port())


def test_serve_starts_answers_ready_stops_and_frees_its_port(tmp_path):
    assert XYZCYL.is_file(), f"{XYZCYL} not installed (pip install -e .)"
    with serve(tmp_path / "store", tmp_path / "serve.log", ["--ort-threads", "1"]) as server:
        assert server.url == f"http://127.0.0.1:{server.port}"
        assert server.ready_s is not None and server.ready_s > 0
        r = httpx.get(server.url + "/v2/health/ready", timeout=10.0)
        assert r.status_code == 200 and r.json()["ready"] is True
        assert not _port_is_free(server.port)
        assert server.stop() == 0
        assert server.stop_info["returncode"] == 0
    assert server.proc.poll() == 0
    assert _port_is_free(server.port)
    with pytest.raises(httpx.TransportError):
        httpx.get(server.url + "/v2/health/live", timeout=2.0)


def test_a_server_that_exits_is_reported_with_its_log(tmp_path):
    log = tmp_path / "serve.log"
    t0 = time.monotonic()
    with Server(tmp_path / "store", log, ["--no-such-flag"]) as server, \
            pytest.raises(ServeError, match="exited with 2") as e:
        server.wait_ready(60)
    assert time.monotonic() - t0 < 30                 # at the exit, not at the time-out
    assert "--no-such-flag" in str(e.value) and "--no-such-flag" in log.read_text()
    assert _port_is_free(server.port)


def test_leaving_the_block_kills_a_server_that_still_runs(tmp_path):
    with Server(tmp_path / "store", tmp_path / "serve.log") as server:
        assert server.proc.poll() is None
    assert server.proc.poll() is not None


def test_rig_files_are_the_example_rig_as_multipart_parts():
    from xyzcyl.testing.rigs import example_rig, multipart_body, rig_files

    rig = example_rig()
    parts = rig_files()
    assert [name for name, _ in parts] == ["rig"] + [c["name"] for c in rig["cameras"]]
    assert all(p[1][2] == "image/png" and p[1][1].startswith(b"\x89PNG") for p in parts[1:])
    body, ctype = multipart_body(parts)
    assert ctype.startswith("multipart/form-data; boundary=") and len(body) > sum(len(p[1][1]) for p in parts)
    assert [n for n, _ in rig_files(drop=("rig", "CAM_BACK"))] == [c["name"] for c in rig["cameras"]
                                                                   if c["name"] != "CAM_BACK"]
    swapped = dict(rig_files(images={"CAM_BACK": b"x"}))["CAM_BACK"]
    assert swapped == ("CAM_BACK.png", b"x", "image/png")
