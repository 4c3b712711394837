"""S3Store (server/store/s3.py) against moto's S3 server on loopback: records and files in the bucket, a second
replica that sees and downloads them, deletes (and a delete racing a commit), recovery of a restarted or dead
replica's jobs, the quota and the TTL; then two app instances sharing one bucket (a scene posted to one renders
from the other with the same bytes; deleted on one, 404 on the other)."""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from pathlib import Path

import pytest

boto3 = pytest.importorskip("boto3")
pytest.importorskip("moto")

from xyzcyl.server.store import StoreFull, new_scene_id
from xyzcyl.server.store import s3 as s3_mod
from xyzcyl.server.store.s3 import S3Store, parse_url

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "synth_nuscenes"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3_endpoint():
    """moto's S3 in server mode on 127.0.0.1 (a real HTTP endpoint, as MinIO would be), with the AWS environment
    pointing at it for the whole module."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    port = _free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    url = f"http://127.0.0.1:{port}"
    with pytest.MonkeyPatch.context() as mp:
        for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN"):
            mp.delenv(k, raising=False)
        mp.setenv("AWS_ACCESS_KEY_ID", "testing")
        mp.setenv("AWS_SECRET_ACCESS_KEY", "testing")
        mp.setenv("AWS_DEFAULT_REGION", "us-east-1")
        mp.setenv("AWS_ENDPOINT_URL", url)
        mp.setenv("AWS_CONFIG_FILE", "/nonexistent/aws-config")
        mp.setenv("AWS_SHARED_CREDENTIALS_FILE", "/nonexistent/aws-credentials")
        yield url
    server.stop()


@pytest.fixture
def bucket(s3_endpoint):
    """A fresh bucket per test."""
    name = f"xyzcyl-{new_scene_id().lower().replace('_', '0').replace('-', '0')[:16]}"
    client = boto3.client("s3")
    client.create_bucket(Bucket=name)
    return name


def keys(bucket: str, prefix: str = "") -> list[str]:
    out = []
    for page in boto3.client("s3").get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        out += [o["Key"] for o in page.get("Contents", [])]
    return sorted(out)


def make(bucket: str, tmp_path: Path, replica: str, prefix: str = "pfx", **kw) -> S3Store:
    st = S3Store(f"s3://{bucket}/{prefix}", cache_dir=tmp_path / f"cache-{replica}", replica_id=replica, **kw)
    st.open()
    return st


def scene_folder(store: S3Store, nbytes: int = 100) -> Path:
    d = store.work_dir() / "scene"
    d.mkdir()
    head = b'{"version": 1}'
    (d / "scene.json").write_bytes(head)
    (d / "scene.ply").write_bytes(b"x" * (nbytes - len(head)))
    return d


def ready_scene(store: S3Store, nbytes: int = 100) -> str:
    sid = new_scene_id()
    store.create(sid, {"cameras": []})
    store.update(sid, state="running")
    assert store.commit(sid, scene_folder(store, nbytes), gaussians=7).state == "ready"
    return sid


# ----------------------------------------------------------------------------------------------- records


def test_parse_url():
    assert parse_url("s3://bkt/a/b/") == ("bkt", "a/b/")
    assert parse_url("s3://bkt") == ("bkt", "")
    with pytest.raises(ValueError):
        parse_url("s3:///x")


def test_records_files_and_a_second_replica(bucket, tmp_path):
    a = make(bucket, tmp_path, "a")
    sid = new_scene_id()
    rec = a.create(sid, {"cameras": [{"name": "CAM_FRONT", "width": 1600, "height": 900, "model": "pinhole"}]})
    assert rec.state == "queued" and rec.owner == "a"
    with pytest.raises(ValueError):
        a.create(sid, {})
    assert keys(bucket) == [f"pfx/records/{sid}.json"]
    assert a.update(sid, state="running").state == "running"
    src = scene_folder(a, 123)
    rec = a.commit(sid, src, gaussians=5, background=False)
    assert rec.state == "ready" and rec.bytes == 123 and rec.files == ["scene.json", "scene.ply"]
    assert keys(bucket, "pfx/scenes/") == [f"pfx/scenes/{sid}/scene.json", f"pfx/scenes/{sid}/scene.ply"]
    # the finished folder became replica a's local copy: no download on a
    assert not src.exists() and a.scene_dir(sid) == tmp_path / "cache-a" / "scenes" / sid

    b = make(bucket, tmp_path, "b")
    assert b.get(sid).state == "ready" and b.list()[1] == 1
    local = b.scene_dir(sid)                               # downloaded once, into b's cache
    assert local == tmp_path / "cache-b" / "scenes" / sid
    assert (local / "scene.ply").read_bytes() == (a.scene_dir(sid) / "scene.ply").read_bytes()
    assert b.usage()["scenes"]["ready"] == 1 and b.usage()["bytes"] == 123

    seen = []
    b.on_delete.append(seen.append)
    b.record_ttl_s = 0.0                                   # no cached ready record: see the delete at once
    assert a.delete(sid) is True and a.delete(sid) is False
    assert keys(bucket, "pfx/records/") == [] and keys(bucket, "pfx/scenes/") == []
    assert b.get(sid) is None and seen == [sid] and not local.exists()    # b drops its copy when it sees
    with pytest.raises(KeyError):
        b.scene_dir(sid)
    assert b.update(sid, state="running") is None and b.fail(sid, "x", "y") is None


def test_list_newest_first_and_a_failed_job(bucket, tmp_path):
    st = make(bucket, tmp_path, "a")
    ids = []
    for _ in range(3):
        sid = new_scene_id()
        st.create(sid, {})
        ids.append(sid)
        time.sleep(0.002)
    page, total = st.list(0, 2)
    assert total == 3 and [r.id for r in page] == ids[::-1][:2]
    failed = st.fail(ids[0], "invalid_input", "bad rig")
    assert failed.state == "failed"
    assert failed.error.model_dump() == {"code": "invalid_input", "message": "bad rig"}
    assert st.list(2, 5)[0][0].state == "failed"           # the listing re-read the record whose ETag changed


def test_malformed_ids_are_unknown(bucket, tmp_path):
    st = make(bucket, tmp_path, "a")
    for bad in ("../x", "a/b", "A" * 21, "..%2F..%2Fetc", "", None):
        assert st.get(bad) is None and st.delete(bad) is False
        assert st.update(bad, state="ready") is None and st.fail(bad, "x", "y") is None
        with pytest.raises(KeyError):
            st.scene_dir(bad)
        with pytest.raises(KeyError):
            st.create(bad, {})
        st.touch(bad)
    assert keys(bucket) == []


def test_commit_after_a_delete_leaves_nothing(bucket, tmp_path):
    a = make(bucket, tmp_path, "a")
    b = make(bucket, tmp_path, "b")
    gone = new_scene_id()
    a.create(gone, {})
    assert b.delete(gone)                                  # deleted on b while a reconstructs
    late = scene_folder(a)
    assert a.commit(gone, late) is None and not late.exists()
    assert keys(bucket, "pfx/records/") == [] and keys(bucket, "pfx/scenes/") == []

    # the race: a read the record just before b's delete, then uploads and writes it ready (after b removed the
    # record); the tombstone that b wrote first makes a undo its own write
    racing = new_scene_id()
    a.create(racing, {})
    stale = a._fresh(racing)
    assert b.delete(racing)
    a._fresh = lambda sid: dict(stale)
    assert a.commit(racing, scene_folder(a)) is None
    assert b.get(racing) is None
    assert keys(bucket, "pfx/records/") == [] and keys(bucket, "pfx/scenes/") == []


# ----------------------------------------------------------------------------------------------- recovery


def test_open_recovers_own_and_dead_replicas_jobs(bucket, tmp_path, monkeypatch):
    a = make(bucket, tmp_path, "a", stale_running_s=600, stale_queued_s=1200)
    queued, running = new_scene_id(), new_scene_id()
    a.create(queued, {})
    a.create(running, {})
    a.update(running, state="running")
    ok = ready_scene(a)
    lost = ready_scene(a)
    client = boto3.client("s3")
    client.delete_object(Bucket=bucket, Key=f"pfx/scenes/{lost}/scene.json")      # ready record, files gone
    orphan = new_scene_id()
    client.put_object(Bucket=bucket, Key=f"pfx/scenes/{orphan}/scene.json", Body=b"{}")  # files, no record
    client.put_object(Bucket=bucket, Key="pfx/records/notes.json", Body=b"{}")     # not ours: left alone

    # another replica starting now leaves a's fresh jobs alone (a is alive)
    b = S3Store(f"s3://{bucket}/pfx", cache_dir=tmp_path / "cache-b", replica_id="b", stale_running_s=600,
                stale_queued_s=1200)
    assert b.open() == {"ready": 1, "interrupted": 0, "files_missing": 1, "orphans": 1}
    assert b.get(queued).state == "queued" and b.get(running).state == "running"
    assert b.get(lost).error.code == "files_missing"
    assert keys(bucket, f"pfx/scenes/{orphan}") == [] and "pfx/records/notes.json" in keys(bucket)

    # replica a restarted (same replica id): its own queued/running jobs were interrupted
    a2 = S3Store(f"s3://{bucket}/pfx", cache_dir=tmp_path / "cache-a", replica_id="a")
    assert a2.open()["interrupted"] == 2
    for sid in (queued, running):
        assert b.get(sid).state == "failed" and b.get(sid).error.code == "interrupted"
    assert a2.get(ok).state == "ready" and (a2.scene_dir(ok) / "scene.json").is_file()

    # replica c's jobs, c dead: stale after the windows (running: 600 s; queued: 1200 s), seen by anyone
    c = make(bucket, tmp_path, "c")
    q2, r2 = new_scene_id(), new_scene_id()
    c.create(q2, {})
    c.create(r2, {})
    c.update(r2, state="running")
    t = time.time()
    monkeypatch.setattr(s3_mod, "_now", lambda: t + 900)
    assert b.get(r2).state == "failed" and b.get(q2).state == "queued"
    monkeypatch.setattr(s3_mod, "_now", lambda: t + 1300)
    d = S3Store(f"s3://{bucket}/pfx", cache_dir=tmp_path / "cache-d", replica_id="d", stale_running_s=600,
                stale_queued_s=1200)
    assert d.open()["interrupted"] == 1 and d.get(q2).error.code == "interrupted"


# ----------------------------------------------------------------------------------------------- quota


def test_count_quota_evicts_the_least_recently_used(bucket, tmp_path):
    st = make(bucket, tmp_path, "a", max_scenes=2, when_full="evict")
    a = ready_scene(st)
    b = ready_scene(st)
    time.sleep(0.01)
    st.touch(a)                                        # a was rendered: b is now the least recently used
    c = new_scene_id()
    st.create(c, {})
    assert st.get(b) is None and st.get(a).state == "ready" and st.get(c).state == "queued"
    assert st.usage()["evicted"] == 1 and keys(bucket, f"pfx/scenes/{b}") == []
    # only ready scenes are evicted (queued ones are work in progress); failed records do not count
    st.delete(a)
    q = new_scene_id()
    st.create(q, {})
    with pytest.raises(StoreFull):
        st.create(new_scene_id(), {})
    assert st.get(c) and st.get(q) and st.list()[1] == 2
    st.fail(c, "timeout", "slow")
    d = new_scene_id()
    st.create(d, {})
    assert st.get(d).state == "queued"


def test_count_quota_reject_and_byte_quota(bucket, tmp_path):
    st = make(bucket, tmp_path, "a", max_scenes=1, when_full="reject")
    a = ready_scene(st)
    with pytest.raises(StoreFull):
        st.create(new_scene_id(), {})
    assert st.get(a).state == "ready" and st.usage()["evicted"] == 0

    by = make(bucket, tmp_path, "b", prefix="other", max_bytes=250, when_full="evict")
    x = ready_scene(by, 100)
    y = ready_scene(by, 100)
    time.sleep(0.01)
    by.touch(x)
    z = ready_scene(by, 100)                          # 300 > 250: y (least recently used) goes
    assert by.get(y) is None and by.get(x).state == "ready" and by.get(z).state == "ready"
    assert by.usage()["bytes"] == 200
    big = new_scene_id()
    by.create(big, {})
    src = scene_folder(by, 300)                       # over the whole quota: refused, nothing evicted
    with pytest.raises(StoreFull):
        by.commit(big, src)
    assert not src.exists() and by.get(big).state == "queued" and by.usage()["bytes"] == 200


def test_ttl_sweep_and_litter(bucket, tmp_path):
    st = make(bucket, tmp_path, "a", ttl_s=100)
    old = ready_scene(st)
    queued = new_scene_id()
    st.create(queued, {})
    st._mark_used(old)
    boto3.client("s3").put_object(Bucket=bucket, Key=f"pfx/used/{new_scene_id()}", Body=b"")   # a deleted one's
    assert st.sweep(now=time.time() + 50) == []
    assert st.sweep(now=time.time() + 200) == [old]
    assert st.get(old) is None and st.get(queued).state == "queued"
    assert keys(bucket, "pfx/used/") == [] and keys(bucket, f"pfx/scenes/{old}") == []
    assert keys(bucket, "pfx/deleted/") == [f"pfx/deleted/{old}"]       # kept while a late writer could come
    st.sweep(now=time.time() + st.stale_queued_s + 3700)
    assert keys(bucket, "pfx/deleted/") == []


# ----------------------------------------------------------------------------------------------- two apps


def _rig_files() -> list:
    rig = json.loads((EXAMPLE / "rig.json").read_text())
    files = [("rig", ("rig.json", json.dumps(rig), "application/json"))]
    for c in rig["cameras"]:
        files.append((c["name"], (c["name"] + ".png", (EXAMPLE / c["image"]).read_bytes(), "image/png")))
    return files


@pytest.mark.slow
def test_two_replicas_share_the_bucket(bucket, tmp_path):
    """Two apps (two replicas) on one bucket: posted to A, rendered by B with the same bytes; deleted on B, 404
    on A."""
    from fastapi.testclient import TestClient
    from xyzcyl.server import Settings, create_app

    def app(name):
        return create_app(Settings(store=f"s3://{bucket}/pfx", replica_id=name, s3_cache=tmp_path / name,
                                   render_threads=1, ort_threads=1, scene_cache=1))

    with TestClient(app("a")) as ca, TestClient(app("b")) as cb:
        deadline = time.time() + 120
        while ca.get("/v2/health/ready").status_code != 200 and time.time() < deadline:
            time.sleep(0.1)
        r = ca.post("/v1/scenes?wait=120", files=_rig_files())
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        assert cb.get(f"/v1/scenes/{sid}").json()["state"] == "ready"
        assert [s["id"] for s in cb.get("/v1/scenes").json()["scenes"]] == [sid]
        view = f"/v1/scenes/{sid}/render?camera=CAM_FRONT&width=320&height=180"
        ra, rb = ca.get(view), cb.get(view)
        assert ra.status_code == rb.status_code == 200 and ra.headers["content-type"] == "image/png"
        assert ra.content == rb.content
        ply = cb.get(f"/v1/scenes/{sid}/gaussians")
        assert ply.status_code == 200 and ply.content == (tmp_path / "a" / "scenes" / sid / "scene.ply").read_bytes()

        assert cb.delete(f"/v1/scenes/{sid}").status_code == 204
        assert cb.get(f"/v1/scenes/{sid}").status_code == 404
        t0 = time.time()
        while ca.get(f"/v1/scenes/{sid}").status_code != 404:       # a's cached ready record expires (1 s)
            assert time.time() - t0 < 5
            time.sleep(0.05)
        assert ca.get(view).status_code == 404
        assert not (tmp_path / "a" / "scenes" / sid).exists()          # a dropped its copy
    assert keys(bucket, "pfx/records/") == [] and keys(bucket, "pfx/scenes/") == []
    assert os.environ["AWS_ENDPOINT_URL"].startswith("http://127.0.0.1:")


# ----------------------------------------------------------------------------------------------- an outage


def test_an_unreachable_bucket_is_503_and_not_ready(s3_endpoint, tmp_path, monkeypatch):
    """The bucket stops answering after start-up (its server stops): the /v1 routes answer 503 store_unavailable +
    Retry-After (not 500), /v2/health/ready turns 503, /metrics still answers; once the bucket is back, both
    recover. Issue 27 defect 8. An app without its lifespan (no workers): the store is opened and the service
    marked ready by hand."""
    from fastapi.testclient import TestClient
    from moto.server import ThreadedMotoServer
    from xyzcyl.server import Settings, create_app

    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    monkeypatch.setenv("AWS_ENDPOINT_URL", url)         # this test's own S3 server, stopped below
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        boto3.client("s3").create_bucket(Bucket="outage")
        app = create_app(Settings(store="s3://outage/pfx", s3_cache=tmp_path / "cache", replica_id="r"))
        service = app.state.service
        store = service.store
        store.open()
        service.ready = True
        sid = ready_scene(store)
        client = TestClient(app)
        assert client.get("/v2/health/ready").status_code == 200
        assert client.get("/v1/scenes").json()["total"] == 1
        assert client.get(f"/v1/scenes/{sid}").json()["state"] == "ready"
    finally:
        server.stop()

    store._probed = None            # the probe's last answer (kept 2 s) is from before the stop
    for method, path in (("GET", "/v1/scenes"), ("GET", f"/v1/scenes/{sid}"), ("DELETE", f"/v1/scenes/{sid}"),
                         ("GET", f"/v1/scenes/{sid}/render?camera=CAM_FRONT"), ("GET", f"/v1/scenes/{sid}/gaussians")):
        t0 = time.monotonic()
        r = client.request(method, path)
        assert r.status_code == 503, (method, path, r.status_code, r.text)
        assert r.json()["error"]["code"] == "store_unavailable" and r.headers["retry-after"] == "1"
        assert "127.0.0.1" not in r.text and "outage" not in r.text          # no endpoint or bucket in the body
        assert time.monotonic() - t0 < 10
    r = client.get("/v2/health/ready")
    assert r.status_code == 503 and r.json() == {"ready": False, "reason": "the scene store cannot be reached; "
                                                                           "retry later"}
    assert client.get("/v2/models/xyzcyl-cpu-v1/ready").status_code == 503
    assert client.get("/v2/health/live").status_code == 200
    assert client.get("/metrics").status_code == 200

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)   # back, with the same objects
    server.start()                                                                   # (moto's state is in-process)
    try:
        t0 = time.monotonic()
        while client.get("/v2/health/ready").status_code != 200:
            assert time.monotonic() - t0 < 10, "ready did not come back"
            time.sleep(0.2)
        r = client.get("/v1/scenes")
        assert r.status_code == 200 and r.json()["total"] == 1
        assert client.get(f"/v1/scenes/{sid}").json()["state"] == "ready"
        assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    finally:
        server.stop()
