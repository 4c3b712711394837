"""A warm-up render that fails keeps the service not ready, loudly (issue 35 item 1: the warm-up logged a traceback
for the f-theta render's IndexError and reported ready anyway, over a renderer that failed on a lens model).
In process: the render warm-up is made to fail; the app never answers ready, its reason names the failure, the
log says so at ERROR, and no reconstruction worker is started."""

from __future__ import annotations

import logging
import time

import pytest
from fastapi.testclient import TestClient
from xyzcyl.server import Settings, create_app, service


@pytest.mark.parametrize("which", ["pinhole", "lenses"])
def test_a_failing_warm_up_render_is_not_ready(tmp_path, monkeypatch, caplog, which):
    calls = []

    def warm(models: str) -> float:
        calls.append(models)
        if models == which:
            raise IndexError("index 2340 is out of bounds for axis 0 with size 2340")
        return 0.0

    monkeypatch.setattr(service, "_warm_renders", warm)
    monkeypatch.setattr(service.Service, "_compile_lenses", _no_child)        # no lens compile process here
    started = []
    monkeypatch.setattr(service.Reconstructions, "start", lambda self: _started(started))
    caplog.set_level(logging.ERROR, logger="xyzcyl")
    with TestClient(create_app(Settings(store=str(tmp_path / "store"), warm_up=True))) as client:
        t0 = time.monotonic()
        while len(calls) < (1 if which == "pinhole" else 2) and time.monotonic() - t0 < 30:   # bounded
            time.sleep(0.05)
        time.sleep(0.2)
        r = client.get("/v2/health/ready")
        assert r.status_code == 503, r.text
        assert "warm-up failed" in r.text and "IndexError" in r.text, r.text
    assert any("warm-up failed" in rec.getMessage() and rec.exc_info for rec in caplog.records)
    assert started == ([] if which == "pinhole" else [1])       # a failed pinhole warm-up starts no worker


async def _no_child(self) -> tuple[float, str]:
    return 0.0, "not run"


async def _started(started: list) -> float:
    started.append(1)
    return 0.0
