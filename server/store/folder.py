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
rendered or downloaded), ``"reject"`` raises StoreFull (507). ``ttl_s`` deletes scenes unused for that long. The
decisions are base.BaseStore's, shared with the S3 store (s3.py); both implement base.Store. Records are
record.SceneRecord, kept unchanged in memory (a change replaces one) and handed out as copies.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from xyzcyl.common.files import atomic_file

from .base import (
    SCENE_ID,
    STATES,
    TOUCH_PERSIST_S,
    BaseStore,
    SceneRecord,
    StoreFull,
    check_id,
    folder_bytes,
    interrupted_message,
    new_scene_id,
    newest_first,
    remove_folder,
    valid_id,
)


def _now() -> float:
    return time.time()


def _write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    with atomic_file(path, "w", fsync=True) as f:
        json.dump(doc, f, allow_nan=False)


class FolderStore(BaseStore):
    def __init__(self, root: str | os.PathLike, max_scenes: int = 100, max_bytes: int = 10 << 30,
                 when_full: str = "evict", ttl_s: float | None = None):
        super().__init__(max_scenes=max_scenes, max_bytes=max_bytes, when_full=when_full, ttl_s=ttl_s)
        self.root = Path(root)
        self._records: dict[str, SceneRecord] = {}
        self._persisted_use: dict[str, float] = {}
        self._lock = threading.RLock()

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
                    rec = SceneRecord.parse(sid, json.loads(p.read_text()))
                    if rec is None:
                        raise ValueError("not a record")
                except (OSError, ValueError):
                    p.unlink(missing_ok=True)        # a stray or damaged file: never half-visible
                    report["orphans"] += 1
                    continue
                self._records[sid] = rec
            for sid, rec in list(self._records.items()):
                folder = self._scene_path(sid)
                if rec.state in ("queued", "running"):
                    self._fail_locked(sid, "interrupted", interrupted_message(rec.state))
                    report["interrupted"] += 1
                elif rec.state == "ready":
                    if (folder / "scene.json").is_file():
                        report["ready"] += 1
                        self._persisted_use[sid] = rec.last_used if rec.last_used is not None else rec.created_ts
                    else:
                        self._fail_locked(sid, "files_missing", "the scene's files are missing from the store")
                        report["files_missing"] += 1
            for p in (self.root / "scenes").iterdir():
                rec = self._records.get(p.name)
                if rec is None or rec.state != "ready":
                    self._remove_folder(p)
                    report["orphans"] += 1
        return report

    # -- paths --------------------------------------------------------------------------------------------------
    def _scene_path(self, sid: str) -> Path:
        return self.root / "scenes" / check_id(sid)

    def _record_path(self, sid: str) -> Path:
        return self.root / "records" / f"{check_id(sid)}.json"

    def scene_dir(self, sid: str) -> Path:
        """The folder of a ready scene (KeyError when unknown or not ready)."""
        rec = self.get(sid)
        if rec is None or rec.state != "ready":
            raise KeyError(sid)
        return self._scene_path(sid)

    def work_dir(self) -> Path:
        """A new empty folder under tmp/ for an upload or a reconstruction (the caller removes it)."""
        d = self.root / "tmp" / secrets.token_hex(8)
        d.mkdir(parents=True)
        return d

    # -- records ------------------------------------------------------------------------------------------------
    def get(self, sid: str) -> SceneRecord | None:
        if not valid_id(sid):
            return None
        with self._lock:
            rec = self._records.get(sid)
            return None if rec is None else rec.model_copy(deep=True)

    def reload(self, sid: str) -> SceneRecord | None:
        """The record of ``sid`` as its file holds it now, taken into memory (None, and forgotten, when there is
        none or it is damaged): for a store folder that other processes write too (`xyzcyl batch`'s tasks each
        hold a FolderStore of one folder without open(), which would empty the others' tmp/)."""
        if not valid_id(sid):
            return None
        try:
            rec = SceneRecord.parse(sid, json.loads(self._record_path(sid).read_text()))
        except (OSError, ValueError):
            rec = None
        with self._lock:
            if rec is None:
                self._records.pop(sid, None)
                return None
            self._records[sid] = rec
            return rec.model_copy(deep=True)

    def list(self, offset: int = 0, limit: int = 100) -> tuple[list[SceneRecord], int]:
        """Records, newest first, and the total count."""
        with self._lock:
            recs = newest_first(self._records.values())
            page = [r.model_copy(deep=True) for r in recs[offset:offset + limit]]
            return page, len(recs)

    def create(self, sid: str, record: Mapping[str, Any]) -> SceneRecord:
        """A new ``queued`` record; makes room under the scene-count quota first (StoreFull when it cannot)."""
        rec = SceneRecord.queued(sid, record, _now())
        with self._lock:
            if sid in self._records:
                raise ValueError(f"scene id {sid} exists")
            for old in self.failed_beyond_quota(list(self._records.values())):
                self.delete(old)
            self._evict(self.room_for_scene(list(self._records.values()), exclude=sid))
            self._records[sid] = rec
            try:
                self._persist(sid)
            except BaseException:       # not on disk (disk full, bad id): not in the store either
                del self._records[sid]
                raise
            return rec.model_copy(deep=True)

    def update(self, sid: str, **fields: Any) -> SceneRecord | None:
        """Change fields of a record (None when it was deleted meanwhile)."""
        with self._lock:
            rec = self._records.get(sid)
            if rec is None:
                return None
            self._records[sid] = rec = rec.updated(_now(), **fields)
            self._persist(sid)
            return rec.model_copy(deep=True)

    def fail(self, sid: str, code: str, message: str) -> SceneRecord | None:
        with self._lock:
            if sid not in self._records:
                return None
            self._fail_locked(sid, code, message)
            return self._records[sid].model_copy(deep=True)

    def _fail_locked(self, sid: str, code: str, message: str) -> None:
        self._records[sid] = self._records[sid].failed(code, message, _now())
        self._persist(sid)

    def _persist(self, sid: str) -> None:
        _write_json_atomic(self._record_path(sid), self._records[sid].to_json())

    def commit(self, sid: str, folder: Path, **fields: Any) -> SceneRecord | None:
        """Move a finished scene folder into place and mark the record ready (with ``fields``); then keep the byte
        quota by evicting least recently used scenes. None when the record was deleted meanwhile (the folder is
        removed). StoreFull when this scene alone is over the quota, or the disk is full."""
        size = folder_bytes(folder)
        with self._lock:
            if sid not in self._records:
                self._remove_folder(folder)
                return None
            try:
                victims = self.room_for_bytes(list(self._records.values()), sid, size)
            except StoreFull:
                self._remove_folder(folder)
                raise
            self._evict(victims)
            os.replace(folder, self._scene_path(sid))
            now = _now()
            self._records[sid] = rec = self._records[sid].ready(size, now, **fields)
            self._persisted_use[sid] = now
            self._persist(sid)
            return rec.model_copy(deep=True)

    def touch(self, sid: str) -> None:
        """Mark a scene used now (for LRU eviction and the TTL)."""
        now = _now()
        with self._lock:
            rec = self._records.get(sid)
            if rec is None:
                return
            self._records[sid] = rec.replace(last_used=now)
            if now - self._persisted_use.get(sid, 0.0) >= TOUCH_PERSIST_S:
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
        self._notify_deleted(sid)
        return True

    def _remove_folder(self, folder: Path) -> None:
        remove_folder(folder, self.root / "tmp")

    # -- quota ----------------------------------------------------------------------------------------------------
    def _evict(self, victims: list[str]) -> None:
        for sid in victims:
            self.delete(sid)
            self.evicted += 1

    def sweep(self, now: float | None = None) -> list[str]:
        """Delete scenes unused for longer than ttl_s (ready and failed). Returns the removed ids."""
        if self.ttl_s is None:
            return []
        now = _now() if now is None else now
        with self._lock:
            old = self.expired(list(self._records.values()), now)
        for sid in old:
            self.delete(sid)
        return old

    def usage(self) -> dict[str, Any]:
        with self._lock:
            return self.usage_of(list(self._records.values()))


__all__ = ["SCENE_ID", "STATES", "FolderStore", "StoreFull", "folder_bytes", "new_scene_id"]
