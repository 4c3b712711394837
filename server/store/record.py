"""A scene's id and record, as every store keeps them.

Ids are 22 URL-safe characters (128 random bits, ``new_scene_id``), matched against SCENE_ID before any path or
object key is built from one (``check_id``). The record holds a scene's state, its metadata and, once failed,
its error:

    {"cameras": [...], "detail": {"enabled": true, "stride": 2}, "name": "clipgt-...", "id": "...", "state": "ready",
     "created_ts": 1764092077.4, "updated_ts": 1764092082.9, "error": null, "model": {...}, "counts": {...},
     "timings": {...}, "bbox": {...}, "gaussians": 544123, "background": true, "bytes": 38442211,
     "last_used": 1764092082.9}

SceneRecord is that JSON (STORE/records/<id>.json in the folder store, prefix/records/<id>.json in S3) with
explicit fields, in the order the stores have always written them. ``to_json`` writes back exactly the keys that
were read or set (a key that was absent stays absent: older records have no ``detail``, test records no
``cameras``), and keys it does not know are kept as they are, so records written before this class load and
round-trip unchanged. Changes make a new record (``replace`` and the state changes below): the stores keep
theirs unchanged and hand out copies."""

from __future__ import annotations

import re
import secrets
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict
from xyzcyl.common.wire import STATES, CameraInfo, DetailInfo, DriveInfo, SceneState

SCENE_ID = re.compile(r"^[A-Za-z0-9_-]{22}$")
# a scene's optional name (POST /v1/scenes?name=): a simulator's scene id such as AlpaSim's "clipgt-<uuid>"
SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._:/+=@-]{0,199}$")


def new_scene_id() -> str:
    """22 URL-safe characters, 128 random bits (unguessable, not enumerable), never starting with "-" (a command
    line takes such a word for an option: the client's CLI accepts one, other tools may not)."""
    while True:
        sid = secrets.token_urlsafe(16)
        if not sid.startswith("-"):
            return sid


def valid_id(sid: Any) -> bool:
    return isinstance(sid, str) and SCENE_ID.match(sid) is not None


def name_error(name: str) -> str | None:
    """Why ``name`` cannot name a scene (None: it can): SCENE_NAME's characters and length, and not of an id's
    form (a name and an id must never be mistaken for each other where either is accepted)."""
    if not SCENE_NAME.match(name):
        return ("1 to 200 characters: letters, digits and . _ : / + = @ -, starting with a letter or a digit "
                f"(got {name[:60]!r})")
    if valid_id(name):
        return f"{name!r} has the form of a scene id (22 characters of A-Z a-z 0-9 _ -); give a name that does not"
    return None


def check_id(sid: Any) -> str:
    """The id itself, or KeyError before any path or object key is built from a malformed one."""
    if not valid_id(sid):
        raise KeyError(sid)
    return sid


class SceneFailure(BaseModel):
    """Why a scene failed: ``code`` (invalid_input, worker_crashed, timeout, storage_full, interrupted,
    files_missing, ...; docs/api.md) and a message for people."""

    model_config = ConfigDict(frozen=True, extra="allow")

    code: str
    message: str


class SceneRecord(BaseModel):
    model_config = ConfigDict(extra="allow", validate_assignment=True)

    # the fields in the order today's stores write them (the JSON keeps it)
    cameras: list[CameraInfo] = []              # the rig's cameras as posted (name, width, height, model)
    detail: DetailInfo | None = None            # the detail layer asked for; absent for scenes posted before it
    name: str | None = None                     # POST /v1/scenes?name= (e.g. a simulator's scene id); absent: none
    id: str
    state: SceneState
    created_ts: float = 0.0                     # time.time() of the POST
    updated_ts: float = 0.0                     # of the last change
    error: SceneFailure | None = None           # set while failed
    owner: str | None = None                    # the S3 store's replica that runs the job
    model: dict[str, Any] | None = None         # from here on: set when ready (the worker's scene metadata)
    counts: dict[str, Any] | None = None
    timings: dict[str, Any] | None = None
    bbox: dict[str, Any] | None = None
    gaussians: int | None = None
    background: bool | None = None
    bytes: int | None = None                    # the scene folder's size
    last_used: float | None = None              # created, rendered or downloaded (LRU eviction, TTL)
    files: list[str] | None = None              # the S3 store: the scene's files under prefix/scenes/<id>/
    drive: DriveInfo | None = None              # a posted drive's frames and keyframes; absent for one rig

    # -- JSON ---------------------------------------------------------------------------------------------------
    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> SceneRecord:
        """The record of its JSON (a pydantic ValidationError, a ValueError, when it is not one)."""
        return cls.model_validate(dict(doc))

    @classmethod
    def parse(cls, sid: str, doc: Any) -> SceneRecord | None:
        """The record that the JSON ``doc`` stored under ``sid`` holds, or None when it is not a well-formed record
        of that scene (a stray or damaged file)."""
        if not (valid_id(sid) and isinstance(doc, dict) and doc.get("id") == sid and doc.get("state") in STATES):
            return None
        try:
            return cls.from_json(doc)
        except ValueError:
            return None

    def to_json(self) -> dict[str, Any]:
        """The JSON the stores write: the keys that were read or set, in the fields' order, then unknown keys."""
        return self.model_dump(mode="json", exclude_unset=True)

    # -- changes: each makes a new record -----------------------------------------------------------------------
    def replace(self, **fields: Any) -> SceneRecord:
        """A copy with ``fields`` set (TypeError for a name that is not a field; values are checked)."""
        unknown = sorted(set(fields) - set(type(self).model_fields))
        if unknown:
            raise TypeError(f"not a field of a scene record: {', '.join(unknown)}")
        return self.from_json({**self.to_json(), **fields})

    @classmethod
    def queued(cls, sid: str, fields: Mapping[str, Any], now: float) -> SceneRecord:
        """A new scene's record: ``fields`` (cameras, detail) with the id, state queued and the times."""
        return cls.from_json({**fields, "id": sid, "state": "queued", "created_ts": now, "updated_ts": now,
                              "error": None})

    def updated(self, now: float, **fields: Any) -> SceneRecord:
        return self.replace(**fields, updated_ts=now)

    def failed(self, code: str, message: str, now: float) -> SceneRecord:
        return self.replace(state="failed", error=SceneFailure(code=code, message=message), updated_ts=now)

    def ready(self, size: int, now: float, **fields: Any) -> SceneRecord:
        """Ready with the worker's ``fields`` (model, counts, timings, bbox, gaussians, background), ``size`` bytes,
        used now."""
        return self.replace(**fields, state="ready", bytes=int(size), last_used=now, updated_ts=now, error=None)

    @property
    def last_use(self) -> float:
        """When it was last used: ``last_used``, else its last change."""
        return self.last_used if self.last_used is not None else self.updated_ts


__all__ = ["SCENE_ID", "SCENE_NAME", "STATES", "SceneFailure", "SceneRecord", "check_id", "name_error", "new_scene_id",
           "valid_id"]
