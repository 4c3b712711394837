"""Issue 27 defect 7 (the service's part): /openapi.json, /docs and /redoc are off when API keys are set, unless the
``api_docs`` setting opens them (a browser sends no key, so they cannot sit behind one); and
``xyzcyl_store_evictions`` is a Prometheus counter (``..._total``), not a gauge. Apps without their lifespan."""

from __future__ import annotations

import pytest
from api_helpers import cold_client

KEY = "docs-test-key-1"
DOCS = ("/openapi.json", "/docs", "/redoc")


@pytest.mark.parametrize("keys, api_docs, served", [
    ((), None, True),             # default without keys: open
    ((KEY,), None, False),        # default with keys: off
    ((KEY,), True, True),         # opened on purpose
    ((), False, False),           # closed on purpose
])
def test_docs_follow_the_keys_and_the_setting(tmp_path, keys, api_docs, served):
    client = cold_client(tmp_path, api_keys=keys, api_docs=api_docs)
    for path in DOCS:
        for headers in ({}, {"X-API-Key": KEY}):
            r = client.get(path, headers=headers)
            assert r.status_code == (200 if served else 404), (path, headers, r.status_code)
    if served:
        assert "/v1/scenes" in client.get("/openapi.json").json()["paths"]
    else:
        assert client.get("/openapi.json").json()["error"]["code"] == "not_found"
    assert "/v1/scenes" in client.app.openapi()["paths"]      # the document itself still exists (tests, tooling)
    assert client.get("/v2/health/live").status_code == 200


def test_api_docs_from_the_environment(monkeypatch):
    from xyzcyl.server import Settings

    monkeypatch.setenv("XYZCYL_API_KEYS", KEY)
    assert Settings().docs_open() is False
    monkeypatch.setenv("XYZCYL_API_DOCS", "true")
    assert Settings().docs_open() is True


def test_store_evictions_is_a_counter(tmp_path):
    from prometheus_client.parser import text_string_to_metric_families

    client = cold_client(tmp_path)
    service = client.app.state.service
    service.store.open()
    service.store.evicted = 3
    families = {f.name: f for f in text_string_to_metric_families(client.get("/metrics").text)}
    fam = families["xyzcyl_store_evictions"]
    assert fam.type == "counter"
    assert [(s.name, s.value) for s in fam.samples] == [("xyzcyl_store_evictions_total", 3.0)]
    assert families["xyzcyl_store_bytes"].type == "gauge"
