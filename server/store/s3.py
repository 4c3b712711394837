"""The S3 store: scenes on S3-compatible object storage (AWS S3, MinIO, ...), so that several replicas of the
service behind a load balancer serve every scene. Selected by ``XYZCYL_STORE=s3://bucket/prefix``; boto3 reads
the credentials, region and endpoint from the usual environment (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``,
``AWS_DEFAULT_REGION``, ``AWS_ENDPOINT_URL`` / ``AWS_ENDPOINT_URL_S3`` for a non-AWS server).

    prefix/records/<id>.json     the record (state, metadata, ``owner``): one PUT, atomic per object
    prefix/scenes/<id>/<file>    scene.ply, scene.json, background.exr/png (uploaded before the record is ready)
    prefix/used/<id>             empty marker rewritten (at most once a minute per replica) when a scene is used;
                                 its LastModified is the last use (LRU eviction, TTL)
    prefix/deleted/<id>          tombstone written before a delete (see below; removed an hour after the stale
                                 windows, by open, sweep and at most hourly by create, with orphan use markers)
    <s3_cache>/scenes/<id>/      this replica's downloaded copy of a ready scene (LRU, ``s3_cache_bytes``)
    <s3_cache>/tmp/              uploads and reconstructions in progress on this replica

Consistency. S3 reads are strongly consistent after writes (AWS since 2020, MinIO). A scene becomes ``ready`` by
writing its record *after* all its files are uploaded, so no reader sees a ready record with missing files. Every
replica reads records from S3 (``get`` does a GET; a ready record, immutable, is cached for ``record_ttl_s``;
``list`` re-reads only records whose ETag changed), so a scene posted to replica A is visible and renderable from
replica B. ``scene_dir(id)`` downloads the scene's files once into the local cache (temporary folder, then a
rename) and returns that folder; ``work_dir()`` is local: the replica that took the POST reconstructs and uploads.

Delete: tombstone, record, then the files (listed, batch-deleted) and the use marker. The owner of a job checks
the tombstone after each record write and deletes again when it lost the race, so a delete from replica B is
never undone by replica A finishing the reconstruction. Other replicas drop their cached copy (files and loaded
scene, through ``on_delete``) when they next find the record gone: within ``record_ttl_s`` for renders.

Recovery. ``open()`` fails (code ``interrupted``) the queued/running records that this replica owns (``owner`` ==
``replica_id``: the same replica restarted) and those of any owner not updated for longer than the stale windows
(a dead replica's jobs): ``running`` after ``reconstruct_timeout_s`` + 120 s, ``queued`` after that times the
number of job slots ahead of it. ``get``/``list``/``sweep`` apply the same rule to other owners' records. Scene
files without a record are removed by ``open()``; ready records whose scene.json is gone become ``files_missing``.

Quota (``max_scenes``, ``max_bytes``, ``when_full``, ``ttl_s``: base.BaseStore's rules) is computed from a
listing of records and use markers at the time of each create/commit/sweep. It is approximate with several
replicas: two replicas that create at the same moment can both pass the count check (over by at most one scene
per concurrent replica), a use is seen by others only once its marker is written (up to a minute late), and the
TTL compares the object store's clock (LastModified) with this replica's. ``evicted`` counts this replica's
evictions.

Outages. When the bucket stops answering after start-up (connection refused or timed out, credentials refused,
5xx), every public method raises base.StoreUnavailable (the service: 503 + Retry-After) instead of botocore's
error, and for OUTAGE_HOLD_S after each such failure calls fail at once without trying S3 (a request does not sit
through boto3's retries again for every client); then the next call tries S3 again. ``health()``
(/v2/health/ready) reports the outage, probing the bucket with one short HEAD at most every PROBE_TTL_S; it is
ready again as soon as a probe succeeds. Connection attempts give up after CONNECT_TIMEOUT_S.
"""

from __future__ import annotations

import atexit
import concurrent.futures as cf
import functools
import json
import logging
import os
import secrets
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from xyzcyl.common.files import atomic_folder

from .base import (
    TOUCH_PERSIST_S,
    BaseStore,
    SceneRecord,
    StoreFull,
    StoreUnavailable,
    check_id,
    folder_bytes,
    interrupted_message,
    newest_first,
    remove_folder,
    valid_id,
)

log = logging.getLogger("xyzcyl.server")

STALE_MARGIN_S = 120.0        # beyond the reconstruction timeout: the upload of the scene's files
_CACHE_GRACE_S = 10.0         # a local copy used this recently is never evicted (a render may be opening it)
USAGE_TTL_S = 5.0             # /metrics lists the bucket at most this often
OUTAGE_HOLD_S = 2.0           # after a failure that says the bucket is unreachable, calls fail at once this long
PROBE_TTL_S = 2.0             # health() HEADs the bucket at most this often
CONNECT_TIMEOUT_S = 5.0       # boto3's default is 60 s per attempt: an unreachable endpoint held requests minutes
PROBE_TIMEOUT_S = 2.0         # health()'s HEAD: one attempt, connect and read
# ClientError codes that mean the bucket cannot be used now (besides any 5xx status)
_OUTAGE_CODES = {"SlowDown", "RequestTimeout", "Throttling", "ThrottlingException", "RequestLimitExceeded",
                 "ServiceUnavailable", "InternalError", "AccessDenied", "InvalidAccessKeyId", "ExpiredToken",
                 "InvalidToken", "SignatureDoesNotMatch", "RequestTimeTooSkewed", "NoSuchBucket"}


def _now() -> float:
    return time.time()


def default_replica_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def parse_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` -> ("bucket", "some/prefix/"); the prefix is "" without one."""
    if not url.startswith("s3://"):
        raise ValueError(f"not an s3:// URL: {url!r}")
    bucket, _, prefix = url[5:].partition("/")
    if not bucket:
        raise ValueError(f"no bucket in {url!r} (s3://bucket/prefix)")
    prefix = prefix.strip("/")
    return bucket, (prefix + "/" if prefix else "")


def _missing(e: Exception) -> bool:
    """A ClientError that says the object (or key) does not exist."""
    err = getattr(e, "response", {}).get("Error", {})
    return str(err.get("Code")) in ("NoSuchKey", "404", "NotFound")


def _outage(e: BaseException) -> bool:
    """Whether an exception from boto3 says that the bucket cannot be reached or used now (network, timeouts,
    credentials, a 5xx or throttling answer, the bucket gone), as opposed to a missing object or a bug."""
    from boto3.exceptions import RetriesExceededError, S3TransferFailedError, S3UploadFailedError
    from botocore import exceptions as bx

    if isinstance(e, bx.ClientError):
        status = int(e.response.get("ResponseMetadata", {}).get("HTTPStatusCode") or 0)
        return status >= 500 or str(e.response.get("Error", {}).get("Code")) in _OUTAGE_CODES
    return isinstance(e, (bx.ConnectionError, bx.HTTPClientError, bx.NoCredentialsError, bx.PartialCredentialsError,
                          bx.CredentialRetrievalError, bx.IncompleteReadError, RetriesExceededError,
                          S3UploadFailedError, S3TransferFailedError))


def _reachable(method):
    """A public S3Store method whose outage errors become StoreUnavailable (see the module doc, "Outages")."""
    @functools.wraps(method)
    def call(self: S3Store, *args, **kwargs):
        self._fail_fast()
        try:
            out = method(self, *args, **kwargs)
        except StoreUnavailable:
            raise
        except Exception as e:
            if _outage(e):
                raise self._down(e) from e
            raise
        return out

    return call


class S3Store(BaseStore):
    def __init__(self, url: str, max_scenes: int = 100, max_bytes: int = 10 << 30, when_full: str = "evict",
                 ttl_s: float | None = None, cache_dir: str | os.PathLike | None = None,
                 cache_bytes: int = 2 << 30, replica_id: str | None = None, stale_running_s: float = 420.0,
                 stale_queued_s: float | None = None, record_ttl_s: float = 1.0, client=None):
        super().__init__(max_scenes=max_scenes, max_bytes=max_bytes, when_full=when_full, ttl_s=ttl_s)
        try:
            import boto3
            from botocore.config import Config
        except ImportError:
            raise OSError("the s3:// store needs boto3: pip install 'xyzcyl[server]'") from None
        self.url = url
        try:
            self.bucket, self.prefix = parse_url(url)
        except ValueError as e:
            raise OSError(str(e)) from None
        self.client = client or boto3.client("s3", config=Config(
            max_pool_connections=32, retries={"mode": "standard", "max_attempts": 5},
            connect_timeout=CONNECT_TIMEOUT_S))
        # health()'s client: one attempt with short timeouts (a readiness probe must answer within seconds)
        self.probe_client = client or boto3.client("s3", config=Config(
            retries={"mode": "standard", "max_attempts": 1}, connect_timeout=PROBE_TIMEOUT_S,
            read_timeout=PROBE_TIMEOUT_S))
        self._outage_at: float | None = None                     # time.monotonic() of the last outage error
        self._probed: tuple[float, str | None] | None = None      # (when, health()) of the last probe
        if cache_dir is None:
            cache_dir = tempfile.mkdtemp(prefix="xyzcyl-s3-cache-")
            atexit.register(shutil.rmtree, cache_dir, True)
        self.cache = Path(cache_dir)
        self.cache_bytes = int(cache_bytes)
        self.replica_id = replica_id or default_replica_id()
        self.stale_running_s = float(stale_running_s)
        self.stale_queued_s = float(stale_queued_s if stale_queued_s is not None else stale_running_s)
        self.record_ttl_s = float(record_ttl_s)
        self._lock = threading.RLock()                          # this replica's quota decisions
        self._ready: dict[str, tuple[SceneRecord, float]] = {}      # id -> (ready record, fetched at)
        self._etags: dict[str, tuple[str, SceneRecord]] = {}        # id -> (ETag, record) seen by a listing
        self._seen: set[str] = set()                            # ids this replica has served (to forget)
        self._used: dict[str, float] = {}                       # id -> last use here
        self._persisted_use: dict[str, float] = {}
        self._local: dict[str, list[float]] = {}                # id -> [bytes, last use] of local copies
        self._downloading: dict[str, threading.Lock] = {}
        self._pool: cf.ThreadPoolExecutor | None = None
        self._cleaned = 0.0                                     # when litter was last removed (time.time)
        self._opened = False
        self._usage: tuple[dict[str, Any], float] | None = None  # (usage, when) for /metrics

    # -- S3 helpers ---------------------------------------------------------------------------------------------
    def _key(self, *parts: str) -> str:
        return self.prefix + "/".join(parts)

    def _record_key(self, sid: str) -> str:
        return self._key("records", f"{check_id(sid)}.json")

    def _scene_prefix(self, sid: str) -> str:
        return self._key("scenes", check_id(sid)) + "/"

    def _objects(self, prefix: str) -> Iterator[dict[str, Any]]:
        for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix):
            yield from page.get("Contents", [])

    def _exists(self, key: str) -> bool:
        from botocore.exceptions import ClientError

        try:
            self.client.head_object(Bucket=self.bucket, Key=key)
            return True
        except ClientError as e:
            if _missing(e):
                return False
            raise

    def _read(self, sid: str) -> tuple[SceneRecord, str] | None:
        """(record, ETag) from S3, or None when there is none (or it is not a record)."""
        from botocore.exceptions import ClientError

        try:
            obj = self.client.get_object(Bucket=self.bucket, Key=self._record_key(sid))
            body = obj["Body"].read()
        except ClientError as e:
            if _missing(e):
                return None
            raise
        try:
            rec = SceneRecord.parse(sid, json.loads(body))
        except ValueError:
            return None
        return None if rec is None else (rec, obj.get("ETag", ""))

    def _write(self, rec: SceneRecord) -> None:
        self._usage = None
        self.client.put_object(Bucket=self.bucket, Key=self._record_key(rec.id),
                               Body=json.dumps(rec.to_json(), allow_nan=False).encode(),
                               ContentType="application/json")

    def _delete_keys(self, keys: list[str]) -> None:
        for i in range(0, len(keys), 1000):
            batch = keys[i:i + 1000]
            if batch:
                self.client.delete_objects(Bucket=self.bucket,
                                           Delete={"Objects": [{"Key": k} for k in batch], "Quiet": True})

    def _tombstoned(self, sid: str) -> bool:
        return self._exists(self._key("deleted", sid))

    # -- outages (module doc) -----------------------------------------------------------------------------------
    _UNREACHABLE = "the scene store cannot be reached; retry later"

    def _fail_fast(self) -> None:
        t = self._outage_at
        if t is not None and time.monotonic() - t < OUTAGE_HOLD_S:
            raise StoreUnavailable(self._UNREACHABLE)

    def _down(self, e: BaseException) -> StoreUnavailable:
        """Record an outage error (logged when it starts an outage, or a minute after the last one)."""
        now = time.monotonic()
        if self._outage_at is None or now - self._outage_at > 60.0:
            log.warning("the scene store %s cannot be reached (%s: %s); answering 503 until it can", self.url,
                        type(e).__name__, e)
        self._outage_at = now
        return StoreUnavailable(self._UNREACHABLE)

    def health(self) -> str | None:
        """None when the bucket answers, else why not (/v2/health/ready's reason): an outage seen by any call in the
        last OUTAGE_HOLD_S, else a HEAD of the bucket (one attempt, PROBE_TIMEOUT_S), at most every PROBE_TTL_S."""
        now = time.monotonic()
        if self._outage_at is not None and now - self._outage_at < OUTAGE_HOLD_S:
            return self._UNREACHABLE
        probed = self._probed
        if probed is not None and now - probed[0] < PROBE_TTL_S:
            return probed[1]
        try:
            self.probe_client.head_bucket(Bucket=self.bucket)
            reason = None
            if self._outage_at is not None:
                self._outage_at = None
                log.info("the scene store %s answers again", self.url)
        except Exception as e:      # noqa: BLE001 - any failure of the probe means "not ready"
            self._down(e)
            reason = self._UNREACHABLE
        self._probed = (time.monotonic(), reason)
        return reason

    # -- opening and recovery -----------------------------------------------------------------------------------
    def open(self) -> dict[str, int]:
        """Check the bucket, prepare the local cache and recover (see the module doc). Returns
        {"ready", "interrupted", "files_missing", "orphans"} as seen by this replica."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            self.client.head_bucket(Bucket=self.bucket)
        except (BotoCoreError, ClientError) as e:
            raise OSError(f"{self.url}: the bucket cannot be reached ({e})") from None
        for sub in ("scenes", "tmp"):
            (self.cache / sub).mkdir(parents=True, exist_ok=True)
        for p in (self.cache / "tmp").iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
        with self._lock:
            self._local.clear()
            for p in (self.cache / "scenes").iterdir():
                if valid_id(p.name) and (p / "scene.json").is_file():      # a copy kept from the last run
                    age = max(0.0, time.time() - p.stat().st_mtime)
                    self._local[p.name] = [float(folder_bytes(p)), time.monotonic() - age]
                else:
                    self._remove_local(p)
        report = {"ready": 0, "interrupted": 0, "files_missing": 0, "orphans": 0}
        files: dict[str, set[str]] = {}     # listed before the records: every file seen has its record listed
        for obj in self._objects(self._key("scenes") + "/"):
            sid, _, name = obj["Key"][len(self._key("scenes")) + 1:].partition("/")
            files.setdefault(sid, set()).add(name)
        records = {r.id: r for r in self._snapshot(expire=False)}
        now = _now()
        for sid, rec in records.items():
            if rec.state in ("queued", "running"):
                mine_or_dead = rec.owner == self.replica_id or self._stale(rec, now)
                if mine_or_dead and self._fail_record(rec, "interrupted", interrupted_message(rec.state)):
                    report["interrupted"] += 1
            elif rec.state == "ready":
                if "scene.json" in files.get(sid, ()) or self._exists(self._scene_prefix(sid) + "scene.json"):
                    report["ready"] += 1
                elif self._fail_record(rec, "files_missing", "the scene's files are missing from the store"):
                    report["files_missing"] += 1
        for sid, names in files.items():
            if sid not in records:           # a delete that stopped half-way (records are written first)
                self._delete_keys([self._key("scenes", sid, n) for n in names])
                report["orphans"] += 1
        for sid in list(self._local):
            rec = records.get(sid)
            if rec is None or rec.state != "ready":
                self._drop_local(sid)
        self._clean_litter(now, set(records))
        self._opened = True
        return report

    def _stale(self, rec: SceneRecord, now: float) -> bool:
        """A queued/running record whose owner stopped updating it (a dead replica's job)."""
        window = self.stale_running_s if rec.state == "running" else self.stale_queued_s
        return now - rec.updated_ts > window

    def _expire_if_stale(self, rec: SceneRecord) -> SceneRecord:
        """The record, failed (``interrupted``, and written) when it is another replica's stale job."""
        if rec.state in ("queued", "running") and rec.owner != self.replica_id and self._stale(rec, _now()):
            rec = rec.failed("interrupted", interrupted_message(rec.state) +
                             f" (replica {rec.owner} stopped updating it)", _now())
            self._write_checked(rec)
        return rec

    def _fail_record(self, rec: SceneRecord, code: str, message: str) -> SceneRecord | None:
        """Write ``rec`` as failed; the failed record, or None when it was deleted meanwhile."""
        rec = rec.failed(code, message, _now())
        return rec if self._write_checked(rec) else None

    def _write_checked(self, rec: SceneRecord) -> bool:
        """Write a record, then look for the scene's tombstone: a delete that began before this write may have
        removed the record before it (the write would resurrect it), so finish that delete. False when the scene
        is deleted. (A delete writes its tombstone before removing the record, so either it removes this write
        or this check sees the tombstone.)"""
        self._write(rec)
        if self._tombstoned(rec.id):
            self._purge(rec.id)
            return False
        return True

    # -- paths ----------------------------------------------------------------------------------------------------
    @_reachable
    def scene_dir(self, sid: str) -> Path:
        """The local folder of a ready scene, downloaded on first use (KeyError when unknown, not ready, or
        deleted while it was downloaded)."""
        rec = self.get(sid)
        if rec is None or rec.state != "ready":
            raise KeyError(sid)
        local = self.cache / "scenes" / sid
        with self._lock:
            gate = self._downloading.setdefault(sid, threading.Lock())
        with gate:
            if sid in self._local and (local / "scene.json").is_file():
                self._local[sid][1] = time.monotonic()
                return local
            self._download(sid, rec, local)
        self._trim_cache(keep=sid)
        return local

    def _download(self, sid: str, rec: SceneRecord, local: Path) -> None:
        from botocore.exceptions import ClientError

        names = list(rec.files or ())
        if not names:
            base = self._scene_prefix(sid)
            names = [o["Key"][len(base):] for o in self._objects(base)]
        if any(not n or n.startswith("/") or ".." in Path(n).parts for n in names):
            raise KeyError(sid)                  # never a path outside the scene's folder
        with atomic_folder(local) as tmp:        # a copy cut short by an error is never seen
            for name in names:
                dest = tmp / name
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    self.client.download_file(self.bucket, self._scene_prefix(sid) + name, str(dest))
                except ClientError as e:
                    if _missing(e):
                        raise KeyError(sid) from None        # deleted while we downloaded
                    raise
            if not (tmp / "scene.json").is_file():
                raise KeyError(sid)
        with self._lock:
            self._local[sid] = [float(folder_bytes(local)), time.monotonic()]

    def work_dir(self) -> Path:
        """A new empty local folder for an upload or a reconstruction (the caller removes it)."""
        d = self.cache / "tmp" / secrets.token_hex(8)
        d.mkdir(parents=True)
        return d

    # -- the local cache --------------------------------------------------------------------------------------
    def _remove_local(self, folder: Path) -> None:
        remove_folder(folder, self.cache / "tmp")

    def _drop_local(self, sid: str) -> None:
        with self._lock:
            self._local.pop(sid, None)
        self._remove_local(self.cache / "scenes" / sid)

    def _trim_cache(self, keep: str) -> None:
        """Drop the least recently used local copies beyond ``cache_bytes`` (never ``keep`` nor one used in the
        last few seconds: the bound is soft)."""
        with self._lock:
            total = sum(v[0] for v in self._local.values())
            if total <= self.cache_bytes:
                return
            limit = time.monotonic() - _CACHE_GRACE_S
            victims = []
            for sid, (size, used) in sorted(self._local.items(), key=lambda kv: kv[1][1]):
                if total <= self.cache_bytes:
                    break
                if sid != keep and used < limit:
                    victims.append(sid)
                    total -= size
        for sid in victims:
            self._drop_local(sid)

    def _forget(self, sid: str) -> None:
        """The record is gone from S3: drop everything this replica holds of the scene."""
        with self._lock:
            self._ready.pop(sid, None)
            self._etags.pop(sid, None)
            self._used.pop(sid, None)
            self._persisted_use.pop(sid, None)
            self._downloading.pop(sid, None)
            known = sid in self._seen or sid in self._local
            self._seen.discard(sid)
        if known:
            self._drop_local(sid)
            self._notify_deleted(sid)

    # -- records --------------------------------------------------------------------------------------------------
    @_reachable
    def get(self, sid: str) -> SceneRecord | None:
        if not valid_id(sid):
            return None
        with self._lock:
            hit = self._ready.get(sid)
        if hit is not None and time.monotonic() - hit[1] < self.record_ttl_s:
            return hit[0].model_copy(deep=True)
        got = self._read(sid)
        if got is None:
            self._forget(sid)
            return None
        rec = self._expire_if_stale(got[0])
        with self._lock:
            self._seen.add(sid)
            if rec.state == "ready":
                self._ready[sid] = (rec, time.monotonic())
        return rec.model_copy(deep=True)

    def _snapshot(self, with_use: bool = False, expire: bool = True) -> list[SceneRecord]:
        """Every record in the store (read again only where its ETag changed since the last listing), with
        ``last_used`` raised to the use markers' times when ``with_use``; other replicas' stale jobs failed when
        ``expire``. Scenes this replica knew and the listing lacks are forgotten."""
        with self._lock:
            before = self._seen | set(self._local)     # known before the listing: a gone one was deleted
        listed: dict[str, str] = {}
        base = self._key("records") + "/"
        for obj in self._objects(base):
            name = obj["Key"][len(base):]
            if name.endswith(".json") and valid_id(name[:-5]):
                listed[name[:-5]] = obj.get("ETag", "")
        with self._lock:
            known = dict(self._etags)
        stale = [sid for sid, etag in listed.items() if known.get(sid, ("",))[0] != etag]
        if stale:
            if self._pool is None:
                self._pool = cf.ThreadPoolExecutor(8, thread_name_prefix="s3-records")
            for sid, got in zip(stale, self._pool.map(self._read, stale), strict=True):
                if got is not None:
                    known[sid] = (got[1], got[0])
                else:
                    listed.pop(sid)
        records = [known[sid][1] for sid in listed]
        if expire:
            records = [self._expire_if_stale(r) for r in records]
        with self._lock:
            self._etags = {sid: known[sid] for sid in listed}
        for sid in before - set(listed):
            self._forget(sid)
        if with_use:
            marks = self._use_marks()
            for i, rec in enumerate(records):
                t = max(marks.get(rec.id, 0.0), self._used.get(rec.id, 0.0))
                if t > (rec.last_used or 0.0):
                    records[i] = rec.replace(last_used=t)
        return records

    def _use_marks(self) -> dict[str, float]:
        base = self._key("used") + "/"
        return {o["Key"][len(base):]: o["LastModified"].timestamp() for o in self._objects(base)}

    @_reachable
    def list(self, offset: int = 0, limit: int = 100) -> tuple[list[SceneRecord], int]:
        """Records, newest first, and the total count."""
        recs = newest_first(self._snapshot())
        return [r.model_copy(deep=True) for r in recs[offset:offset + limit]], len(recs)

    @_reachable
    def create(self, sid: str, record: Mapping[str, Any]) -> SceneRecord:
        """A new ``queued`` record owned by this replica; makes room under the scene-count quota first."""
        check_id(sid)
        now = _now()
        rec = SceneRecord.queued(sid, {**record, "owner": self.replica_id}, now)
        with self._lock:
            if self._exists(self._record_key(sid)):
                raise ValueError(f"scene id {sid} exists")
            records = self._snapshot(with_use=True)
            if now - self._cleaned > 3600.0:
                self._clean_litter(now, {r.id for r in records})
            for old in self.failed_beyond_quota(records):
                self.delete(old)
            self._evict(self.room_for_scene(records, exclude=sid))
            self._write(rec)
        return rec.model_copy(deep=True)

    def _fresh(self, sid: str) -> dict[str, Any] | None:
        """The record's JSON as S3 holds it now (read again, never cached), or None."""
        if not valid_id(sid):
            return None
        got = self._read(sid)
        return None if got is None else got[0].to_json()

    @_reachable
    def update(self, sid: str, **fields: Any) -> SceneRecord | None:
        """Change fields of a record (None when it was deleted meanwhile)."""
        doc = self._fresh(sid)
        if doc is None:
            return None
        rec = SceneRecord.from_json(doc).updated(_now(), **fields)
        return rec.model_copy(deep=True) if self._write_checked(rec) else None

    @_reachable
    def fail(self, sid: str, code: str, message: str) -> SceneRecord | None:
        doc = self._fresh(sid)
        if doc is None:
            return None
        return self._fail_record(SceneRecord.from_json(doc), code, message)

    @_reachable
    def commit(self, sid: str, folder: Path, **fields: Any) -> SceneRecord | None:
        """Upload a finished scene folder, then mark the record ready (with ``fields``); keep the byte quota by
        evicting least recently used scenes first. The folder becomes this replica's local copy. None when the
        record was deleted meanwhile; StoreFull when the quota cannot take the scene (the folder is removed)."""
        folder = Path(folder)
        files = {p.relative_to(folder).as_posix(): p for p in sorted(folder.rglob("*")) if p.is_file()}
        size = sum(p.stat().st_size for p in files.values())
        doc = self._fresh(sid)
        if doc is None:
            shutil.rmtree(folder, ignore_errors=True)
            return None
        with self._lock:
            try:
                victims = self.room_for_bytes(self._snapshot(with_use=True), sid, size)
            except StoreFull:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            self._evict(victims)
        try:
            for name, path in files.items():
                self.client.upload_file(str(path), self.bucket, self._scene_prefix(sid) + name)
            now = _now()
            rec = SceneRecord.from_json(doc).ready(size, now, **fields, files=sorted(files))
            ok = self._write_checked(rec)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            self._delete_keys([self._scene_prefix(sid) + n for n in files])
            raise
        if not ok:
            shutil.rmtree(folder, ignore_errors=True)
            return None
        local = self.cache / "scenes" / sid
        with self._lock:
            self._remove_local(local)
            os.replace(folder, local)
            self._local[sid] = [float(size), time.monotonic()]
            self._seen.add(sid)
            self._ready[sid] = (rec, time.monotonic())
            self._used[sid] = self._persisted_use[sid] = now
        self._trim_cache(keep=sid)
        return rec.model_copy(deep=True)

    def touch(self, sid: str) -> None:
        """Mark a scene used now (LRU, TTL); its marker object is rewritten at most once a minute, in the
        background (renders call this on the event loop)."""
        if not valid_id(sid):
            return
        now = _now()
        with self._lock:
            self._used[sid] = now
            if sid in self._local:
                self._local[sid][1] = time.monotonic()
            if now - self._persisted_use.get(sid, 0.0) < TOUCH_PERSIST_S:
                return
            self._persisted_use[sid] = now
            if self._pool is None:
                self._pool = cf.ThreadPoolExecutor(8, thread_name_prefix="s3-records")
        self._pool.submit(self._mark_used, sid)

    def _mark_used(self, sid: str) -> None:
        try:
            self.client.put_object(Bucket=self.bucket, Key=self._key("used", sid), Body=b"")
        except Exception as e:       # noqa: BLE001 - a lost use mark must never fail a render
            log.warning("scene %s: use mark not written (%s)", sid, e)

    @_reachable
    def delete(self, sid: str) -> bool:
        """Remove a scene: tombstone, record, then its files. False when unknown."""
        if not valid_id(sid):
            return False
        if not self._exists(self._record_key(sid)):
            self._forget(sid)
            return False
        self.client.put_object(Bucket=self.bucket, Key=self._key("deleted", sid),
                               Body=json.dumps({"by": self.replica_id, "ts": _now()}).encode())
        self._purge(sid)
        with self._lock:
            self._seen.add(sid)          # so that _forget drops the local copy and tells on_delete
        self._forget(sid)
        return True

    def _purge(self, sid: str) -> None:
        self._usage = None
        self.client.delete_object(Bucket=self.bucket, Key=self._record_key(sid))
        keys = [o["Key"] for o in self._objects(self._scene_prefix(sid))]
        self._delete_keys(keys + [self._key("used", sid)])

    def _evict(self, victims: list[str]) -> None:
        for sid in victims:
            if self.delete(sid):
                self.evicted += 1

    # -- quota ----------------------------------------------------------------------------------------------------
    @_reachable
    def sweep(self, now: float | None = None) -> list[str]:
        """Delete scenes unused for longer than ttl_s; drop use markers and tombstones left by deletes. Returns the
        removed ids."""
        now = _now() if now is None else now
        records = self._snapshot(with_use=True)
        old = self.expired(records, now)
        for sid in old:
            self.delete(sid)
        self._clean_litter(now, {r.id for r in records} - set(old))
        return old

    def _clean_litter(self, now: float, live: set[str]) -> None:
        """Remove use markers of scenes that are gone and tombstones older than any job that could still write
        (on open, in sweep, and at most hourly on create)."""
        self._cleaned = now
        marks = self._key("used") + "/"
        graves = self._key("deleted") + "/"
        litter = [o["Key"] for o in self._objects(marks) if o["Key"][len(marks):] not in live]
        keep_s = max(self.stale_running_s, self.stale_queued_s) + 3600.0
        litter += [o["Key"] for o in self._objects(graves) if now - o["LastModified"].timestamp() > keep_s]
        self._delete_keys(litter)

    def usage(self) -> dict[str, Any]:
        """For /metrics: from a listing at most every USAGE_TTL_S (at once after this replica changed something);
        zeros before open(); the last figures when the bucket cannot be reached (a scrape never fails)."""
        from botocore.exceptions import BotoCoreError, ClientError

        if not self._opened:
            return self.usage_of([])
        hit = self._usage
        if hit is None or time.monotonic() - hit[1] > USAGE_TTL_S:
            try:
                hit = self._usage = (self.usage_of(self._snapshot()), time.monotonic())
            except (BotoCoreError, ClientError, StoreUnavailable) as e:
                log.warning("store usage: the bucket cannot be listed (%s)", e)
                if hit is None:
                    return self.usage_of([])
        return {**hit[0], "evicted": self.evicted}


__all__ = ["S3Store", "default_replica_id", "parse_url"]
