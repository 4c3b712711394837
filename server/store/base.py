"""What every store backend shares: the Store protocol (what the service calls), the quota decisions, and helpers
for the local folders. Records and ids are record.py's.

The quota functions below only *decide* (which scenes to evict, whether the store is full): they take the records
as a list and return ids, so the folder store (records in memory) and the S3 store (records from a listing) apply
the same rules:

- ``max_scenes`` counts queued, running and ready records (failed ones are kept for inspection, at most
  ``max_scenes`` of them, oldest dropped first);
- ``max_bytes`` counts the bytes of ready scenes;
- when a new scene does not fit, ``when_full="evict"`` deletes the least recently used ready scenes (use =
  created, rendered or downloaded) and ``"reject"`` raises StoreFull; nothing is evicted when eviction cannot
  make enough room;
- ``ttl_s`` expires ready and failed scenes unused for that long (work in progress never expires).
"""

from __future__ import annotations

import builtins
import os
import secrets
import shutil
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from .record import SCENE_ID, STATES, SceneRecord, check_id, new_scene_id, valid_id

TOUCH_PERSIST_S = 60.0     # last use is written to the store at most this often per scene (renders are hot)


class StoreFull(OSError):
    """The store's quota (or the disk) cannot take the scene."""


class StoreUnavailable(OSError):
    """The store cannot be reached (its object storage does not answer, refuses the credentials, or fails with a
    server error): the service answers 503 + Retry-After and /v2/health/ready turns 503 until it answers again.
    The message names no endpoint or bucket (the details are logged)."""


@runtime_checkable
class Store(Protocol):
    """A scene store, as the service uses it: records (SceneRecord) and, once ready, the scene's folder.
    folder.FolderStore and s3.S3Store implement it (both on BaseStore's quota rules); open_store picks one.

    Every method is thread-safe and blocking (the service calls them in threads). An unknown or malformed id is
    simply unknown: None, False or KeyError, never a path built from it. ``on_delete`` callbacks get the id of
    each scene removed (deleted, evicted, expired, or found gone)."""

    max_scenes: int
    max_bytes: int
    when_full: str                       # "evict" | "reject"
    ttl_s: float | None
    evicted: int                         # scenes evicted by the quota since start
    on_delete: list[Callable[[str], None]]

    def open(self) -> dict[str, int]:
        """Prepare and recover after a crash: {"ready", "interrupted", "files_missing", "orphans"}."""

    def health(self) -> str | None:
        """None when the store can be used, else why not (/v2/health/ready's reason)."""

    def get(self, sid: str) -> SceneRecord | None:
        """A copy of the scene's record, or None."""

    def list(self, offset: int = 0, limit: int = 100) -> tuple[builtins.list[SceneRecord], int]:
        """A page of records, newest first, and the total count."""

    def create(self, sid: str, record: Mapping[str, Any]) -> SceneRecord:
        """A new ``queued`` record with the fields of ``record`` (cameras, detail); makes room under the
        scene-count quota first (StoreFull when it cannot; ValueError when the id exists)."""

    def update(self, sid: str, **fields: Any) -> SceneRecord | None:
        """Change fields of a record (None when it was deleted meanwhile)."""

    def fail(self, sid: str, code: str, message: str) -> SceneRecord | None:
        """Mark a scene failed with an error (None when it was deleted meanwhile)."""

    def commit(self, sid: str, folder: Path, **fields: Any) -> SceneRecord | None:
        """Take a finished scene folder into the store and mark the record ready with ``fields``, keeping the byte
        quota (StoreFull); None when the record was deleted meanwhile. The folder is gone afterwards."""

    def touch(self, sid: str) -> None:
        """Mark a scene used now (LRU eviction, TTL)."""

    def delete(self, sid: str) -> bool:
        """Remove a scene, record and files (False when unknown)."""

    def scene_dir(self, sid: str) -> Path:
        """The local folder of a ready scene (KeyError when unknown or not ready)."""

    def work_dir(self) -> Path:
        """A new empty local folder for an upload or a reconstruction (the caller removes it)."""

    def sweep(self, now: float | None = None) -> builtins.list[str]:
        """Delete the scenes unused for longer than ``ttl_s``; the removed ids."""

    def usage(self) -> dict[str, Any]:
        """For /metrics: {"scenes": {state: n}, "bytes", "max_scenes", "max_bytes", "evicted"}."""


def interrupted_message(state: str) -> str:
    return f"the server stopped while this reconstruction was {state}; post the rig again"


def newest_first(records: Iterable[SceneRecord]) -> list[SceneRecord]:
    return sorted(records, key=lambda r: (r.created_ts, r.id), reverse=True)


def folder_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def remove_folder(folder: Path, trash_dir: Path) -> None:
    """Remove ``folder``: renamed into ``trash_dir`` first (invisible at once), then removed."""
    if not folder.exists():
        return
    trash = trash_dir / f"deleted-{secrets.token_hex(6)}"
    try:
        os.replace(folder, trash)
    except OSError:
        trash = folder
    shutil.rmtree(trash, ignore_errors=True)


class BaseStore:
    """The quota settings and the decisions on them; subclasses hold the records and files."""

    def __init__(self, max_scenes: int = 100, max_bytes: int = 10 << 30, when_full: str = "evict",
                 ttl_s: float | None = None):
        self.max_scenes = int(max_scenes)
        self.max_bytes = int(max_bytes)
        self.when_full = when_full
        self.ttl_s = ttl_s
        self.on_delete: list[Callable[[str], None]] = []    # called with the id after a scene is removed
        self.evicted = 0

    def _notify_deleted(self, sid: str) -> None:
        for cb in self.on_delete:
            cb(sid)

    def health(self) -> str | None:
        """None when the store can be used, else why not (for /v2/health/ready). A local folder always can."""
        return None

    # -- quota decisions (pure: records in, ids out) -------------------------------------------------------------
    def failed_beyond_quota(self, records: Iterable[SceneRecord]) -> list[str]:
        """Failed records beyond ``max_scenes`` of them, oldest first (to be deleted)."""
        failed = sorted((r for r in records if r.state == "failed"), key=lambda r: r.updated_ts)
        return [r.id for r in failed[:max(0, len(failed) - self.max_scenes)]]

    def _lru_ready(self, records: Iterable[SceneRecord], exclude: str) -> list[SceneRecord]:
        return sorted((r for r in records if r.state == "ready" and r.id != exclude),
                      key=lambda r: r.last_used or 0.0)

    def room_for_scene(self, records: list[SceneRecord], exclude: str) -> list[str]:
        """The ready scenes to evict so that one more scene fits under ``max_scenes`` (StoreFull when it cannot,
        or when ``when_full`` is reject)."""
        need = sum(r.state != "failed" for r in records) - self.max_scenes + 1
        if need <= 0:
            return []
        full = StoreFull(f"the store holds its maximum of {self.max_scenes} scenes; delete some "
                         "(DELETE /v1/scenes/{id})")
        if self.when_full != "evict":
            raise full
        victims = self._lru_ready(records, exclude)
        if len(victims) < need:
            raise full
        return [r.id for r in victims[:need]]

    def room_for_bytes(self, records: list[SceneRecord], sid: str, size: int) -> list[str]:
        """The ready scenes to evict so that ``size`` more bytes fit under ``max_bytes`` (StoreFull when the scene
        alone is over the quota, when eviction cannot make room, or when ``when_full`` is reject)."""
        if size > self.max_bytes:
            raise StoreFull(f"the scene needs {size} bytes, more than the store's quota of {self.max_bytes}")
        used = self.ready_bytes(records)
        if used + size <= self.max_bytes:
            return []
        full = StoreFull(f"the store's quota of {self.max_bytes} bytes is used; delete some scenes")
        if self.when_full != "evict":
            raise full
        out = []
        for r in self._lru_ready(records, sid):
            out.append(r.id)
            used -= r.bytes or 0
            if used + size <= self.max_bytes:
                return out
        raise full

    def expired(self, records: Iterable[SceneRecord], now: float) -> list[str]:
        """Ready and failed scenes unused for longer than ``ttl_s`` (none without a TTL)."""
        if self.ttl_s is None:
            return []
        return [r.id for r in records if r.state in ("ready", "failed") and now - r.last_use > self.ttl_s]

    @staticmethod
    def ready_bytes(records: Iterable[SceneRecord]) -> int:
        return sum(r.bytes or 0 for r in records if r.state == "ready")

    def usage_of(self, records: list[SceneRecord]) -> dict[str, Any]:
        states = {s: 0 for s in STATES}
        for r in records:
            states[r.state] += 1
        return {"scenes": states, "bytes": self.ready_bytes(records), "max_scenes": self.max_scenes,
                "max_bytes": self.max_bytes, "evicted": self.evicted}


__all__ = ["SCENE_ID", "STATES", "TOUCH_PERSIST_S", "BaseStore", "SceneRecord", "Store", "StoreFull",
           "StoreUnavailable", "check_id", "folder_bytes", "interrupted_message", "new_scene_id", "newest_first",
           "remove_folder", "valid_id"]
