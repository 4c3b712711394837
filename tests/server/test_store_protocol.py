"""The store interface (issue 27, house 3): FolderStore and S3Store implement server.store.Store (every member,
with the protocol's signatures), and a scene record written in the format the stores have always written
(server/store/record.py) loads into a SceneRecord and is written back with the same JSON: the same keys in the
same order, absent keys still absent, unknown keys kept. S3 through moto's in-process mock."""

from __future__ import annotations

import inspect
import json

import pytest
from xyzcyl.server.store import FolderStore, SceneRecord, Store
from xyzcyl.server.store import folder as folder_mod

# Records as the stores wrote them before SceneRecord (json.dumps of the dicts, keys in the order they were made)
QUEUED = ('{"cameras": [{"name": "CAM_FRONT", "width": 800, "height": 450, "model": "pinhole"}], "detail": '
          '{"enabled": true, "stride": 2}, "id": "AAAAAAAAAAAAAAAAAAAAAA", "state": "queued", "created_ts": '
          '1764092077.25, "updated_ts": 1764092077.25, "error": null}')
READY = ('{"cameras": [{"name": "CAM_FRONT", "width": 800, "height": 450, "model": "pinhole"}], "id": '
         '"BBBBBBBBBBBBBBBBBBBBBB", "state": "ready", "created_ts": 1764092077.5, "updated_ts": 1764092082.75, '
         '"error": null, "model": {"name": "xyzcyl-cpu-v1", "version": "1.4.0", "model_json_sha256": "000fd278"}, '
         '"counts": {"pixel": 114688, "pruned": 6521, "total": 544123, "detail": 531251}, "timings": {"decode": '
         '0.196, "total": 4.9, "queued": 0.002, "worker_total": 5.498}, "bbox": {"min": [-299.92, -143.89, -0.68], '
         '"max": [299.86, 237.66, 157.45]}, "gaussians": 544123, "background": true, "bytes": 38442211, '
         '"last_used": 1764092082.75, "a_later_key": {"kept": [1, 2]}}')
FAILED = ('{"cameras": [], "id": "CCCCCCCCCCCCCCCCCCCCCC", "state": "failed", "created_ts": 1764092000.0, '
          '"updated_ts": 1764092001.5, "error": {"code": "invalid_input", "message": "camera \'CAM_FRONT\': K: fx '
          'must be > 0"}}')
S3_READY = ('{"cameras": [], "detail": {"enabled": false, "stride": null}, "id": "DDDDDDDDDDDDDDDDDDDDDD", '
            '"state": "ready", "created_ts": 1764092077.5, "updated_ts": 1764092082.75, "error": null, "owner": '
            '"host:1234", "model": {"name": "m"}, "counts": {"total": 3}, "timings": {"total": 1.0}, "bbox": null, '
            '"gaussians": 3, "background": false, "bytes": 14, "last_used": 1764092082.75, "files": '
            '["scene.json"]}')


def _members(cls) -> dict[str, object]:
    return {k: v for k, v in vars(cls).items() if not k.startswith("_")}


def check_implements(store) -> None:
    """``store`` is a Store: isinstance (every member present) and each method's parameters the protocol's."""
    assert isinstance(store, Store)
    for name, proto in _members(Store).items():
        if not callable(proto):
            continue
        impl = getattr(type(store), name)
        want = list(inspect.signature(proto).parameters.values())
        got = list(inspect.signature(impl).parameters.values())
        assert [(p.name, p.kind, p.default) for p in got] == [(p.name, p.kind, p.default) for p in want], name
    for name in Store.__annotations__:
        assert hasattr(store, name), name


def test_record_json_round_trip_is_exact():
    for text in (QUEUED, READY, FAILED, S3_READY):
        doc = json.loads(text)
        rec = SceneRecord.from_json(doc)
        assert json.dumps(rec.to_json()) == text
        assert rec.error is None or (rec.error.code, rec.error.message) == tuple(doc["error"].values())
    ready = SceneRecord.from_json(json.loads(READY))
    assert (ready.state, ready.bytes, ready.gaussians, ready.background) == ("ready", 38442211, 544123, True)
    assert "detail" not in ready.to_json()                     # absent stays absent (a scene from before the layer)
    # a change makes a new record with the fields checked; the old one is unchanged
    failed = ready.failed("files_missing", "gone", 5.0)
    assert (failed.state, failed.error.model_dump(), ready.state) == (
        "failed", {"code": "files_missing", "message": "gone"}, "ready")
    with pytest.raises(TypeError, match="bogus"):
        ready.replace(bogus=1)
    with pytest.raises(ValueError):
        ready.replace(state="finished")
    assert SceneRecord.parse("BBBBBBBBBBBBBBBBBBBBBB", {**json.loads(READY), "gaussians": "many"}) is None
    assert SceneRecord.parse("AAAAAAAAAAAAAAAAAAAAAA", json.loads(READY)) is None          # another id


def test_folder_store_implements_the_protocol_and_keeps_the_record_json(tmp_path, monkeypatch):
    root = tmp_path / "store"
    for text in (QUEUED, READY, FAILED):
        doc = json.loads(text)
        (root / "records").mkdir(parents=True, exist_ok=True)
        (root / "records" / f"{doc['id']}.json").write_text(text)
    scene = root / "scenes" / "BBBBBBBBBBBBBBBBBBBBBB"
    scene.mkdir(parents=True)
    (scene / "scene.json").write_text("{}")

    store = FolderStore(root)
    check_implements(store)
    assert store.open() == {"ready": 1, "interrupted": 1, "files_missing": 0, "orphans": 0}

    def on_disk(sid: str) -> str:
        return (root / "records" / f"{sid}.json").read_text()

    # loaded and written back unchanged (the ready and the failed record were not touched by open)
    assert on_disk("BBBBBBBBBBBBBBBBBBBBBB") == READY and on_disk("CCCCCCCCCCCCCCCCCCCCCC") == FAILED
    assert json.dumps(store.get("BBBBBBBBBBBBBBBBBBBBBB").to_json()) == READY
    # the queued one was interrupted by open: the same keys in the same order, three values changed
    monkeypatch.setattr(folder_mod, "_now", lambda: 1764099999.0)
    store.fail("AAAAAAAAAAAAAAAAAAAAAA", "interrupted", "stopped")
    expected = {**json.loads(QUEUED), "state": "failed", "updated_ts": 1764099999.0,
                "error": {"code": "interrupted", "message": "stopped"}}
    assert on_disk("AAAAAAAAAAAAAAAAAAAAAA") == json.dumps(expected)
    # a use of the ready scene rewrites last_used only
    store.touch("BBBBBBBBBBBBBBBBBBBBBB")
    assert on_disk("BBBBBBBBBBBBBBBBBBBBBB") == json.dumps({**json.loads(READY), "last_used": 1764099999.0})


def test_s3_store_implements_the_protocol_and_keeps_the_record_json(tmp_path, monkeypatch):
    boto3 = pytest.importorskip("boto3")
    moto = pytest.importorskip("moto")
    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    from xyzcyl.server.store import s3 as s3_mod
    from xyzcyl.server.store.s3 import S3Store

    with moto.mock_aws():
        client = boto3.client("s3")
        client.create_bucket(Bucket="bkt")
        for text in (S3_READY, FAILED):
            sid = json.loads(text)["id"]
            client.put_object(Bucket="bkt", Key=f"pfx/records/{sid}.json", Body=text.encode())
        client.put_object(Bucket="bkt", Key="pfx/scenes/DDDDDDDDDDDDDDDDDDDDDD/scene.json", Body=b"{}")

        def stored(sid: str) -> str:
            return client.get_object(Bucket="bkt", Key=f"pfx/records/{sid}.json")["Body"].read().decode()

        store = S3Store("s3://bkt/pfx", cache_dir=tmp_path / "cache", replica_id="here")
        check_implements(store)
        assert store.open() == {"ready": 1, "interrupted": 0, "files_missing": 0, "orphans": 0}
        assert json.dumps(store.get("DDDDDDDDDDDDDDDDDDDDDD").to_json()) == S3_READY
        assert [r.id for r in store.list()[0]] == ["DDDDDDDDDDDDDDDDDDDDDD", "CCCCCCCCCCCCCCCCCCCCCC"]
        assert (store.scene_dir("DDDDDDDDDDDDDDDDDDDDDD") / "scene.json").read_bytes() == b"{}"
        assert stored("DDDDDDDDDDDDDDDDDDDDDD") == S3_READY and stored("CCCCCCCCCCCCCCCCCCCCCC") == FAILED

        monkeypatch.setattr(s3_mod, "_now", lambda: 1764099999.0)
        store.update("CCCCCCCCCCCCCCCCCCCCCC", state="running")
        assert stored("CCCCCCCCCCCCCCCCCCCCCC") == json.dumps({**json.loads(FAILED), "state": "running",
                                                                "updated_ts": 1764099999.0})
        # the record a replica creates now: today's keys and order, owner after error
        new = store.create("EEEEEEEEEEEEEEEEEEEEEE", {"cameras": [], "detail": {"enabled": True, "stride": 2}})
        assert list(json.loads(stored(new.id))) == ["cameras", "detail", "id", "state", "created_ts", "updated_ts",
                                                    "error", "owner"]

