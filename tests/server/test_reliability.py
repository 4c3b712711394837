"""Reliability and security of the service (issue 14): the fast subset of benchmarks/reliability.py that runs in CI
(docs/reliability.md has the long runs and their figures). Most tests talk to a real `xyzcyl serve` subprocess on
a free loopback port over raw sockets where the client library would hide what is measured (bytes the server read,
connections it closed, temporary files it left). What tests/server/test_api.py covers in-process (every status
of every endpoint) is not repeated here."""

from __future__ import annotations

import errno
import json
import sys
import time
from pathlib import Path

import pytest

httpx = pytest.importorskip("httpx")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import reliability as R  # noqa: E402  (benchmarks/reliability.py: the same helpers as the long runs)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory) -> R.Ctx:
    """The example rig as JPEG parts, distinct render poses, a work folder for stores and the server log."""
    return R.Ctx(tmp_path_factory.mktemp("reliability"), quick=True)


def show_log(ctx: R.Ctx) -> str:
    return ctx.log.read_text(errors="replace")[-6000:] if ctx.log.is_file() else ""


# ----------------------------------------------------------------------------------------------- in process


@pytest.mark.slow
def test_a_store_that_cannot_write_does_not_stop_the_reconstruction_queue(tmp_path):
    """Regression: when the store could not write a record (a full disk) while a job failed, the exception escaped
    the queue's consumer task, which died: every later job stayed `queued` forever."""
    from fastapi.testclient import TestClient
    from xyzcyl.server import Settings, create_app

    ctx = R.Ctx(tmp_path, quick=True)
    app = create_app(Settings(store=str(tmp_path / "store"), ort_threads=1, render_threads=1))
    with TestClient(app) as c:
        deadline = time.monotonic() + 120
        while c.get("/v2/health/ready").status_code != 200:
            assert time.monotonic() < deadline, "not ready in 120 s"
            time.sleep(0.1)
        store = app.state.service.store

        def disk_full(*args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device")

        store.update, store.fail = disk_full, disk_full      # nothing can be written: not `running`, not `failed`
        try:
            r = c.post("/v1/scenes", params={"wait": 20}, files=ctx.files)
            assert r.status_code in (202, 500, 507), r.text
        finally:
            del store.update, store.fail                       # the disk has room again
        r = c.post("/v1/scenes", params={"wait": 60}, files=ctx.files)
        assert r.status_code == 201, f"the queue stopped after a failed record write: {r.status_code} {r.text[:300]}"
        assert r.json()["state"] == "ready"


# ----------------------------------------------------------------------------------------------- crashes


@pytest.mark.slow
def test_worker_kill_and_server_kill9_then_restart(ctx):
    """A reconstruction worker killed mid-job (kill -9 of the pid found under the server in /proc): that job is
    `failed` (`worker_crashed`) and the API stays live. Then the server itself is killed (kill -9) while a job runs:
    its worker processes exit on their own (regression: they were orphaned and held the model's memory forever),
    and after a restart on the same store the running job is `failed` (`interrupted`), no folder is half-visible,
    tmp/ is empty, and a new post reconstructs."""
    import os
    import signal

    store = ctx.store("kill")
    flags = ["--reconstruct-workers", "1", "--reconstruct-queue", "2", "--ort-threads", "1", "--render-threads", "1"]
    try:
        with ctx.serve(store, flags) as (proc, url, _), R.client(url) as c:
            crashed = c.post("/v1/scenes", files=ctx.files).json()["id"]
            assert R.wait_state(c, crashed, ("running",), 60, 0.02), "the job never ran"
            victims = R.worker_pids(proc.pid)
            assert len(victims) == 1, [R.cmdline(p) for p in R.children(proc.pid)]
            R.kill_all(victims)
            rec = R.wait_state(c, crashed, ("failed", "ready"), 60, 0.02)
            assert rec and rec["state"] == "failed" and rec["error"]["code"] == "worker_crashed", rec
            assert c.get("/v2/health/live").status_code == 200

            running = c.post("/v1/scenes", files=ctx.files).json()["id"]
            assert R.wait_state(c, running, ("running",), 120, 0.02), "the job never ran on the new worker"
            kids = R.children(proc.pid)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
            deadline = time.monotonic() + 5
            while any(R.alive(p) for p in kids) and time.monotonic() < deadline:
                time.sleep(0.1)
            left = [R.cmdline(p) for p in kids if R.alive(p)]
            R.kill_all(p for p in kids if R.alive(p))
            assert not left, f"processes of the killed server still alive after 5 s: {left}"

        with ctx.serve(store, flags) as (proc, url, _), R.client(url) as c:
            report = R.check_store(url, store, [running])
            assert report["problems"] == [], report
            assert report["posted"] == {running: "failed"}
            recs = {r["id"]: r for r in R.all_records(c)}
            assert recs[running]["error"]["code"] == "interrupted"
            assert recs[crashed]["error"]["code"] == "worker_crashed"
            r = c.post("/v1/scenes", params={"wait": 120}, files=ctx.files)
            assert r.status_code == 201, r.text
            assert c.get(f"/v1/scenes/{r.json()['id']}/render", params={"camera": "CAM_FRONT", "width": 160,
                                                                         "format": "jpeg"}).status_code == 200
    except BaseException:
        sys.stderr.write(show_log(ctx))
        raise


# ----------------------------------------------------------------------------------------------- one guarded server

KEY = "ci-reliability-key-0123456789"
AUTH = {"Authorization": f"Bearer {KEY}"}
LIMIT = 8 << 20                 # the noise rig of the disconnect test (~6.5 MB) fits under it


@pytest.fixture(scope="module")
def guarded(ctx):
    """One `xyzcyl serve` with API keys and an 8 MiB body limit, and a ready scene."""
    import types

    store = ctx.store("guarded")
    flags = ["--api-keys", KEY, "--max-body-bytes", str(LIMIT), "--ort-threads", "1", "--render-threads", "1"]
    try:
        with ctx.serve(store, flags) as (proc, url, _):
            with R.client(url, 120, AUTH) as c:
                sid = R.new_scene(c, ctx)["id"]
            yield types.SimpleNamespace(url=url, pid=proc.pid, port=R.port_of(url), store=store, sid=sid)
    except BaseException:
        sys.stderr.write(show_log(ctx))
        raise


@pytest.mark.slow
def test_client_disconnect_mid_upload_leaves_no_files(ctx, guarded):
    """A client that sends part of a multipart upload and closes: the upload folder under the store's tmp/ and the
    temporary files Starlette spooled the parts into (open, deleted, in /proc/PID/fd) are gone within 5 s; the
    request counts as 499, not as a server error (regression: 500 and a logged traceback)."""
    body, boundary = R.noise_rig(ctx)
    assert len(body) < LIMIT
    fd0 = len(R.fds(guarded.pid))
    log0 = ctx.log.stat().st_size
    for fraction in (0.3, 0.9):
        run = R.disconnect_upload(guarded.port, guarded.pid, guarded.store, body, boundary, fraction, AUTH)
        assert run["during"]["tmp"] >= 1 and run["during"]["deleted_fds"] >= 1, run     # the upload was under way
        assert run["after"] == {"tmp": 0, "deleted_fds": 0}, run
    assert len(R.fds(guarded.pid)) <= fd0 + 1
    with R.client(guarded.url, 60, AUTH) as c:
        m = c.get("/metrics").text
    posts = {line.split("status=")[1].split('"')[1]: float(line.rsplit(" ", 1)[1]) for line in m.splitlines()
             if line.startswith("xyzcyl_http_requests_total{") and 'method="POST"' in line and "/v1/scenes\"" in line}
    assert posts.get("499") == 2 and "500" not in posts, posts
    with open(ctx.log, "rb") as f:
        f.seek(log0)
        assert b"Traceback" not in f.read()
