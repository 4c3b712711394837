"""The health router (server/routes/health.py): readiness (503 until the model is loaded), liveness, server and
model metadata (Open Inference Protocol), the OpenAPI document, Prometheus metrics. The app and its scene are
tests/server/conftest.py's ``env``; readiness before the model loads also on a "cold" app (no lifespan)."""

from __future__ import annotations

from api_helpers import BODY_LIMIT, MODEL_NAME, cold_client, err, url
from fastapi.testclient import TestClient
from xyzcyl.testing.rigs import rig_files

# ----------------------------------------------------------------------------------------------- readiness


def test_ready_is_503_until_the_model_is_loaded(env, tmp_path):
    r = env.first_ready                      # asked right after startup, while the worker loads the model
    assert r.status_code == 503 and r.headers["retry-after"] == "1"
    assert r.json() == {"ready": False, "reason": "loading the model"}
    assert env.client.get("/v2/health/ready").json()["ready"] is True

    cold = cold_client(tmp_path)
    assert cold.get("/v2/health/live").status_code == 200
    r = cold.get("/v2/health/ready")
    assert r.status_code == 503 and r.json()["ready"] is False
    r = cold.get(f"/v2/models/{MODEL_NAME}/ready")
    assert r.status_code == 503 and r.json() == {"name": MODEL_NAME, "ready": False}
    r = cold.post("/v1/scenes", files=rig_files())
    err(r, 503, None, "busy")
    assert r.headers["retry-after"] == "1"


# ----------------------------------------------------------------------------------------------- health, metadata


def test_health_and_model_metadata(client, env):
    assert client.get("/v2/health/live").json() == {"live": True}
    assert client.get("/v2/health/ready").json()["ready"] is True
    from xyzcyl.server import __version__

    assert client.get("/v2").json() == {"name": "xyzcyl", "version": __version__, "extensions": []}
    meta = client.get(f"/v2/models/{MODEL_NAME}").json()
    assert meta["name"] == MODEL_NAME and meta["versions"] == [env.service.info.version]
    assert meta["platform"] == "onnxruntime_onnx" and meta["inputs"] and meta["outputs"]
    assert all({"name", "datatype", "shape"} <= set(t) for t in meta["inputs"] + meta["outputs"])
    assert client.get(f"/v2/models/{MODEL_NAME}/ready").json() == {"name": MODEL_NAME, "ready": True}
    err(client.get("/v2/models/resnet50"), 404, "name", "not_found")
    err(client.get("/v2/models/resnet50/ready"), 404, "name", "not_found")
    err(client.get("/v3/nothing"), 404, None, "not_found")
    err(client.put("/v2/health/live"), 405, None, "method_not_allowed")
    doc = client.get("/openapi.json").json()
    assert {"/v1/scenes", "/v1/scenes/{scene_id}", "/v1/scenes/{scene_id}/gaussians",
            "/v1/scenes/{scene_id}/background", "/v1/scenes/{scene_id}/render", "/v2/health/live",
            "/v2/health/ready", "/v2", "/v2/models/{name}", "/metrics"} <= set(doc["paths"])


def _scrape(client: TestClient):
    """GET /metrics parsed: value(name, **labels) sums the samples whose labels match."""
    from prometheus_client.parser import text_string_to_metric_families

    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    samples: dict = {}
    for fam in text_string_to_metric_families(r.text):
        for s in fam.samples:
            samples.setdefault(s.name, []).append((s.labels, s.value))

    def value(name: str, **labels) -> float:
        return sum(v for lab, v in samples.get(name, []) if all(lab.get(k) == x for k, x in labels.items()))

    return value, r.text


def test_metrics(client, env):
    route = "/v1/scenes/{scene_id}/render"
    req = "xyzcyl_http_requests_total"
    before, _ = _scrape(client)
    assert client.get(url(env, "/render?camera=CAM_BACK_RIGHT&width=72")).status_code == 200
    assert client.get(url(env, "/render?camera=CAM_BACK_RIGHT&width=72")).status_code == 200     # cached
    assert client.get(url(env, "/render?camera=NOPE")).status_code == 422
    assert client.get("/no/such/route").status_code == 404
    assert client.post("/v1/scenes", content=b"x" * (BODY_LIMIT + 1),
                       headers={"content-type": "multipart/form-data; boundary=x"}).status_code == 413
    after, text = _scrape(client)

    def delta(name, **labels):
        return after(name, **labels) - before(name, **labels)

    assert delta(req, route=route, method="GET", status="200") == 2
    assert delta(req, route=route, method="GET", status="422") == 1
    assert delta(req, route="unmatched", method="GET", status="404") == 1
    # a 413 from Content-Length is answered before routing, so it counts under "unmatched"
    assert delta(req, method="POST", status="413") == 1
    assert delta("xyzcyl_http_request_duration_seconds_count", route=route, method="GET") == 3
    assert delta("xyzcyl_render_duration_seconds_count") == 1
    assert delta("xyzcyl_render_cache_total", result="miss") == 1
    assert delta("xyzcyl_render_cache_total", result="hit") == 1
    assert after(req, route="/v1/scenes", method="POST", status="201") >= 1        # the module's scene
    assert after("xyzcyl_reconstructions_total", outcome="ready") >= 1
    assert after("xyzcyl_reconstruction_duration_seconds_count") >= 1
    assert env.sid not in text                                   # route templates, never ids
    usage = env.service.store.usage()
    for state in ("queued", "running", "ready", "failed"):
        assert after("xyzcyl_scenes", state=state) == usage["scenes"][state]
    assert usage["scenes"]["ready"] >= 1
    assert after("xyzcyl_store_bytes") == usage["bytes"] > 0
    assert after("xyzcyl_queue_depth", queue="render") == 0 and after("xyzcyl_queue_depth", queue="reconstruct") == 0
