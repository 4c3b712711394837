"""What every store backend shares: scene ids, the record's shape and states, and the quota decisions.

A record is a JSON object ``{"id", "state", "created_ts", "updated_ts", "error", ...}`` with ``state`` one of
STATES; a ready record also has ``bytes`` and ``last_used``. The quota functions below only *decide* (which
scenes to evict, whether the store is full): they take the records as a list and return ids, so the folder store
(records in memory) and the S3 store (records from a listing) apply the same rules:

- ``max_scenes`` counts queued, running and ready records (failed ones are kept for inspection, at most
  ``max_scenes`` of them, oldest dropped first);
- ``max_bytes`` counts the bytes of ready scenes;
- when a new scene does not fit, ``when_full="evict"`` deletes the least recently used ready scenes (use =
  created, rendered or downloaded) and ``"reject"`` raises StoreFull; nothing is evicted when eviction cannot
  make enough room;
- ``ttl_s`` expires ready and failed scenes unused for that long (work in progress never expires).
"""

from __future__ import annotations

import json
import re
import secrets
from collections.abc import Callable, Iterable
from typing import Any

SCENE_ID = re.compile(r"^[A-Za-z0-9_-]{22}$")
STATES = ("queued", "running", "ready", "failed")
TOUCH_PERSIST_S = 60.0     # last use is written to the store at most this often per scene (renders are hot)


class StoreFull(OSError):
    """The store's quota (or the disk) cannot take the scene."""


class StoreUnavailable(OSError):
    """The store cannot be reached (its object storage does not answer, refuses the credentials, or fails with a
    server error): the service answers 503 + Retry-After and /v2/health/ready turns 503 until it answers again.
    The message names no endpoint or bucket (the details are logged)."""


def new_scene_id() -> str:
    """22 URL-safe characters, 128 random bits (unguessable, not enumerable)."""
    return secrets.token_urlsafe(16)


def valid_id(sid: Any) -> bool:
    return isinstance(sid, str) and SCENE_ID.match(sid) is not None


def check_id(sid: Any) -> str:
    """The id itself, or KeyError before any path or object key is built from a malformed one."""
    if not valid_id(sid):
        raise KeyError(sid)
    return sid


def copy_record(rec: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(rec))


def is_record(sid: str, rec: Any) -> bool:
    """Whether ``rec`` (parsed JSON stored under ``sid``) is a well-formed record of that scene."""
    return valid_id(sid) and isinstance(rec, dict) and rec.get("id") == sid and rec.get("state") in STATES


def new_record(sid: str, record: dict[str, Any], now: float) -> dict[str, Any]:
    return {**record, "id": sid, "state": "queued", "created_ts": now, "updated_ts": now, "error": None}


def failed_fields(code: str, message: str, now: float) -> dict[str, Any]:
    return {"state": "failed", "error": {"code": code, "message": message}, "updated_ts": now}


def ready_fields(size: int, now: float) -> dict[str, Any]:
    return {"state": "ready", "bytes": int(size), "last_used": now, "updated_ts": now, "error": None}


def interrupted_message(state: str) -> str:
    return f"the server stopped while this reconstruction was {state}; post the rig again"


def newest_first(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    return sorted(records, key=lambda r: (r.get("created_ts", 0.0), r["id"]), reverse=True)


def _last_used(rec: dict[str, Any]) -> float:
    return float(rec.get("last_used", rec.get("updated_ts", 0.0)))


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
    def failed_beyond_quota(self, records: Iterable[dict[str, Any]]) -> list[str]:
        """Failed records beyond ``max_scenes`` of them, oldest first (to be deleted)."""
        failed = sorted((r for r in records if r["state"] == "failed"), key=lambda r: r.get("updated_ts", 0.0))
        return [r["id"] for r in failed[:max(0, len(failed) - self.max_scenes)]]

    def _lru_ready(self, records: Iterable[dict[str, Any]], exclude: str) -> list[dict[str, Any]]:
        return sorted((r for r in records if r["state"] == "ready" and r["id"] != exclude),
                      key=lambda r: r.get("last_used", 0.0))

    def room_for_scene(self, records: list[dict[str, Any]], exclude: str) -> list[str]:
        """The ready scenes to evict so that one more scene fits under ``max_scenes`` (StoreFull when it cannot,
        or when ``when_full`` is reject)."""
        need = sum(r["state"] != "failed" for r in records) - self.max_scenes + 1
        if need <= 0:
            return []
        full = StoreFull(f"the store holds its maximum of {self.max_scenes} scenes; delete some "
                         "(DELETE /v1/scenes/{id})")
        if self.when_full != "evict":
            raise full
        victims = self._lru_ready(records, exclude)
        if len(victims) < need:
            raise full
        return [r["id"] for r in victims[:need]]

    def room_for_bytes(self, records: list[dict[str, Any]], sid: str, size: int) -> list[str]:
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
            out.append(r["id"])
            used -= int(r.get("bytes", 0))
            if used + size <= self.max_bytes:
                return out
        raise full

    def expired(self, records: Iterable[dict[str, Any]], now: float) -> list[str]:
        """Ready and failed scenes unused for longer than ``ttl_s`` (none without a TTL)."""
        if self.ttl_s is None:
            return []
        return [r["id"] for r in records if r["state"] in ("ready", "failed") and now - _last_used(r) > self.ttl_s]

    @staticmethod
    def ready_bytes(records: Iterable[dict[str, Any]]) -> int:
        return sum(int(r.get("bytes", 0)) for r in records if r["state"] == "ready")

    def usage_of(self, records: list[dict[str, Any]]) -> dict[str, Any]:
        states = {s: 0 for s in STATES}
        for r in records:
            states[r["state"]] += 1
        return {"scenes": states, "bytes": self.ready_bytes(records), "max_scenes": self.max_scenes,
                "max_bytes": self.max_bytes, "evicted": self.evicted}


__all__ = ["SCENE_ID", "STATES", "TOUCH_PERSIST_S", "BaseStore", "StoreFull", "StoreUnavailable", "check_id",
           "copy_record", "failed_fields", "interrupted_message", "is_record", "new_record", "new_scene_id",
           "newest_first", "ready_fields", "valid_id"]
