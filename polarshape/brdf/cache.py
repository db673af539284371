"""A bounded least-recently-used store: the table builders' layout caches (:mod:`polarshape.brdf.body_fast`,
:mod:`polarshape.brdf.smith`) and a run's tables (:class:`polarshape.recover.coarse_to_fine.TableCache`).

Written here rather than taken from a library: ``functools.lru_cache`` wraps a function (these caches are
filled by builders whose keys leave out some arguments, and skip entries above a size), and a dependency
such as ``cachetools`` for twenty lines was not worth it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from typing import Generic, TypeVar

__all__ = ["BoundedCache"]

V = TypeVar("V")


class BoundedCache(Generic[V]):
    """At most ``entries`` values by key, the least recently used dropped first; values of more than
    ``max_elements`` elements (as the caller counts them) are not kept.

    Args:
        entries: how many values are kept (≥ 1).
        max_elements: the largest value :meth:`put` keeps (None: any).
    """

    def __init__(self, entries: int, max_elements: int | None = None) -> None:
        if entries < 1:
            raise ValueError(f"BoundedCache: entries must be ≥ 1 (got {entries})")
        self.entries = entries
        self.max_elements = max_elements
        self._values: OrderedDict[Hashable, V] = OrderedDict()

    def __len__(self) -> int:
        return len(self._values)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._values

    def get(self, key: Hashable) -> V | None:
        """The value of ``key`` (now the most recently used), or None."""
        value = self._values.get(key)
        if value is not None:
            self._values.move_to_end(key)
        return value

    def put(self, key: Hashable, value: V, elements: int = 0) -> V:
        """Keep ``value`` under ``key`` unless it has more than ``max_elements`` elements; returns it."""
        if self.max_elements is None or elements <= self.max_elements:
            self._values[key] = value
            self._values.move_to_end(key)
            while len(self._values) > self.entries:
                self._values.popitem(last=False)
        return value

    def clear(self) -> int:
        """Drop every value; returns how many there were."""
        n = len(self._values)
        self._values.clear()
        return n
