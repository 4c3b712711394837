"""Fixtures of the server tests that run the app in process (fastapi TestClient = httpx over ASGI, the lifespan
runs): ``env``, one app with a real reconstruction worker process and the example rig reconstructed once
(``env.sid``), and ``client``, its TestClient. Helpers are in api_helpers.py.

One app for the session, shared by test_scenes, test_render, test_health and test_app (its start-up and the first
reconstruction take ~20 s on 2 busy cores). Apps that only need the middleware or the dependencies (413, API keys,
CORS, readiness before the model loads) are built without running their lifespan (api_helpers.cold_client: no
worker processes). The app runs with render_threads=1, render_queue=0 and reconstruct_queue=0 so that the
backpressure tests can fill the queues deterministically; TestClient sends one request at a time, so the other
tests are unaffected. Each test leaves no job running behind it and deletes the scenes it made (a file that checks
counts compares with the count before it)."""

from __future__ import annotations

import pytest
from api_helpers import BODY_LIMIT, Env, wait_ready
from fastapi.testclient import TestClient
from xyzcyl.testing.rigs import rig_files


@pytest.fixture(scope="session")
def env(tmp_path_factory):
    from xyzcyl.server import Settings, create_app

    root = tmp_path_factory.mktemp("store")
    settings = Settings(store=str(root), max_body_bytes=BODY_LIMIT, render_threads=1, render_queue=0,
                        reconstruct_queue=0)
    app = create_app(settings)
    seen: list = []
    with TestClient(app) as client:
        client.event_hooks = {"request": [], "response": [seen.append]}
        first = client.get("/v2/health/ready")
        wait_ready(client)
        created = client.post("/v1/scenes?wait=60", files=rig_files())
        assert created.status_code == 201, created.text
        yield Env(app, client, app.state.service, root, first, created, created.json()["id"], seen)


@pytest.fixture
def client(env) -> TestClient:
    return env.client
