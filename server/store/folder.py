"""The folder store: every scene as a record file and, once ready, a scene folder (runtime.scene's format).

    STORE/records/<id>.json   state queued | running | ready | failed, metadata, error (written atomically:
                              temporary file + os.replace)
    STORE/scenes/<id>/        scene.ply, background.exr/png, scene.json (renamed into place whole)
    STORE/tmp/                uploads and reconstructions in progress (emptied when the store opens)

A scene is ``ready`` only after its folder has been renamed into place, so a crash at any moment leaves either
no folder or a whole one. When the store opens, records left ``queued``/``running`` by a process that died become
``failed`` (code ``interrupted``), folders without a ready record are removed, and ready records whose folder is
gone become ``failed`` (``files_missing``). Ids come from ``secrets`` (128 bits) and are matched against
SCENE_ID before any path is built from them.

Quota: at most ``max_scenes`` records (not counting failed ones) and ``max_bytes`` of ready scene folders. When a
new scene would exceed them, ``when_full="evict"`` deletes the least recently used ready scenes (use = created,
rendered or downloaded), ``"reject"`` raises StoreFull (507). ``ttl_s`` deletes scenes unused for that long.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

SCENE_ID = re.compile(r"^[A-Za-z0-9_-]{22}$")
STATES = ("queued", "running", "ready", "failed")
_TOUCH_PERSIST_S = 60.0     # last_used is written to the record at most this often per scene (renders are hot)


class StoreFull(OSError):
    """The store's quota (or the disk) cannot take the scene."""


def new_scene_id() -> str:
    """22 URL-safe characters, 128 random bits (unguessable, not enumerable)."""
    return secrets.token_urlsafe(16)


def _now() -> float:
    return time.time()


def folder_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "w") as f:
            json.dump(doc, f, allow_nan=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


class FolderStore:
    def __init__(self, root: str | os.PathLike, max_scenes: int = 100, max_bytes: int = 10 << 30,
                 when_full: str = "evict", ttl_s: float | None = None):
        self.root = Path(root)
        self.max_scenes = int(max_scenes)
        self.max_bytes = int(max_bytes)
        self.when_full = when_full
        self.ttl_s = ttl_s
        self._records: dict[str, dict[str, Any]] = {}
        self._persisted_use: dict[str, float] = {}
        self._lock = threading.RLock()
        self.on_delete: list[Callable[[str], None]] = []    # called with the id after a scene is removed
        self.evicted = 0

    # -- opening and recovery ---------------------------------------------------------------------------------
    def open(self) -> dict[str, int]:
        """Create the folders, empty tmp/, load the records and recover from a crash (see the module doc).
        Returns what was recovered: {"ready", "interrupted", "files_missing", "orphans"}."""
        for sub in ("records", "scenes", "tmp"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        for p in (self.root / "tmp").iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
        report = {"ready": 0, "interrupted": 0, "files_missing": 0, "orphans": 0}
        with self._lock:
            self._records.clear()
            for p in (self.root / "records").glob("*.json"):
                sid = p.stem
                try:
                    rec = json.loads(p.read_text())
                    if not SCENE_ID.match(sid) or rec.get("id") != sid or rec.get("state") not in STATES:
                        raise ValueError("not a record")
                except (OSError, ValueError):
                    p.unlink(missing_ok=True)        # a stray or damaged file: never half-visible
                    report["orphans"] += 1
                    continue
                self._records[sid] = rec
            for sid, rec in list(self._records.items()):
                folder = self._scene_path(sid)
                if rec["state"] in ("queued", "running"):
                    self._fail_locked(sid, "interrupted", "the server stopped while this reconstruction was "
                                      f"{rec['state']}; post the rig again")
                    report["interrupted"] += 1
                elif rec["state"] == "ready":
                    if (folder / "scene.json").is_file():
                        report["ready"] += 1
                        self._persisted_use[sid] = rec.get("last_used", rec.get("created_ts", 0.0))
                    else:
                        self._fail_locked(sid, "files_missing", "the scene's files are missing from the store")
                        report["files_missing"] += 1
            for p in (self.root / "scenes").iterdir():
                rec = self._records.get(p.name)
                if rec is None or rec["state"] != "ready":
                    self._remove_folder(p)
                    report["orphans"] += 1
        return report

    # -- paths --------------------------------------------------------------------------------------------------
    def _scene_path(self, sid: str) -> Path:
        if not SCENE_ID.match(sid):
            raise KeyError(sid)
        return self.root / "scenes" / sid

    def _record_path(self, sid: str) -> Path:
        if not SCENE_ID.match(sid):
            raise KeyError(sid)
        return self.root / "records" / f"{sid}.json"

    def scene_dir(self, sid: str) -> Path:
        """The folder of a ready scene (KeyError when unknown or not ready)."""
        rec = self.get(sid)
        if rec is None or rec["state"] != "ready":
            raise KeyError(sid)
        return self._scene_path(sid)

    def work_dir(self) -> Path:
        """A new empty folder under tmp/ for an upload or a reconstruction (the caller removes it)."""
        d = self.root / "tmp" / secrets.token_hex(8)
        d.mkdir(parents=True)
        return d

    # -- records ------------------------------------------------------------------------------------------------
    def get(self, sid: str) -> dict[str, Any] | None:
        if not isinstance(sid, str) or not SCENE_ID.match(sid):
            return None
        with self._lock:
            rec = self._records.get(sid)
            return None if rec is None else json.loads(json.dumps(rec))

    def list(self, offset: int = 0, limit: int = 100) -> tuple[list[dict[str, Any]], int]:
        """Records, newest first, and the total count."""
        with self._lock:
            recs = sorted(self._records.values(), key=lambda r: (r.get("created_ts", 0.0), r["id"]), reverse=True)
            page = [json.loads(json.dumps(r)) for r in recs[offset:offset + limit]]
            return page, len(recs)

    def _live(self) -> list[dict[str, Any]]:
        return [r for r in self._records.values() if r["state"] != "failed"]

    def create(self, sid: str, record: dict[str, Any]) -> dict[str, Any]:
        """A new ``queued`` record; makes room under the scene-count quota first (StoreFull when it cannot)."""
        now = _now()
        rec = {**record, "id": sid, "state": "queued", "created_ts": now, "updated_ts": now, "error": None}
        with self._lock:
            if sid in self._records:
                raise ValueError(f"scene id {sid} exists")
            self._drop_failed_beyond_quota()
            while len(self._live()) >= self.max_scenes:
                if self.when_full != "evict" or not self._evict_one(exclude=sid):
                    raise StoreFull(f"the store holds its maximum of {self.max_scenes} scenes; delete some "
                                    "(DELETE /v1/scenes/{id})")
            self._records[sid] = rec
            try:
                self._persist(sid)
            except BaseException:       # not on disk (disk full, bad id): not in the store either
                del self._records[sid]
                raise
            return json.loads(json.dumps(rec))

    def update(self, sid: str, **fields: Any) -> dict[str, Any] | None:
        """Change fields of a record (None when it was deleted meanwhile)."""
        with self._lock:
            rec = self._records.get(sid)
            if rec is None:
                return None
            rec.update(fields, updated_ts=_now())
            self._persist(sid)
            return json.loads(json.dumps(rec))

    def fail(self, sid: str, code: str, message: str) -> dict[str, Any] | None:
        with self._lock:
            if sid not in self._records:
                return None
            self._fail_locked(sid, code, message)
            return json.loads(json.dumps(self._records[sid]))

    def _fail_locked(self, sid: str, code: str, message: str) -> None:
        rec = self._records[sid]
        rec.update(state="failed", error={"code": code, "message": message}, updated_ts=_now())
        self._persist(sid)

    def _persist(self, sid: str) -> None:
        _write_json_atomic(self._record_path(sid), self._records[sid])

    def commit(self, sid: str, folder: Path, **fields: Any) -> dict[str, Any] | None:
        """Move a finished scene folder into place and mark the record ready (with ``fields``); then keep the byte
        quota by evicting least recently used scenes. None when the record was deleted meanwhile (the folder is
        removed). StoreFull when this scene alone is over the quota, or the disk is full."""
        size = folder_bytes(folder)
        with self._lock:
            if sid not in self._records:
                self._remove_folder(folder)
                return None
            if size > self.max_bytes:
                self._remove_folder(folder)
                raise StoreFull(f"the scene needs {size} bytes, more than the store's quota of {self.max_bytes}")
            while self._ready_bytes() + size > self.max_bytes:
                if self.when_full != "evict" or not self._evict_one(exclude=sid):
                    self._remove_folder(folder)
                    raise StoreFull(f"the store's quota of {self.max_bytes} bytes is used; delete some scenes")
            os.replace(folder, self._scene_path(sid))
            now = _now()
            rec = self._records[sid]
            rec.update(fields, state="ready", bytes=size, last_used=now, updated_ts=now, error=None)
            self._persisted_use[sid] = now
            self._persist(sid)
            return json.loads(json.dumps(rec))

    def touch(self, sid: str) -> None:
        """Mark a scene used now (for LRU eviction and the TTL)."""
        now = _now()
        with self._lock:
            rec = self._records.get(sid)
            if rec is None:
                return
            rec["last_used"] = now
            if now - self._persisted_use.get(sid, 0.0) >= _TOUCH_PERSIST_S:
                self._persisted_use[sid] = now
                try:
                    self._persist(sid)
                except OSError:
                    pass       # a full disk must not fail a render; the in-memory time still counts

    def delete(self, sid: str) -> bool:
        """Remove a scene (record first, then its folder). False when unknown."""
        with self._lock:
            if sid not in self._records:
                return False
            del self._records[sid]
            self._persisted_use.pop(sid, None)
            self._record_path(sid).unlink(missing_ok=True)
            self._remove_folder(self._scene_path(sid))
        for cb in self.on_delete:
            cb(sid)
        return True

    def _remove_folder(self, folder: Path) -> None:
        if not folder.exists():
            return
        trash = self.root / "tmp" / f"deleted-{secrets.token_hex(6)}"
        try:
            os.replace(folder, trash)      # invisible at once, then removed
        except OSError:
            trash = folder
        shutil.rmtree(trash, ignore_errors=True)

    # -- quota ----------------------------------------------------------------------------------------------------
    def _ready_bytes(self) -> int:
        return sum(int(r.get("bytes", 0)) for r in self._records.values() if r["state"] == "ready")

    def _evict_one(self, exclude: str) -> bool:
        ready = [r for r in self._records.values() if r["state"] == "ready" and r["id"] != exclude]
        if not ready:
            return False
        victim = min(ready, key=lambda r: r.get("last_used", 0.0))["id"]
        self.delete(victim)
        self.evicted += 1
        return True

    def _drop_failed_beyond_quota(self) -> None:
        """Failed records are kept for inspection, at most max_scenes of them (oldest dropped)."""
        failed = sorted((r for r in self._records.values() if r["state"] == "failed"),
                        key=lambda r: r.get("updated_ts", 0.0))
        for r in failed[:max(0, len(failed) - self.max_scenes)]:
            self.delete(r["id"])

    def sweep(self, now: float | None = None) -> list[str]:
        """Delete scenes unused for longer than ttl_s (ready and failed). Returns the removed ids."""
        if self.ttl_s is None:
            return []
        now = _now() if now is None else now
        with self._lock:
            old = [r["id"] for r in self._records.values() if r["state"] in ("ready", "failed")
                   and now - r.get("last_used", r.get("updated_ts", 0.0)) > self.ttl_s]
        for sid in old:
            self.delete(sid)
        return old

    def usage(self) -> dict[str, Any]:
        with self._lock:
            states = {s: 0 for s in STATES}
            for r in self._records.values():
                states[r["state"]] += 1
            return {"scenes": states, "bytes": self._ready_bytes(), "max_scenes": self.max_scenes,
                    "max_bytes": self.max_bytes, "evicted": self.evicted}


__all__ = ["SCENE_ID", "STATES", "FolderStore", "StoreFull", "folder_bytes", "new_scene_id"]
