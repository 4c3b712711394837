"""Where scenes live: records (record.SceneRecord: state, metadata) and the scene folders, behind base.Store (the
protocol the service uses). ``open_store(settings)`` picks the backend from ``settings.store``: a folder path
(folder.FolderStore) or ``s3://bucket/prefix`` (s3.S3Store, for several replicas; boto3 is imported only then).
Both share record.py's ids and record format and base.BaseStore's quota rules."""

from __future__ import annotations

import math

from .base import BaseStore, Store, StoreFull, StoreUnavailable
from .folder import FolderStore
from .record import SCENE_ID, SceneFailure, SceneRecord, name_error, new_scene_id, valid_id


def open_store(settings) -> Store:
    quota = {"max_scenes": settings.max_scenes, "max_bytes": settings.max_store_bytes,
             "when_full": settings.when_full, "ttl_s": settings.scene_ttl_s}
    if str(settings.store).startswith("s3://"):
        from .s3 import STALE_MARGIN_S, S3Store

        # a running job is updated when it starts and when it ends (within the timeout, plus its upload); a queued
        # one waits for at most the jobs ahead of it on its replica
        running = settings.reconstruct_timeout_s + STALE_MARGIN_S
        queued = running * (1 + math.ceil(settings.reconstruct_queue / settings.reconstruct_workers))
        return S3Store(settings.store, **quota, cache_dir=settings.s3_cache, cache_bytes=settings.s3_cache_bytes,
                       replica_id=settings.replica_id, stale_running_s=running, stale_queued_s=queued)
    return FolderStore(settings.store, **quota)


__all__ = ["SCENE_ID", "BaseStore", "FolderStore", "SceneFailure", "SceneRecord", "Store", "StoreFull",
           "StoreUnavailable", "name_error", "new_scene_id", "open_store", "valid_id"]
