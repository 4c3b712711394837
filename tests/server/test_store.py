"""FolderStore (server/store/folder.py) without the app: records, atomic commits, recovery when a store is
opened after a crash, the count and byte quotas (LRU eviction or StoreFull), the TTL and scene ids."""

from __future__ import annotations

import errno
import json
import os
import re
import sys
from pathlib import Path

import pytest
from xyzcyl.server.store import folder as folder_mod
from xyzcyl.server.store.folder import SCENE_ID, FolderStore, StoreFull, new_scene_id

CAM = {"name": "CAM_FRONT", "width": 1600, "height": 900, "model": "pinhole"}   # a complete camera of a rig


class Clock:
    """A controllable replacement of folder._now (LRU and TTL decisions compare these times)."""

    def __init__(self, t: float = 1_000_000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t

    def tick(self, dt: float = 1.0) -> float:
        self.t += dt
        return self.t


@pytest.fixture
def clock(monkeypatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(folder_mod, "_now", c)
    return c


def make_store(root: Path, **kw) -> FolderStore:
    s = FolderStore(root, **kw)
    s.open()
    return s


def scene_folder(store: FolderStore, nbytes: int = 100) -> Path:
    """A finished scene folder under tmp/ (as a reconstruction leaves it): scene.json + payload, nbytes in all."""
    d = store.work_dir() / "scene"
    d.mkdir()
    head = b'{"version": 1}'
    (d / "scene.json").write_bytes(head)
    (d / "scene.ply").write_bytes(b"x" * (nbytes - len(head)))
    return d


def ready_scene(store: FolderStore, nbytes: int = 100, **fields) -> str:
    sid = new_scene_id()
    store.create(sid, {"cameras": []})
    store.update(sid, state="running")
    assert store.commit(sid, scene_folder(store, nbytes), gaussians=7, **fields).state == "ready"
    return sid


def disk_record(store: FolderStore, sid: str) -> dict:
    return json.loads((store.root / "records" / f"{sid}.json").read_text())


# ----------------------------------------------------------------------------------------------- records


def test_create_update_fail_delete_persist(tmp_path):
    store = make_store(tmp_path / "st")
    sid = new_scene_id()
    rec = store.create(sid, {"cameras": [CAM]})
    assert rec.state == "queued" and rec.id == sid and rec.error is None
    assert disk_record(store, sid)["state"] == "queued"
    with pytest.raises(ValueError):
        store.create(sid, {})

    assert store.update(sid, state="running").state == "running"
    assert disk_record(store, sid)["state"] == "running"
    # get() hands out a copy: changing it does not change the store
    got = store.get(sid)
    got.state = "ready"
    assert store.get(sid).state == "running"

    failed = store.fail(sid, "invalid_input", "bad rig")
    assert failed.state == "failed"
    assert failed.error.model_dump() == {"code": "invalid_input", "message": "bad rig"}
    assert disk_record(store, sid)["error"]["code"] == "invalid_input"

    seen = []
    store.on_delete.append(seen.append)
    assert store.delete(sid) is True
    assert seen == [sid]
    assert store.get(sid) is None and not (store.root / "records" / f"{sid}.json").exists()
    assert store.delete(sid) is False
    assert store.update(sid, state="running") is None and store.fail(sid, "x", "y") is None


def test_commit_moves_the_folder_and_marks_ready(tmp_path):
    store = make_store(tmp_path / "st")
    sid = new_scene_id()
    store.create(sid, {"cameras": []})
    src = scene_folder(store, 123)
    assert not (store.root / "scenes" / sid).exists()
    rec = store.commit(sid, src, gaussians=5, background=True)
    assert rec.state == "ready" and rec.bytes == 123 and rec.gaussians == 5 and rec.background
    assert not src.exists()
    assert (store.root / "scenes" / sid / "scene.json").is_file()
    assert store.scene_dir(sid) == store.root / "scenes" / sid
    assert disk_record(store, sid)["state"] == "ready"
    assert store.usage()["bytes"] == 123 and store.usage()["scenes"]["ready"] == 1

    # a scene deleted while it was reconstructed: commit refuses and removes the finished folder
    gone = new_scene_id()
    store.create(gone, {})
    store.delete(gone)
    late = scene_folder(store)
    assert store.commit(gone, late) is None
    assert not late.exists() and not (store.root / "scenes" / gone).exists()

    store.delete(sid)
    assert not (store.root / "scenes" / sid).exists()
    with pytest.raises(KeyError):
        store.scene_dir(sid)


def test_commit_is_atomic_a_crash_before_the_rename_leaves_no_ready_record(tmp_path, monkeypatch):
    root = tmp_path / "st"
    store = make_store(root)
    sid = new_scene_id()
    store.create(sid, {})
    store.update(sid, state="running")
    src = scene_folder(store)
    real_replace = os.replace

    def crash(a, b, *args, **kw):
        if Path(b).parent == root / "scenes":         # the folder's rename into place "crashes"
            raise OSError(errno.EIO, "simulated crash")
        return real_replace(a, b, *args, **kw)

    monkeypatch.setattr(folder_mod.os, "replace", crash)
    with pytest.raises(OSError):
        store.commit(sid, src)
    monkeypatch.setattr(folder_mod.os, "replace", real_replace)
    assert store.get(sid).state == "running"
    assert disk_record(store, sid)["state"] == "running"
    assert not (root / "scenes" / sid).exists()
    # the process "dies" here; the next one sees an interrupted job, never a half-written ready scene
    again = FolderStore(root)
    report = again.open()
    assert report["interrupted"] == 1 and report["ready"] == 0
    assert again.get(sid).state == "failed" and again.get(sid).error.code == "interrupted"


def test_create_that_cannot_be_written_leaves_no_record(tmp_path, monkeypatch):
    store = make_store(tmp_path / "st")

    def full(path, doc):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(folder_mod, "_write_json_atomic", full)
    sid = new_scene_id()
    with pytest.raises(OSError):
        store.create(sid, {})
    assert store.get(sid) is None
    assert store.list() == ([], 0)
    assert store.usage()["scenes"]["queued"] == 0


def test_list_newest_first_with_paging(tmp_path, clock):
    store = make_store(tmp_path / "st")
    ids = []
    for _ in range(5):
        clock.tick()
        sid = new_scene_id()
        store.create(sid, {})
        ids.append(sid)
    page, total = store.list(0, 2)
    assert total == 5 and [r.id for r in page] == ids[::-1][:2]
    page, total = store.list(4, 2)
    assert [r.id for r in page] == [ids[0]]


# ----------------------------------------------------------------------------------------------- recovery


def test_open_recovers_from_a_crash(tmp_path, clock):
    root = tmp_path / "st"
    store = make_store(root)
    ok = ready_scene(store)
    queued, running = new_scene_id(), new_scene_id()
    store.create(queued, {})
    store.create(running, {})
    store.update(running, state="running")
    lost = ready_scene(store)
    failed = new_scene_id()
    store.create(failed, {})
    store.fail(failed, "invalid_input", "bad")

    # what a crash (or an operator) can leave behind
    import shutil

    shutil.rmtree(root / "scenes" / lost)                                   # ready record, folder gone
    orphan = new_scene_id()
    (root / "scenes" / orphan).mkdir()                                      # folder without a record
    (root / "scenes" / orphan / "scene.json").write_text("{}")
    (root / "scenes" / failed).mkdir()                                      # folder of a failed record
    (root / "scenes" / queued).mkdir()                                      # half a reconstruction
    damaged = new_scene_id()
    (root / "records" / f"{damaged}.json").write_text('{"id": "' + damaged + '", "sta')   # torn write
    other = new_scene_id()
    (root / "records" / f"{other}.json").write_text(json.dumps({"id": new_scene_id(), "state": "ready"}))
    (root / "records" / "notes.json").write_text(json.dumps({"id": "notes", "state": "ready"}))
    badstate = new_scene_id()
    (root / "records" / f"{badstate}.json").write_text(json.dumps({"id": badstate, "state": "done"}))
    (root / "tmp" / "upload-1").mkdir(exist_ok=True)
    (root / "tmp" / "upload-1" / "CAM_FRONT.png").write_bytes(b"x")
    (root / "tmp" / "stray.bin").write_bytes(b"x")

    again = FolderStore(root)
    report = again.open()
    assert report == {"ready": 1, "interrupted": 2, "files_missing": 1, "orphans": 7}

    assert again.get(ok).state == "ready" and (root / "scenes" / ok / "scene.json").is_file()
    for sid in (queued, running):
        rec = again.get(sid)
        assert rec.state == "failed" and rec.error.code == "interrupted"
        assert disk_record(again, sid)["state"] == "failed"
    assert again.get(lost).state == "failed" and again.get(lost).error.code == "files_missing"
    assert again.get(failed).error.code == "invalid_input"
    assert sorted(p.name for p in (root / "scenes").iterdir()) == [ok]
    assert sorted(p.name for p in (root / "records").iterdir()) == sorted(
        f"{s}.json" for s in (ok, queued, running, lost, failed))
    for sid in (damaged, other, badstate):
        assert again.get(sid) is None
    assert list((root / "tmp").iterdir()) == []
    assert again.list()[1] == 5

    # reopening a recovered store changes nothing
    third = FolderStore(root)
    assert third.open() == {"ready": 1, "interrupted": 0, "files_missing": 0, "orphans": 0}


# ----------------------------------------------------------------------------------------------- quota


def test_count_quota_evicts_the_least_recently_used(tmp_path, clock):
    store = make_store(tmp_path / "st", max_scenes=2, when_full="evict")
    a = ready_scene(store)
    clock.tick()
    b = ready_scene(store)
    clock.tick()
    c = new_scene_id()
    store.create(c, {})                                  # a is the least recently used: evicted
    assert store.get(a) is None and not (store.root / "scenes" / a).exists()
    assert store.get(b).state == "ready" and store.usage()["evicted"] == 1


def test_touch_changes_the_eviction_victim(tmp_path, clock):
    store = make_store(tmp_path / "st", max_scenes=2, when_full="evict")
    a = ready_scene(store)
    clock.tick()
    b = ready_scene(store)
    clock.tick()
    store.touch(a)                                       # a was rendered: b is now the least recently used
    clock.tick()
    c = new_scene_id()
    store.create(c, {})
    assert store.get(b) is None and not (store.root / "scenes" / b).exists()
    assert store.get(a).state == "ready" and store.get(c).state == "queued"


def test_count_quota_only_evicts_ready_scenes(tmp_path, clock):
    store = make_store(tmp_path / "st", max_scenes=2, when_full="evict")
    q1, q2 = new_scene_id(), new_scene_id()
    store.create(q1, {})
    store.create(q2, {})
    with pytest.raises(StoreFull):
        store.create(new_scene_id(), {})
    assert store.get(q1) and store.get(q2) and store.list()[1] == 2
    # failed records do not count against max_scenes
    store.fail(q1, "timeout", "slow")
    c = new_scene_id()
    store.create(c, {})
    assert store.get(c).state == "queued"


def test_count_quota_reject(tmp_path, clock):
    store = make_store(tmp_path / "st", max_scenes=1, when_full="reject")
    a = ready_scene(store)
    with pytest.raises(StoreFull):
        store.create(new_scene_id(), {})
    assert store.get(a).state == "ready" and store.list()[1] == 1 and store.usage()["evicted"] == 0


def test_byte_quota_on_commit_evicts(tmp_path, clock):
    store = make_store(tmp_path / "st", max_bytes=250, when_full="evict")
    a = ready_scene(store, 100)
    clock.tick()
    b = ready_scene(store, 100)
    clock.tick()
    store.touch(a)
    clock.tick()
    c = ready_scene(store, 100)                          # 300 > 250: b (least recently used) goes
    assert store.get(b) is None and store.get(a).state == "ready" and store.get(c).state == "ready"
    assert store.usage()["bytes"] == 200


def test_byte_quota_on_commit_reject_and_too_big(tmp_path, clock):
    store = make_store(tmp_path / "st", max_bytes=250, when_full="reject")
    a = ready_scene(store, 100)
    b = ready_scene(store, 100)
    c = new_scene_id()
    store.create(c, {})
    src = scene_folder(store, 100)
    with pytest.raises(StoreFull):
        store.commit(c, src)
    assert not src.exists() and not (store.root / "scenes" / c).exists()
    assert store.get(c).state == "queued"
    assert store.get(a) and store.get(b) and store.usage()["bytes"] == 200

    # a scene over the whole quota is refused even when eviction could make room
    big = FolderStore(tmp_path / "st2", max_bytes=250, when_full="evict")
    big.open()
    keep = ready_scene(big, 100)
    d = new_scene_id()
    big.create(d, {})
    src = scene_folder(big, 300)
    with pytest.raises(StoreFull):
        big.commit(d, src)
    assert not src.exists() and big.get(keep).state == "ready"


def test_ttl_sweep(tmp_path, clock):
    store = make_store(tmp_path / "st", ttl_s=100)
    old = ready_scene(store)
    clock.tick(50)
    young = ready_scene(store)
    stale_failed = new_scene_id()
    store.create(stale_failed, {})
    store.fail(stale_failed, "timeout", "slow")
    queued = new_scene_id()
    store.create(queued, {})
    removed = store.sweep(now=clock.t + 60)              # old: 110 s unused, young / failed: 60 s
    assert removed == [old]
    assert store.get(old) is None and not (store.root / "scenes" / old).exists()
    assert store.get(young).state == "ready"
    clock.tick(60)
    store.touch(young)                                   # used again: its clock restarts
    assert store.sweep(now=clock.t + 50) == [stale_failed]          # failed: 110 s since it failed
    assert store.get(young).state == "ready"
    assert store.sweep(now=clock.t + 150) == [young]
    assert store.get(queued).state == "queued"           # work in progress is never swept
    assert FolderStore(tmp_path / "st3").sweep(now=1e12) == []   # no TTL: nothing expires


# ----------------------------------------------------------------------------------------------- ids


def test_new_scene_id():
    ids = {new_scene_id() for _ in range(2000)}
    assert len(ids) == 2000
    for sid in ids:
        assert len(sid) == 22 and re.fullmatch(r"[A-Za-z0-9_-]{22}", sid) and SCENE_ID.match(sid)


_WATCHED: dict = {"bad": None, "hits": []}


def _audit(event, args):
    bad = _WATCHED["bad"]
    if bad is not None and (event in ("open", "os.listdir", "os.scandir", "os.mkdir", "os.remove", "os.rename",
                                      "os.rmdir", "shutil.rmtree", "os.chmod", "os.utime")
                            and any(bad in str(a) for a in args)):
        _WATCHED["hits"].append((event, args))


@pytest.mark.parametrize("bad", ["../x", "a/b", "A" * 21, "A" * 23, "..%2F..%2Fetc", "/etc/passwd",
                                 "abcdefghijklmnopqrstu.", "abcdefghijklmnopqrstu\n", ""])
def test_malformed_ids_are_unknown_and_touch_no_file(tmp_path, bad, monkeypatch):
    store = make_store(tmp_path / "st")
    ready_scene(store)
    if _audit not in getattr(sys, "_xyzcyl_hooks", ()):
        sys.addaudithook(_audit)          # process-wide and permanent: inert while _WATCHED["bad"] is None
        sys._xyzcyl_hooks = (*getattr(sys, "_xyzcyl_hooks", ()), _audit)
    for name in ("stat", "lstat"):        # no audit event for these: watch them directly
        real = getattr(os, name)

        def watched(path, *a, _real=real, _name=name, **kw):
            if _WATCHED["bad"] and _WATCHED["bad"] in str(path):
                _WATCHED["hits"].append((_name, path))
            return _real(path, *a, **kw)

        monkeypatch.setattr(os, name, watched)
    _WATCHED.update(bad=bad or None, hits=[])
    try:
        assert store.get(bad) is None
        assert store.delete(bad) is False
        assert store.update(bad, state="ready") is None
        assert store.fail(bad, "x", "y") is None
        store.touch(bad)
        with pytest.raises(KeyError):
            store.scene_dir(bad)
    finally:
        hits = list(_WATCHED["hits"])
        _WATCHED.update(bad=None, hits=[])
    assert hits == []
    assert store.list()[1] == 1
    assert not (tmp_path / "x").exists() and not (tmp_path / "st" / "a").exists()


def test_a_new_scene_id_never_starts_with_a_dash():
    """A command line takes a word that starts with "-" for an option; 1 URL-safe id in 64 did (2000 draws: a
    leading "-" would show up with probability 1 - (63/64)^2000 > 0.999999999)."""
    ids = [new_scene_id() for _ in range(2000)]
    assert all(SCENE_ID.match(s) and not s.startswith("-") for s in ids)
    assert len(set(ids)) == len(ids)
