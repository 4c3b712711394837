"""`xyzcyl serve` as a real subprocess on a free loopback port (issue 12, Tests): post the example rig, render a
view, stop the server with SIGTERM (exit status 0), start it again on the same store and render the same view:
the scene is served again and the PNG is byte-identical."""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

httpx = pytest.importorskip("httpx")

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "synth_nuscenes"
XYZCYL = Path(sys.executable).parent / "xyzcyl"
READY_S = 60.0
STOP_S = 30.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """A running `xyzcyl serve`; ``log`` is the file its stdout and stderr go to."""

    def __init__(self, store: Path, log: Path, out):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = log
        self.proc = subprocess.Popen([str(XYZCYL), "serve", "--host", "127.0.0.1", "--port", str(self.port),
                                      "--store", str(store)], stdout=out, stderr=subprocess.STDOUT, cwd=REPO)

    def output(self) -> str:
        return self.log.read_text(errors="replace")[-8000:]

    def wait_ready(self, timeout: float = READY_S) -> float:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if self.proc.poll() is not None:
                raise AssertionError(f"xyzcyl serve exited with {self.proc.returncode}:\n{self.output()}")
            try:
                if httpx.get(self.url + "/v2/health/ready", timeout=2.0).status_code == 200:
                    return time.monotonic() - t0
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"/v2/health/ready not 200 within {timeout} s:\n{self.output()}")

    def stop(self, timeout: float = STOP_S) -> None:
        """SIGTERM; the server must drain and exit with status 0 within ``timeout`` seconds."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"xyzcyl serve did not exit within {timeout} s of SIGTERM:\n{self.output()}")
        assert rc == 0, f"xyzcyl serve exited with status {rc} after SIGTERM (0 expected):\n{self.output()}"

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


@contextlib.contextmanager
def serve(store: Path, log: Path):
    with open(log, "ab") as out:
        server = Server(store, log, out)
        try:
            yield server
        finally:
            server.kill()


def rig_files() -> list:
    rig = json.loads((EXAMPLE / "rig.json").read_text())
    files = [("rig", ("rig.json", json.dumps(rig).encode(), "application/json"))]
    for cam in rig["cameras"]:
        files.append((cam["name"], (Path(cam["image"]).name, (EXAMPLE / cam["image"]).read_bytes(), "image/png")))
    return files


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


def test_print_settings_shows_the_resolved_model(tmp_path, monkeypatch, capsys):
    """--print-settings names the model folder the server would load, not `null` (issue 27, defect 7): the shipped
    one by default, $XYZCYL_MODEL or --model (absolute) when given."""
    pytest.importorskip("pydantic_settings")
    from xyzcyl.clients import cli
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
