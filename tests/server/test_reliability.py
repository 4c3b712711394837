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
