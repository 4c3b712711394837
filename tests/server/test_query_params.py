"""Unknown query parameters are refused with 422 naming them (issue 27 defect 4: ``render?camera=CAM_FRONT&widht=1600``
answered 200 at the default width), on every route that declares query parameters; known ones pass. Apps without
their lifespan (no worker processes): the check runs before the endpoint, so no scene is needed."""

from __future__ import annotations

import pytest
from api_helpers import cold_client
from fastapi.testclient import TestClient

SID = "A" * 22
KEY = "query-test-key-1"


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> TestClient:
    return cold_client(tmp_path_factory.mktemp("query"))


def _error(r, status: int) -> dict:
    assert r.status_code == status, (r.status_code, r.text[:400])
    return r.json()["error"]


def test_a_typo_in_the_render_query_is_422_naming_it(client):
    e = _error(client.get(f"/v1/scenes/{SID}/render?camera=CAM_FRONT&widht=1600"), 422)
    assert e["code"] == "invalid" and e["field"] == "widht"
    assert e["message"].startswith("widht: unknown query parameter (GET /v1/scenes/{scene_id}/render takes ")
    assert "did you mean width?" in e["message"]
    # the same query without the typo passes the check (and finds no scene)
    assert _error(client.get(f"/v1/scenes/{SID}/render?camera=CAM_FRONT&width=1600"), 404)["field"] == "id"


def test_every_unknown_parameter_is_named(client):
    e = _error(client.get(f"/v1/scenes/{SID}/render?camera=X&widht=1&hieght=2&zzz=3&widht=4"), 422)
    assert e["field"] == "widht"
    assert e["message"].startswith("widht, hieght, zzz: unknown query parameters (")
    assert "did you mean width for widht, height for hieght?" in e["message"]


@pytest.mark.parametrize("method, path, query, field", [
    ("GET", "/v1/scenes", "limt=3", "limt"),
    ("GET", f"/v1/scenes/{SID}/gaussians", "fromat=splat", "fromat"),
    ("GET", f"/v1/scenes/{SID}/background", "format=exr&Format=png", "Format"),   # names are case-sensitive
    ("GET", f"/v1/scenes/{SID}/export", "format=usdz&fromat=usdz", "fromat"),
    ("POST", "/v1/scenes", "wiat=60", "wiat"),                                    # before the body is read
    ("POST", f"/v1/scenes/{SID}/render", "fromat=png", "fromat"),
])
def test_unknown_parameters_on_the_other_routes(client, method, path, query, field):
    assert _error(client.request(method, f"{path}?{query}"), 422)["field"] == field


def test_known_parameters_pass(client):
    r = client.get("/v1/scenes?offset=0&limit=3")
    assert r.status_code == 200 and r.json()["limit"] == 3
    assert _error(client.get(f"/v1/scenes/{SID}/gaussians?format=splat"), 404)["field"] == "id"
    # routes that declare no query parameter keep ignoring a query (a cache-busting ?_=1 changes nothing)
    assert client.get("/v2/health/live?_=1").status_code == 200
    assert _error(client.get(f"/v1/scenes/{SID}?_=1"), 404)["field"] == "id"


def test_every_route_with_query_parameters_refuses_unknown_ones(client):
    """Every operation of the OpenAPI document that has query parameters, so a route added later is covered too."""
    checked = []
    for path, ops in client.app.openapi()["paths"].items():
        for method, op in ops.items():
            if not any(p.get("in") == "query" for p in op.get("parameters", [])):
                continue
            target = path.replace("{scene_id}", SID).replace("{name}", "xyzcyl-cpu-v1")
            e = _error(client.request(method.upper(), f"{target}?no_such_parameter=1"), 422)
            assert e["field"] == "no_such_parameter", (method, path, e)
            checked.append(f"{method.upper()} {path}")
    assert len(checked) == 10, checked


def test_the_api_key_is_checked_first(tmp_path):
    client = cold_client(tmp_path, api_keys=(KEY,))
    assert _error(client.get(f"/v1/scenes/{SID}/render?widht=1"), 401)["code"] == "unauthorized"
    r = client.get(f"/v1/scenes/{SID}/render?widht=1", headers={"X-API-Key": KEY})
    assert _error(r, 422)["field"] == "widht"
