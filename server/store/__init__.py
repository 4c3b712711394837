"""Where scenes live: records (state, metadata) and the scene folders. ``open_store(settings)`` picks the
backend from ``settings.store`` (a folder path today)."""

from __future__ import annotations

from .folder import SCENE_ID, FolderStore, StoreFull, new_scene_id


def open_store(settings) -> FolderStore:
    return FolderStore(settings.store, max_scenes=settings.max_scenes, max_bytes=settings.max_store_bytes,
                       when_full=settings.when_full, ttl_s=settings.scene_ttl_s)


__all__ = ["SCENE_ID", "FolderStore", "StoreFull", "new_scene_id", "open_store"]
