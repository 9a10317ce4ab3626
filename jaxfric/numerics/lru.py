"""A bounded least-recently-used store: what the package keeps between calls (compiled programs of
:func:`jaxfric.loadpath.run.run`, curves and grids of :func:`jaxfric.identification.fit.fit`), kept for a few keys
only, so that a process that runs or fits many models does not hold every compiled program until it runs out
of memory."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

__all__ = ["LRU"]

V = TypeVar("V")


class LRU(Generic[V]):
    """At most ``maxsize`` entries by key; the least recently used one is dropped to make room."""

    def __init__(self, maxsize: int):
        self.maxsize = maxsize
        self._entries: dict[Hashable, V] = {}

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        """The entry of ``key``, made by ``make()`` when there is none (dropping the least recently
        used entries first, so that the new one is at most the ``maxsize``-th)."""
        if key in self._entries:
            self._entries[key] = self._entries.pop(key)  # now the most recently used
        else:
            while len(self._entries) >= self.maxsize:
                del self._entries[next(iter(self._entries))]
            self._entries[key] = make()
        return self._entries[key]

    def __len__(self) -> int:
        return len(self._entries)

    def values(self) -> list[V]:
        """The entries, least recently used first."""
        return list(self._entries.values())
