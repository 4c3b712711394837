"""In-memory caches of the render path: loaded scenes (LRU by count) and encoded views (LRU by bytes). Both are
thread-safe; renders run in the render pool's threads."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any


class SceneCache:
    """Up to ``size`` loaded scenes. ``get`` loads a missing one with ``load()`` once even when several threads
    ask at the same time."""

    def __init__(self, size: int):
        self.size = int(size)
        self._items: OrderedDict[str, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[str, threading.Lock] = {}

    def get(self, key: str, load: Callable[[], Any]) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
            gate = self._loading.setdefault(key, threading.Lock())
        with gate:
            with self._lock:
                if key in self._items:
                    return self._items[key]
            try:
                value = load()
            finally:
                with self._lock:
                    self._loading.pop(key, None)
            with self._lock:
                self._items[key] = value
                self._items.move_to_end(key)
                while len(self._items) > self.size:
                    self._items.popitem(last=False)
            return value

    def drop(self, key: str) -> None:
        with self._lock:
            self._items.pop(key, None)


class BytesCache:
    """Encoded responses keyed by a string, at most ``budget`` bytes in all (least recently used dropped)."""

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.used = 0
        self._items: OrderedDict[str, tuple[str, bytes]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: str) -> bytes | None:
        with self._lock:
            hit = self._items.get(key)
            if hit is None:
                return None
            self._items.move_to_end(key)
            return hit[1]

    def put(self, key: str, value: bytes, owner: str = "") -> None:
        if len(value) > self.budget // 4:       # one huge view must not flush everything else
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.used -= len(old[1])
            self._items[key] = (owner, value)
            self.used += len(value)
            while self.used > self.budget and self._items:
                _, (_, v) = self._items.popitem(last=False)
                self.used -= len(v)

    def drop_owner(self, owner: str) -> None:
        with self._lock:
            for k in [k for k, (o, _) in self._items.items() if o == owner]:
                self.used -= len(self._items.pop(k)[1])


__all__ = ["BytesCache", "SceneCache"]
