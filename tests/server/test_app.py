"""What create_app (server/app.py, server/security.py) puts around every route: API keys (on every /v1 route, off by
default), CORS (off by default), no `server` header on any response. "Cold" apps (no lifespan, no worker
processes) where the dependencies and the middleware are all that is tested; the server-header check also looks at
every response of tests/server/conftest.py's ``env``."""

from __future__ import annotations

from api_helpers import MODEL_NAME, cold_client, err, url
from fastapi.testclient import TestClient

# ----------------------------------------------------------------------------------------------- API keys, CORS


def _v1_routes(client: TestClient) -> list[tuple[str, str]]:
    paths = client.app.openapi()["paths"]          # from the app: with API keys /openapi.json is not served
    return [(m.upper(), p.replace("{scene_id}", "AAAAAAAAAAAAAAAAAAAAAA"))
            for p, ops in paths.items() if p.startswith("/v1") for m in ops]


def test_api_keys(tmp_path):
    key = "secret-key-1"
    client = cold_client(tmp_path, api_keys=(key, "another-key-2"))
    routes = _v1_routes(client)
    assert len(routes) == 12
    for method, path in routes:
        for headers in ({}, {"Authorization": "Bearer wrong-key-99"}, {"X-API-Key": "secret-key-"},
                        {"Authorization": f"Basic {key}"}, {"Authorization": "Bearer "},
                        {"X-API-Key": key + "x"}):
            r = client.request(method, path, headers=headers)
            err(r, 401, None, "unauthorized")
            assert r.headers["www-authenticate"] == "Bearer"
            assert key not in r.text
    for headers in ({"Authorization": f"Bearer {key}"}, {"authorization": f"bearer {key}"},
                    {"X-API-Key": key}, {"X-API-Key": "another-key-2"}):
        r = client.get("/v1/scenes", headers=headers)
        assert r.status_code == 200 and r.json()["total"] == 0
        err(client.get("/v1/scenes/AAAAAAAAAAAAAAAAAAAAAA", headers=headers), 404, "id")
        err(client.delete("/v1/scenes/AAAAAAAAAAAAAAAAAAAAAA", headers=headers), 404, "id")
    for path in ("/v2/health/live", "/v2", f"/v2/models/{MODEL_NAME}", "/metrics"):
        assert client.get(path).status_code == 200, path
    assert client.get("/v2/health/ready").status_code == 503          # open (not 401); the model is not loaded


def test_api_keys_are_off_by_default(client):
    assert client.get("/v1/scenes").status_code == 200


def test_cors_off_by_default(client, env):
    r = client.get("/v2/health/live", headers={"Origin": "https://example.org"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
    r = client.options("/v1/scenes", headers={"Origin": "https://example.org", "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in r.headers


def test_cors_when_configured(tmp_path):
    client = cold_client(tmp_path, cors_origins=("https://example.org",))
    r = client.get("/v1/scenes", headers={"Origin": "https://example.org"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://example.org"
    assert "etag" in r.headers["access-control-expose-headers"].lower()
    r = client.options("/v1/scenes", headers={"Origin": "https://example.org", "Access-Control-Request-Method": "POST",
                                              "Access-Control-Request-Headers": "x-api-key"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://example.org"
    r = client.get("/v1/scenes", headers={"Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in r.headers
    r = client.options("/v1/scenes", headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "POST"})
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers


# ----------------------------------------------------------------------------------------------- server header


def test_no_server_header(env, tmp_path):
    for path in ("/v2/health/live", "/metrics", url(env), url(env, "/render?camera=CAM_FRONT&width=64"),
                 "/nowhere", url(env, "/render?camera=NOPE")):
        env.client.get(path)
    assert len(env.responses) > 8
    leaks = [(str(r.request.url), r.headers["server"]) for r in env.responses if "server" in r.headers]
    assert leaks == []
    # a response that does carry one (as a framework or a handler might add it) loses it in the middleware
    from fastapi.responses import Response

    cold = cold_client(tmp_path)
    cold.app.add_api_route("/leaky", lambda: Response(b"x", headers={"Server": "leaky/1.0"}))
    r = cold.get("/leaky")
    assert r.status_code == 200 and r.content == b"x" and "server" not in r.headers
