"""Helpers of the server tests that run the app in process (test_scenes, test_render, test_health, test_app; the
fixtures are in conftest.py): the one error body, the app's own metrics, "cold" apps without their lifespan.
Rigs and multipart bodies come from xyzcyl.testing.rigs."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
from fastapi.testclient import TestClient

MODEL_NAME = "xyzcyl-cpu-v1"
BODY_LIMIT = 2 << 20            # the example rig's upload is ~0.95 MB


def decode(data: bytes, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    assert img is not None, "not a decodable image"
    return img


def read_exr_bytes(data: bytes, tmp_path: Path) -> np.ndarray:
    from xyzcyl.runtime.imageio import read_exr

    assert data[:4] == b"\x76\x2f\x31\x01", "not an OpenEXR file"
    p = tmp_path / f"x{len(data)}.exr"
    p.write_bytes(data)
    return read_exr(p)


def err(r: httpx.Response, status: int, field: str | None = "<any>", code: str | None = None) -> dict:
    """Assert the status and the one error body; return the error object."""
    assert r.status_code == status, (r.status_code, r.text[:400])
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message", "field"}, body
    e = body["error"]
    assert isinstance(e["message"], str) and e["message"]
    if field != "<any>":
        assert e["field"] == field, e
    if code is not None:
        assert e["code"] == code, e
    return e


def wait_ready(client: TestClient, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while client.get("/v2/health/ready").status_code != 200:
        assert time.monotonic() - t0 < timeout, "the service never became ready"
        time.sleep(0.1)


def cold_client(tmp_path: Path, **kw) -> TestClient:
    """An app whose lifespan does not run (no worker processes; the model counts as not loaded yet)."""
    from xyzcyl.server import Settings, create_app

    return TestClient(create_app(Settings(store=str(tmp_path / "cold-store"), **kw)))


@dataclass
class Env:
    app: Any
    client: TestClient
    service: Any
    store_root: Path
    first_ready: httpx.Response
    created: httpx.Response
    sid: str
    responses: list = field(default_factory=list)


def metric(env: Env, name: str, **labels) -> float:
    """A sample of the app's own Prometheus registry (0 when it has not been recorded yet)."""
    return env.service.metrics.registry.get_sample_value(name, labels) or 0.0


def url(env: Env, tail: str = "") -> str:
    return f"/v1/scenes/{env.sid}{tail}"
