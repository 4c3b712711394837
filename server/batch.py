"""`xyzcyl batch MANIFEST --out STORE`: many recorded drives (and plain rigs) reconstructed on Ray into the service's
scene store, on a laptop (a local Ray on its cores) or a cluster (``--address`` / ``RAY_ADDRESS``). docs/batch.md.

The manifest (read_manifest): one input per line, a drive file or a rig.json (a one-frame drive), a local path
(relative to the manifest) or an ``s3://bucket/key``; or JSON lines ``{"input": ..., "name": ..., options}`` with
BatchItem's options. Blank lines and ``#`` comments are skipped.

The pipeline (run_batch), on Ray Data's streaming executor, one row per manifest item:

1. plan (plan_item): the input's folder fetched to this node when it is in S3 (fetch_input), the drive read and
   checked (runtime.drive.load_drive: every frame's rig, image headers, LiDAR files, tracks), its keyframes picked,
   the scene's id derived from what makes the scene (scene_key: the content of every file the drive names, the
   item's options, the model's name, version and model.json hash); a scene of that id already ready in the store
   is skipped (renamed when only the item's name changed), nothing rewritten;
2. reconstruct (reconstruct_item), at most ``drives`` at once: the drive's record created (or retaken, when a
   killed or failed run left it) and set running, the ego's body found, the keyframes made by the keyframe worker
   actors (KeyframeWorker: each loads the ONNX model once and serves every drive's keyframes, at most ``workers``
   of a drive in flight, in Ray's object store), fused in order as they arrive (runtime.drive.reconstruct_drive),
   the scene folder written (and its AlpaSim .usdz with ``usdz``) and committed to the store: renamed into place
   (folder store) or uploaded before its record turns ready (S3 store), as the service commits its own;
3. the driver writes each finished row to the results table (JSON lines, rewritten by every run) and prints one line.

A failing item is a row with its error (code, field, message) and a failed record when it got one; it never stops
the batch. A killed run leaves at most records ``running`` and work folders: a rerun retakes those records and
skips the ready ones, so it ends with the same store.
"""

from __future__ import annotations

import base64
import errno
import hashlib
import json
import os
import posixpath
import re
import shutil
import socket
import tempfile
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError, field_validator
from xyzcyl.common.errors import FieldError
from xyzcyl.common.wire import is_drive_document

from .store.record import name_error

# measured peaks (docs/results.md "Batch on Ray": the shared PandaSet drive, six 1920x1080 cameras + LiDAR, 40
# frames): a keyframe worker ~3.7 GiB RSS, a drive's fusion 3.4-3.7 GiB; the default worker and drive counts keep
# their sum within Ray's memory (default_sizes)
WORKER_BYTES = int(3.7 * 2**30)
FUSION_BYTES = int(3.7 * 2**30)
EXIT_OK, EXIT_PARTIAL = 0, 3             # and 2: bad arguments or manifest (the command)
HUGE = 1 << 62                    # the batch's store handles keep no quota: it writes what the manifest asks
READ_CHUNK = 1 << 20


class BatchError(OSError):
    """The batch cannot go on (Ray or the store failed); the items finished are in the results table."""


class ManifestError(FieldError):
    """A manifest that cannot be used: ``field`` is "line N" or "line N: option", ``where`` the manifest."""


class BatchItem(BaseModel):
    """One manifest line: the input and the reconstruction's options (those of `xyzcyl reconstruct` and of POST
    /v1/scenes)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    input: str = Field(min_length=1, description="a drive file or rig.json: local path or s3://bucket/key")
    name: str | None = Field(None, description="the scene's name (default: the input's folder name)")
    keyframe_spacing: float | None = Field(None, gt=0, allow_inf_nan=False, description="metres")
    keyframe_gap: float | None = Field(None, gt=0, allow_inf_nan=False, description="seconds")
    keyframes: list[int] | None = Field(None, min_length=1, description="frame indices, increasing")
    lidar: StrictBool = True
    stereo: StrictBool = True
    detail_stride: int | None = Field(-1, description="the detail layer's stride; null: no detail layer; "
                                                      "absent: the default")
    stationary_actors: StrictBool = False
    ego_body: StrictBool = True
    exposure: StrictBool = True

    @field_validator("detail_stride")
    @classmethod
    def _stride(cls, v: int | None) -> int | None:
        if v is not None and v != -1 and not 1 <= v <= 64:
            raise ValueError("must be 1..64 (or null: no detail layer)")
        return v

    @field_validator("keyframes")
    @classmethod
    def _keys(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and (v != sorted(set(v)) or v[0] < 0):
            raise ValueError("must be increasing frame indices >= 0")
        return v

    def options(self) -> dict[str, Any]:
        """What makes the scene besides the input's files (scene_key): every option but the input and name."""
        return self.model_dump(exclude={"input", "name"})

    def detail(self):
        """runtime.detail.DetailOptions of ``detail_stride`` (None: no detail layer)."""
        from xyzcyl.runtime.inference import DEFAULT_DETAIL

        if self.detail_stride is None:
            return None
        return DEFAULT_DETAIL if self.detail_stride == -1 else replace(DEFAULT_DETAIL, stride=self.detail_stride)


# -------------------------------------------------------------------------------------------------- the manifest

def is_s3(uri: str) -> bool:
    return uri.startswith("s3://")


def _s3_parts(uri: str) -> tuple[str, str]:
    """``s3://bucket/some/key`` -> ("bucket", "some/key"), the key normalised ("a/../b" -> "b": S3 keys are
    literal); ManifestError naming ``input`` when it has no bucket or key."""
    bucket, _, key = uri[5:].partition("/")
    key = posixpath.normpath(key) if key else ""
    if not bucket or not key or key in (".", "..") or key.startswith("../"):
        raise ManifestError("input", f"an s3:// URI names s3://bucket/key (got {uri!r})")
    return bucket, key


def _s3_client():
    try:
        import boto3
    except ImportError:
        raise OSError("s3:// inputs and stores need boto3: pip install 'xyzcyl[server,batch]'") from None
    return boto3.client("s3")


def read_text(uri: str) -> str:
    """A local file's or an S3 object's text (OSError when it cannot be read)."""
    if is_s3(uri):
        bucket, key = _s3_parts(uri)
        try:
            return _s3_client().get_object(Bucket=bucket, Key=key)["Body"].read().decode()
        except Exception as e:       # noqa: BLE001 - botocore's errors, said as the OSError callers handle
            raise OSError(f"{uri}: cannot be read ({e})") from None
    return Path(uri).read_text()


def default_name(uri: str) -> str:
    """The scene's name when the manifest gives none: the folder of a drive.json / rig.json, else the file's stem."""
    p = PurePosixPath(uri[5:] if is_s3(uri) else Path(uri).resolve().as_posix())
    return p.parent.name if p.name in ("drive.json", "rig.json") and p.parent.name else p.stem


def read_manifest(uri: str) -> list[BatchItem]:
    """The items of a manifest (module doc); ManifestError naming the line (and option) of the first bad one."""
    try:
        text = read_text(uri)
    except OSError as e:
        raise ManifestError("manifest", f"cannot be read ({e.strerror or e})", uri) from None
    except UnicodeDecodeError:
        raise ManifestError("manifest", "is not UTF-8 text", uri) from None
    base = uri.rsplit("/", 1)[0] + "/" if is_s3(uri) else str(Path(uri).resolve().parent) + os.sep
    items: list[BatchItem] = []
    seen: dict[tuple[str, str], int] = {}
    names: dict[str, int] = {}
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"line {n}"
        if line.startswith("{"):
            try:
                doc = json.loads(line)
            except ValueError as e:
                raise ManifestError(where, f"not valid JSON ({e})", uri) from None
            try:
                item = BatchItem.model_validate(doc)
            except ValidationError as e:
                err = e.errors()[0]
                loc = ".".join(str(x) for x in err["loc"])
                raise ManifestError(f"{where}: {loc}" if loc else where, err["msg"], uri) from None
        else:
            item = BatchItem(input=line)
        src = item.input
        if not is_s3(src):
            if "://" in src:
                raise ManifestError(f"{where}: input", f"a local path or s3://bucket/key (got {src!r})", uri)
            if is_s3(uri):
                root = "s3://" + _s3_parts(uri)[0] + "/"       # "/x/drive.json": from the bucket's root
                bucket, key = _s3_parts(root + src.lstrip("/") if src.startswith("/") else base + src)
                src = f"s3://{bucket}/{key}"
            else:
                src = str(Path(base, src).resolve()) if not Path(src).is_absolute() else src
        if not is_s3(src) and not Path(src).is_file():
            raise ManifestError(f"{where}: input", f"no file {src!r}", uri)
        name = item.name or default_name(src)
        if (why := name_error(name)) is not None:
            raise ManifestError(f"{where}: name", why + (" (give one: a JSON line with \"name\")"
                                                         if item.name is None else ""), uri)
        item = item.model_copy(update={"input": src, "name": name})
        key = (src, json.dumps(item.options(), sort_keys=True))
        if key in seen:
            raise ManifestError(where, f"the same input and options as line {seen[key]}", uri)
        if name in names:
            raise ManifestError(f"{where}: name", f"{name!r} is line {names[name]}'s name too (scene names in a "
                                "batch are unique: give one with a JSON line's \"name\")", uri)
        seen[key], names[name] = n, n
        items.append(item)
    if not items:
        raise ManifestError("manifest", "lists no inputs", uri)
    return items


# -------------------------------------------------------------------------------------------------- the inputs

def cache_root() -> Path:
    """This node's folder for inputs fetched from S3: $XYZCYL_BATCH_CACHE, else the temporary folder's."""
    return Path(os.environ.get("XYZCYL_BATCH_CACHE") or Path(tempfile.gettempdir()) / "xyzcyl-batch-inputs")


def fetch_input(uri: str) -> Path:
    """The local file of an input: itself, or (``s3://``) the object's copy after every object under its folder
    (prefix) was downloaded to this node's cache once (cache_root; keyed by the listing's keys and ETags, so a
    changed drive is fetched again; written to a temporary folder and renamed into place whole)."""
    if not is_s3(uri):
        return Path(uri)
    bucket, key = _s3_parts(uri)
    prefix = key.rsplit("/", 1)[0] + "/" if "/" in key else ""
    client = _s3_client()
    objs = []
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        objs += [(o["Key"], o["ETag"], o["Size"]) for o in page.get("Contents", [])]
    if not any(k == key for k, _, _ in objs):
        raise FileNotFoundError(errno.ENOENT, "no such object", uri)
    tag = hashlib.sha256(json.dumps([bucket, sorted(objs)]).encode()).hexdigest()[:24]
    dest = cache_root() / tag
    if not (dest / ".complete").is_file():
        tmp = cache_root() / f".{tag}-{os.getpid()}-{time.monotonic_ns()}"
        for k, _, _ in objs:
            out = tmp / k[len(prefix):]
            out.parent.mkdir(parents=True, exist_ok=True)
            client.download_file(bucket, k, str(out))
        (tmp / ".complete").write_text(uri)
        try:
            os.rename(tmp, dest)
        except OSError:              # another process of this node fetched it first
            shutil.rmtree(tmp, ignore_errors=True)
    return dest / key[len(prefix):]


def load_input(path: Path, check_images: bool = True):
    """The runtime.drive.Drive of a drive file, or of a rig.json (a drive of one frame)."""
    from xyzcyl.runtime.drive import drive_of_rig, load_drive
    from xyzcyl.runtime.rig import load_rig

    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        doc = None
    if is_drive_document(doc):
        return load_drive(path, check_images=check_images)
    return drive_of_rig(load_rig(path, check_images=check_images), path)


def input_files(drive) -> list[Path]:
    """Every file the drive reads: the drive file and its tracks file, each frame's rig.json and the files it
    names (images, depth maps, ego masks, the LiDAR sweep)."""
    files: set[Path] = set()
    if drive.path is not None:
        files.add(Path(drive.path))
        try:
            doc = json.loads(Path(drive.path).read_text())
        except (OSError, ValueError):
            doc = None
        if isinstance(doc, dict) and isinstance(doc.get("tracks"), str):
            files.add(Path(drive.path).parent / doc["tracks"])
    for fr in drive.frames:
        rig = fr.rig
        if fr.rig_path is not None:
            files.add(Path(fr.rig_path))
        for c in rig.cameras:
            for name in (c.image, c.depth, c.extra.get("ego_mask")):
                if isinstance(name, str):
                    files.add(rig.path(name))
        lidar = rig.extra.get("lidar")
        if isinstance(lidar, dict) and isinstance(lidar.get("file"), str):
            files.add(rig.path(lidar["file"]))
    return sorted(files)


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(READ_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def scene_key(drive, root: Path, options: Mapping[str, Any], model: Mapping[str, Any]) -> str:
    """sha256 (hex) of what makes a scene: each input file's content with its path relative to ``root`` (the input's
    folder: a dataset moved elsewhere or fetched from S3 keeps its key), the item's ``options``, and the model's
    name, version and model.json hash."""
    files = []
    for p in input_files(drive):
        try:
            rel = p.resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            rel = p.resolve().as_posix()
        files.append([rel, _file_sha256(p)])
    doc = {"files": files, "options": dict(options), "model": {k: model[k] for k in sorted(model)}}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def scene_id_of(key: str) -> str:
    """The store id of a scene key: 22 URL-safe characters of its first 128 bits (store.record.SCENE_ID)."""
    return base64.urlsafe_b64encode(bytes.fromhex(key)[:16]).decode().rstrip("=")


# -------------------------------------------------------------------------------------------------- the store

_STORES: dict[str, Any] = {}


class StoreHandle:
    """A batch process's handle on the service's store (a folder, or s3://bucket/prefix): several processes write
    one store at once, each scene by one of them. The folder store is never open()ed here (that empties tmp/ and
    fails other processes' running records); records are read from their files (FolderStore.reload). No quota
    (HUGE): a batch writes every scene its manifest names."""

    def __init__(self, url: str):
        self.url = url
        self.s3 = is_s3(url)
        if self.s3:
            from .store.s3 import S3Store

            cache = Path(tempfile.mkdtemp(prefix="xyzcyl-batch-s3-"))
            (cache / "scenes").mkdir()
            self.store = S3Store(url, max_scenes=HUGE, max_bytes=HUGE, cache_dir=cache, cache_bytes=0,
                                 replica_id=f"xyzcyl-batch:{socket.gethostname()}:{os.getpid()}")
        else:
            from .store.folder import FolderStore

            self.store = FolderStore(url, max_scenes=HUGE, max_bytes=HUGE)

    def prepare(self) -> None:
        """The folder store's folders made (a new store); an S3 store's bucket is written as it goes."""
        if not self.s3:
            for sub in ("records", "scenes", "tmp"):
                (Path(self.url) / sub).mkdir(parents=True, exist_ok=True)

    @classmethod
    def of(cls, url: str) -> StoreHandle:
        """This process's handle on ``url`` (made once)."""
        if url not in _STORES:
            _STORES[url] = cls(url)
        return _STORES[url]

    def record(self, sid: str):
        """The scene's record as the store holds it now, or None."""
        if self.s3:
            doc = self.store._fresh(sid)
            from .store.record import SceneRecord

            return None if doc is None else SceneRecord.from_json(doc)
        return self.store.reload(sid)

    def begin(self, sid: str, fields: Mapping[str, Any]) -> None:
        """The scene's record, running: created, or retaken from a run that was killed or failed (a ready one is
        never retaken: plan_item skips it)."""
        self.prepare()
        rec = self.record(sid)
        if rec is None:
            self.store.create(sid, fields)
        self.store.update(sid, **fields, state="running", error=None,
                          **({"owner": self.store.replica_id} if self.s3 else {}))

    def work_dir(self) -> Path:
        """A new empty folder on the store's file system (the folder store: under tmp/, named for this process so
        that a later run can tell a dead run's folder, clean_work)."""
        if self.s3:
            return self.store.work_dir()
        self.prepare()
        d = Path(self.url) / "tmp" / f"batch-{socket.gethostname()}-{os.getpid()}-{time.monotonic_ns()}"
        d.mkdir(parents=True)
        return d


def clean_work(store_url: str) -> int:
    """Remove the folder store's work folders of batch processes of this host that are gone (a killed run's);
    the count removed."""
    if is_s3(store_url):
        return 0
    tmp = Path(store_url) / "tmp"
    removed = 0
    host = socket.gethostname()
    for p in tmp.glob(f"batch-{host}-*") if tmp.is_dir() else ():
        m = re.match(rf"batch-{re.escape(host)}-(\d+)-\d+$", p.name)
        if m is None:
            continue
        try:
            os.kill(int(m.group(1)), 0)
            continue                 # its process runs
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed += 1
    return removed


# -------------------------------------------------------------------------------------------------- errors

def failure_of(exc: BaseException) -> dict[str, Any]:
    """A row's error of an exception: {"code", "field", "message"} (the codes of the service's records: invalid_input,
    storage_full, worker_crashed, error)."""
    try:
        import ray.exceptions as rex
    except ImportError:          # the plan stage's errors are read without Ray too
        rex = None
    if rex is not None and isinstance(exc, rex.RayTaskError):
        cause = getattr(exc, "cause", None)
        if isinstance(cause, BaseException) and not isinstance(cause, rex.RayTaskError):
            return failure_of(cause)
        return {"code": "error", "field": None, "message": str(exc).strip().splitlines()[-1][:2000]}
    if rex is not None and isinstance(exc, (rex.RayActorError, rex.WorkerCrashedError, rex.OutOfMemoryError)):
        return {"code": "worker_crashed", "field": None,
                "message": f"a worker died (crash or out of memory): {str(exc).strip().splitlines()[0][:500]}"}
    if isinstance(exc, FieldError):
        return {"code": "invalid_input", "field": exc.field, "message": str(exc)}
    if isinstance(exc, OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return {"code": "storage_full", "field": None, "message": f"a disk is full ({exc.strerror})"}
        if isinstance(exc, FileNotFoundError):
            return {"code": "invalid_input", "field": "input", "message": str(exc)}
        return {"code": "error", "field": None, "message": f"{type(exc).__name__}: {exc}"}
    if isinstance(exc, MemoryError):
        return {"code": "error", "field": None, "message": "out of memory"}
    return {"code": "error", "field": None, "message": f"{type(exc).__name__}: {exc}"}


# -------------------------------------------------------------------------------------------------- the stages

@dataclass(frozen=True)
class ModelStamp:
    """What reconstruct_drive asks of the model where the keyframes are made elsewhere: the scene's model block."""

    meta: dict[str, str]

    def scene_model(self) -> dict[str, str]:
        return dict(self.meta)


def _keys_of(drive, item: BatchItem) -> list[int]:
    from xyzcyl.runtime.drive import DriveError, pick_keyframes

    if item.keyframes is not None:
        if item.keyframes[-1] >= len(drive):
            raise DriveError("keyframes", f"must be frame indices in 0..{len(drive) - 1} (got {item.keyframes})")
        return list(item.keyframes)
    return pick_keyframes(drive, item.keyframe_spacing, item.keyframe_gap)


def plan_item(row: dict[str, Any], store: str, model: dict[str, str], usdz: bool = False,
              dry: bool = False) -> dict[str, Any]:
    """Stage 1 of a row (module doc): the row with ``status`` "skipped" (its scene is ready in the store), "todo"
    (with ``scene_id``, ``key``, ``fields``: the record's cameras, detail, name, drive) or "failed" (``error``).
    ``usdz``: the scene folder holds its AlpaSim artifact too, a folder of its own (its key says so). ``dry``
    (`--dry-run`): nothing written (a ready scene's new name is not)."""
    item = BatchItem.model_validate_json(row["item"])
    t0 = time.perf_counter()
    out = {**row, "status": "failed", "scene_id": None, "error": None, "frames": None, "keyframes": None}
    try:
        path = fetch_input(item.input)
        drive = load_input(path)
        keys = _keys_of(drive, item)
        key = scene_key(drive, path.parent, {**item.options(), **({"usdz": True} if usdz else {})}, model)
        sid = scene_id_of(key)
        out.update(scene_id=sid, key=key, frames=len(drive), keyframes=len(keys))
        handle = StoreHandle.of(store)
        rec = handle.record(sid)
        if rec is not None and rec.state == "ready":
            if rec.name != item.name and not dry:
                handle.store.update(sid, name=item.name)
            out.update(status="skipped", gaussians=rec.gaussians)
            return out
        from .jobs import drive_info

        rig = drive.frames[0].rig
        stride = item.detail()
        fields: dict[str, Any] = {
            "cameras": [{"name": c.name, "width": c.width, "height": c.height, "model": c.model}
                        for c in rig.cameras],
            "detail": {"enabled": stride is not None, "stride": None if stride is None else stride.stride},
            "name": item.name}
        if drive.path is not None:
            knobs = {k: v for k, v in (("keyframe_spacing", item.keyframe_spacing),
                                       ("keyframe_gap", item.keyframe_gap)) if v is not None}
            fields["drive"] = drive_info(drive, knobs, keys) | {"stationary_actors": item.stationary_actors}
        out.update(status="todo", fields=json.dumps(fields), keys=json.dumps(keys))
    except Exception as e:          # noqa: BLE001 - a row's error, never the batch's
        out["error"] = failure_of(e)
    out["plan_s"] = round(time.perf_counter() - t0, 3)
    return out


def _on_workers(actors: list, uri: str, first: int) -> Callable[..., Iterator]:
    """reconstruct_drive's make_keyframes: each keyframe made by a worker actor (round robin from ``first``), at
    most one per actor in flight, taken back in order. A result's arrays come from Ray's object store without a
    copy and are read-only: the fusion only reads a keyframe's arrays (it makes new ones), as the batch's tests of
    drives with several keyframes show (a write would raise)."""
    import ray

    def make(drive, keys, opts):
        ref = ray.put(opts)
        pending: deque = deque()
        ahead = iter(enumerate(keys))

        def submit() -> None:
            nxt = next(ahead, None)
            if nxt is not None:
                i, k = nxt
                pending.append(actors[(first + i) % len(actors)].keyframe.remote(uri, int(k), ref))

        for _ in range(len(actors)):
            submit()
        try:
            while pending:
                got = ray.get(pending.popleft())
                submit()
                yield got
        finally:
            for r in pending:
                ray.cancel(r)

    return make


def reconstruct_item(row: dict[str, Any], store: str, model: dict[str, str], actors: list,
                     usdz: bool) -> dict[str, Any]:
    """Stage 2 of a row (module doc): a "todo" row's scene made and committed; the row with ``status`` "ready" or
    "failed" (``error``). Other rows pass through."""
    if row["status"] != "todo":
        return row
    import ray
    from xyzcyl.runtime.drive import drive_meta, one_rig, reconstruct_drive

    from .jobs import Reconstructed

    item = BatchItem.model_validate_json(row["item"])
    sid, fields, keys = row["scene_id"], json.loads(row["fields"]), json.loads(row["keys"])
    handle = StoreHandle.of(store)
    t0 = time.perf_counter()
    work = None
    out = {**row, "status": "failed"}
    try:
        handle.begin(sid, fields)
        path = fetch_input(item.input)
        drive = load_input(path, check_images=False)        # checked by plan_item
        opts = dict(lidar=item.lidar, detail=item.detail())
        first = int(sid.encode()[0])        # drives at once start on different workers
        if one_rig(drive, keys):
            scene = ray.get(actors[first % len(actors)].rig_scene.remote(item.input, {**opts,
                                                                                     "exposure": item.exposure}))
            if drive.path is not None:              # a drive file of one frame: its scene says so
                scene.drive = drive_meta(drive, keys)
        else:
            scene = reconstruct_drive(ModelStamp(model), drive, keys, stereo=item.stereo, ego_body=item.ego_body,
                                      exposure=item.exposure, stationary_actors=item.stationary_actors,
                                      make_keyframes=_on_workers(actors, item.input, first), **opts)
        work = handle.work_dir()
        folder = work / "scene"
        scene.save(folder)
        if usdz:
            from xyzcyl.runtime.usdz import export_usdz

            export_usdz(folder, work / "scene.usdz", scene_id=item.name)
            os.replace(work / "scene.usdz", folder / "scene.usdz")
        seconds = time.perf_counter() - t0
        rec = handle.store.commit(sid, folder, **Reconstructed.of(scene).record_fields(0.0, seconds))
        if rec is None:
            raise OSError(f"the store deleted scene {sid} while it was written (a DELETE of it leaves a tombstone "
                          "in an S3 store for hours)")
        out.update(status="ready", gaussians=rec.gaussians, error=None)
    except Exception as e:          # noqa: BLE001 - a row's error, never the batch's
        out["error"] = failure_of(e)
        try:
            handle.store.fail(sid, out["error"]["code"], out["error"]["message"])
        except Exception:           # noqa: BLE001 - the row says why; the record stays running for a rerun
            pass
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


class KeyframeWorker:
    """A Ray actor that makes keyframes (runtime.drive.make_keyframe) with its own model sessions, loaded once:
    any drive's, the drive read once and kept for its next keyframes (the last two)."""

    def __init__(self, model_dir: str, threads: int):
        import numba
        from xyzcyl.runtime.inference import Reconstructor

        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        self.rec = Reconstructor.load(model_dir, threads=threads)
        self.drives: OrderedDict[str, Any] = OrderedDict()

    def ready(self) -> dict[str, Any]:
        return {"pid": os.getpid(), "host": socket.gethostname(), "model": self.rec.scene_model()}

    def _drive(self, uri: str):
        if uri not in self.drives:
            self.drives[uri] = load_input(fetch_input(uri), check_images=False)
            while len(self.drives) > 2:
                self.drives.popitem(last=False)
        self.drives.move_to_end(uri)
        return self.drives[uri]

    def keyframe(self, uri: str, k: int, opts: dict[str, Any]):
        from xyzcyl.runtime.drive import make_keyframe

        return make_keyframe(self.rec, self._drive(uri), k, **opts)

    def rig_scene(self, uri: str, opts: dict[str, Any]):
        """The scene of a one-frame drive (Reconstructor.reconstruct of its rig, its LiDAR sweep's count noted)."""
        from xyzcyl.runtime.lidar import has_lidar, load_lidar

        rig = self._drive(uri).frames[0].rig
        pts = load_lidar(rig) if opts["lidar"] and has_lidar(rig) else None
        scene = self.rec.reconstruct(rig, lidar=None if pts is None else pts.points, detail=opts["detail"],
                                     exposure=opts["exposure"])
        if pts is not None:
            scene.counts.update(pts.counts())
        return scene


# -------------------------------------------------------------------------------------------------- the driver

class Results:
    """The results table: one JSON line per finished item, rewritten by each run (a local file, flushed and synced
    line by line, or an S3 object written again after each line)."""

    def __init__(self, uri: str):
        self.uri = uri
        self.rows: list[dict[str, Any]] = []
        if is_s3(uri):
            self.bucket, self.key = _s3_parts(uri)
            self.client = _s3_client()
            self.file = None
        else:
            Path(uri).parent.mkdir(parents=True, exist_ok=True)
            self.file = open(uri, "w")

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        line = json.dumps(row, allow_nan=False) + "\n"
        if self.file is not None:
            self.file.write(line)
            self.file.flush()
            os.fsync(self.file.fileno())
        else:
            body = "".join(json.dumps(r, allow_nan=False) + "\n" for r in self.rows).encode()
            self.client.put_object(Bucket=self.bucket, Key=self.key, Body=body, ContentType="application/x-ndjson")

    def close(self) -> None:
        if self.file is not None:
            self.file.close()


PUBLIC = ("item", "input", "name", "status", "scene_id", "frames", "keyframes", "gaussians", "seconds", "plan_s",
          "error")


def public_row(row: Mapping[str, Any], run: str) -> dict[str, Any]:
    """A finished row as the results table has it (PUBLIC's keys, the run's id and when it finished)."""
    out = {k: row.get(k) for k in PUBLIC}
    out["run"] = run
    out["finished"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return out


def describe(row: Mapping[str, Any]) -> str:
    """The one line printed when an item finishes."""
    if row["status"] == "failed":
        e = row.get("error") or {}
        return f"{row['name']}: FAILED {e.get('code')}: {e.get('message')}"
    what = f"scene {row['scene_id']}"
    if row.get("gaussians") is not None:
        what += f", {row['gaussians']:,} Gaussians"
    if row["status"] == "skipped":
        return f"{row['name']}: skipped ({what} is in the store)"
    if row["status"] == "todo":
        return f"{row['name']}: to make ({what}, {row.get('keyframes')} keyframes of {row.get('frames')} frames)"
    return f"{row['name']}: ready ({what}, {row.get('keyframes')} keyframes of {row.get('frames')} frames, " \
           f"{row.get('seconds', 0):.1f} s)"


@dataclass(frozen=True)
class BatchOptions:
    store: str                    # folder or s3://bucket/prefix
    model_dir: str                # a model folder, at the same path on every node
    results: str                  # the results table: a local path or s3:// URI
    address: str | None = None    # a Ray cluster (None: RAY_ADDRESS, else a local Ray)
    workers: int | None = None    # keyframe worker actors (None: the cluster's CPUs // worker_cpus)
    worker_cpus: int = 1          # CPUs (and threads) of each worker
    drives: int | None = None     # drives fused at once (None: workers // 4, at least 1)
    usdz: bool = False            # write the AlpaSim artifact into each scene folder too
    quiet: bool = False


def plan_batch(items: list[BatchItem], opts: BatchOptions, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """`--dry-run`: every item's plan step here, without Ray (plan_item: fetched, checked, keyframes, scene id, and
    whether the store has it), said one line each; the rows (status "todo", "skipped" or "failed"). Nothing is
    written but an S3 input's copy in this machine's cache."""
    from xyzcyl.runtime.inference import read_model_info, scene_model_of

    model = scene_model_of(read_model_info(opts.model_dir))
    out = []
    for i, it in enumerate(items):
        row = plan_item({"item": it.model_dump_json(), "input": it.input, "name": it.name, "index": i}, opts.store,
                        model, opts.usdz, dry=True)
        row["item"] = row.pop("index")
        say(f"[{i + 1}/{len(items)}] {describe(row)}")
        out.append(row)
    return out


def default_sizes(cpus: int, memory: float, worker_cpus: int, workers: int | None, drives: int | None
                  ) -> tuple[int, int, str]:
    """(keyframe workers, drives at once, why) for a cluster of ``cpus`` CPUs and ``memory`` bytes that Ray hands
    out (ray.cluster_resources()'s "memory": ~70 % of a local machine's free memory): the given counts, else as many
    workers as the CPUs take (``worker_cpus`` each) and the memory holds beside the fusions (WORKER_BYTES each,
    FUSION_BYTES a drive), and a drive at once per four workers; at least one of each."""
    def fusing(w: int) -> int:
        return drives or max(1, w // 4)

    why = ""
    if workers is None:
        by_cpu = max(1, cpus // worker_cpus)
        workers = 1
        for w in range(by_cpu, 0, -1):       # the most workers whose peaks, with their drives' fusions, fit
            if w * WORKER_BYTES + fusing(w) * FUSION_BYTES <= memory:
                workers = w
                break
        if workers < by_cpu:
            why = (f"{workers} keyframe worker(s), not {by_cpu}: Ray has {memory / 2**30:.1f} GiB, "
                   f"~{WORKER_BYTES / 2**30:.1f} GiB a worker and ~{FUSION_BYTES / 2**30:.1f} GiB a drive's fusion "
                   "(--workers sets it)")
    return workers, fusing(workers), why


def run_batch(items: list[BatchItem], opts: BatchOptions, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """Every item of a manifest through the pipeline (module doc) on Ray; the results table's rows in the order
    they finished."""
    import logging

    import ray
    from xyzcyl.runtime.inference import read_model_info, scene_model_of

    model = scene_model_of(read_model_info(opts.model_dir))
    removed = clean_work(opts.store)
    if removed:
        say(f"removed {removed} work folder(s) of an earlier run that stopped")
    StoreHandle.of(opts.store).prepare()      # the store's folders, and an S3 store's credentials, checked here
    address = opts.address or os.environ.get("RAY_ADDRESS") or None
    t0 = time.perf_counter()
    # a local Ray's workers inherit this process's environment (XYZCYL_*, NUMBA_CACHE_DIR, AWS_*); a cluster's
    # nodes have their own (deploy/rayjob.yaml): nothing is sent along (credentials would sit in the job's metadata)
    ray.init(address=address, include_dashboard=False, log_to_driver=not opts.quiet,
             logging_level=logging.WARNING, configure_logging=True)
    try:
        res = ray.cluster_resources()
        cpus = int(res.get("CPU", 1))
        workers, drives, why = default_sizes(cpus, float(res.get("memory", 0.0)), opts.worker_cpus, opts.workers,
                                             opts.drives)
        if why:
            say(why)
        say(f"Ray: {cpus} CPUs ({'cluster ' + address if address else 'local'}); {workers} keyframe worker(s) of "
            f"{opts.worker_cpus} CPU, {drives} drive(s) at once; model {model['name']} {model['version']}")
        worker = ray.remote(num_cpus=opts.worker_cpus, max_restarts=1)(KeyframeWorker)
        actors = [worker.remote(opts.model_dir, opts.worker_cpus) for _ in range(workers)]
        ready = [a.ready.remote() for a in actors]

        def loaded() -> None:           # the models load while the first items are planned
            try:
                ray.get(ready)
                say(f"keyframe workers ready {time.perf_counter() - t0:.1f} s after Ray's start")
            except Exception as e:      # noqa: BLE001 - said here; the items they were to make fail with it
                say(f"a keyframe worker could not start: {failure_of(e)['message']}")

        threading.Thread(target=loaded, daemon=True).start()
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = not opts.quiet
        ctx.enable_operator_progress_bars = not opts.quiet
        ctx.execution_options.preserve_order = False
        rows = [{"item": it.model_dump_json(), "input": it.input, "name": it.name, "index": i}
                for i, it in enumerate(items)]
        ds = ray.data.from_items(rows, override_num_blocks=len(rows))
        ds = ds.map(plan_item, fn_kwargs={"store": opts.store, "model": model, "usdz": opts.usdz}, num_cpus=0,
                    compute=ray.data.TaskPoolStrategy(size=min(len(rows), max(2, drives))))
        ds = ds.map(reconstruct_item, fn_kwargs={"store": opts.store, "model": model, "actors": actors,
                                                 "usdz": opts.usdz},
                    num_cpus=0, compute=ray.data.TaskPoolStrategy(size=min(len(rows), drives)))
        run = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        table = Results(opts.results)
        done: list[dict[str, Any]] = []
        try:
            rows_out = iter(ds.iter_rows())
            while True:
                try:
                    row = next(rows_out)
                except StopIteration:
                    break
                except Exception as e:      # noqa: BLE001 - Ray gave up (a task crashed past its retries)
                    raise BatchError(f"Ray stopped the batch after {len(done)} of {len(items)} items: "
                                     f"{failure_of(e)['message']}; run it again to finish") from None
                row = dict(row)
                row["item"] = row.pop("index")
                pub = public_row(row, run)
                table.add(pub)
                done.append(pub)
                say(f"[{len(done)}/{len(items)}] {describe(pub)}")
        finally:
            table.close()
        return done
    finally:
        ray.shutdown()


__all__ = ["EXIT_OK", "EXIT_PARTIAL", "BatchError", "BatchItem", "BatchOptions", "KeyframeWorker", "ManifestError",
           "StoreHandle", "clean_work", "default_sizes", "failure_of", "fetch_input", "input_files", "load_input", "plan_batch", "plan_item",
           "read_manifest", "reconstruct_item", "run_batch", "scene_id_of", "scene_key"]
