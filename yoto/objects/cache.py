"""Data derived from an object model once and reused by every query: anchor maps, distance fields, search samples.

Each kind of derived data has one `ModelCache`, keyed by the model's fingerprint and the settings that shape the
data (a frozen dataclass), so that per-query settings never trigger a rebuild. Few models are in use at once, so a
small first-in-first-out cache is enough; the build runs outside the lock (seconds), and two threads that miss
together both build and keep one.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from yoto.objects.model import ObjectModel

Settings = TypeVar("Settings", bound=Hashable)
Derived = TypeVar("Derived")


class ModelCache(Generic[Settings, Derived]):
    """`build(model, settings)` computed once per (model fingerprint, settings); at most `size` entries kept."""

    def __init__(self, build: Callable[[ObjectModel, Settings], Derived], size: int = 4):
        self.build = build
        self.size = size
        self._entries: dict[tuple[str, Settings], Derived] = {}
        self._lock = threading.Lock()

    def get(self, model: ObjectModel, settings: Settings) -> Derived:
        key = (model.fingerprint, settings)
        with self._lock:
            cached = self._entries.get(key)
        if cached is None:
            cached = self.build(model, settings)
            with self._lock:
                cached = self._entries.setdefault(key, cached)
                while len(self._entries) > self.size:
                    self._entries.pop(next(iter(self._entries)))
        return cached

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
