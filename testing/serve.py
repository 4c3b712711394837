"""`xyzcyl serve` in a subprocess on 127.0.0.1 and a free port, for tests and benchmarks:

    with serve(store, log, ["--ort-threads", "1"]) as server:      # started and ready (or ServeError)
        httpx.get(server.url + "/v1/scenes")
        server.stop()                                               # SIGTERM; exit status 0 within 30 s

Every wait is bounded. The server's stdout and stderr go to ``log`` (appended); errors quote its end. Leaving the
block kills a server that still runs. The server inherits the environment unless ``env`` is given (the tests'
conftest sets XYZCYL_WARM_UP=false, so the servers they start skip the warm-up)."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Self

from xyzcyl.testing import checkout

HOST = "127.0.0.1"
XYZCYL = Path(sys.executable).parent / "xyzcyl"     # the console script of the running interpreter's install
READY_S = 60.0
STOP_S = 30.0


class ServeError(RuntimeError):
    """The server exited, did not become ready, or did not stop as asked (the message quotes its log)."""


def free_port(host: str = HOST) -> int:
    """A TCP port nothing listens on now (the kernel's pick; free until someone binds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Server:
    """A started `xyzcyl serve --host 127.0.0.1 --port <free port> --store STORE ARGS...` (not waited for: see
    ``wait_ready``), run in ``cwd`` (default: the source checkout, xyzcyl.testing.checkout, if there is one).
    ``proc`` is the process, ``url`` its base URL, ``ready_s`` the seconds from the start to ready (once
    ``wait_ready`` returned), ``stop_info`` how ``stop`` ended it."""

    def __init__(self, store: Path | str, log: Path, args: Sequence[str] = (), *,
                 env: Mapping[str, str] | None = None, cwd: Path | str | None = None):
        self.port = free_port()
        self.url = f"http://{HOST}:{self.port}"
        self.log = Path(log)
        self.argv = [str(XYZCYL), "serve", "--host", HOST, "--port", str(self.port), "--store", str(store), *args]
        self.ready_s: float | None = None
        self.stop_info: dict | None = None
        self.started = time.perf_counter()
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(self.argv, stdout=out, stderr=subprocess.STDOUT,
                                         cwd=cwd if cwd is not None else checkout(),
                                         env=None if env is None else dict(env))

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self, keep: int = 8000) -> str:
        """The end of the server's log."""
        return self.log.read_text(errors="replace")[-keep:] if self.log.is_file() else ""

    def wait_ready(self, timeout: float = READY_S, every: float = 0.2) -> float:
        """Poll /v2/health/ready until it answers 200 (the model is loaded); the seconds since the start. Raises
        ServeError when the process exits first or ``timeout`` seconds pass."""
        import httpx

        deadline = time.perf_counter() + timeout
        while True:
            if self.proc.poll() is not None:
                raise ServeError(f"xyzcyl serve exited with {self.proc.returncode}:\n{self.output()}")
            try:
                if httpx.get(self.url + "/v2/health/ready", timeout=2.0).status_code == 200:
                    self.ready_s = time.perf_counter() - self.started
                    return self.ready_s
            except httpx.TransportError:
                pass
            if time.perf_counter() > deadline:
                raise ServeError(f"/v2/health/ready not 200 within {timeout} s:\n{self.output()}")
            time.sleep(every)

    def stop(self, timeout: float = STOP_S, check: bool = True) -> int | None:
        """SIGTERM, then wait up to ``timeout`` seconds for the exit: its status (None if it did not exit; it runs
        on until ``kill``). ``check``: raise ServeError unless it exited with status 0 in time."""
        t0 = time.perf_counter()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.stop_info = {"returncode": None, "seconds": None,
                              "note": f"did not exit within {timeout:g} s of SIGTERM"}
            if check:
                raise ServeError(f"xyzcyl serve did not exit within {timeout} s of SIGTERM:\n{self.output()}")
            return None
        self.stop_info = {"returncode": rc, "seconds": round(time.perf_counter() - t0, 2)}
        if check and rc != 0:
            raise ServeError(f"xyzcyl serve exited with status {rc} after SIGTERM (0 expected):\n{self.output()}")
        return rc

    def kill(self) -> None:
        """SIGKILL if it still runs, and reap it."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.kill()


@contextlib.contextmanager
def serve(store: Path | str, log: Path, args: Sequence[str] = (), *, ready_s: float | None = READY_S,
          stop_s: float | None = None, env: Mapping[str, str] | None = None, cwd: Path | str | None = None,
          every: float = 0.2) -> Iterator[Server]:
    """A ``Server`` for the block: ready first (within ``ready_s`` seconds, polled every ``every``; None: not
    waited for); with
    ``stop_s``, stopped with SIGTERM when the block ends normally (not checked: ``stop_info`` says how it went);
    killed if it still runs after."""
    server = Server(store, log, args, env=env, cwd=cwd)
    try:
        if ready_s is not None:
            server.wait_ready(ready_s, every)
        yield server
        if stop_s is not None:
            server.stop(stop_s, check=False)
    finally:
        server.kill()
