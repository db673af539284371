"""The bounded least-recently-used store of the table caches."""

from __future__ import annotations

import pytest

from polarshape.brdf.cache import BoundedCache


def test_least_recently_used_is_dropped_first_and_a_read_counts_as_a_use() -> None:
    cache: BoundedCache[str] = BoundedCache(2)
    cache.put("a", "A")
    cache.put("b", "B")
    assert cache.get("a") == "A"  # now "b" is the least recently used
    cache.put("c", "C")
    assert "b" not in cache and cache.get("a") == "A" and cache.get("c") == "C"
    assert len(cache) == 2
    assert cache.get("missing") is None


def test_values_above_the_element_bound_are_returned_but_not_kept() -> None:
    cache: BoundedCache[list[int]] = BoundedCache(4, max_elements=3)
    big = [0] * 4
    assert cache.put("big", big, len(big)) is big
    assert "big" not in cache
    cache.put("small", [1, 2, 3], 3)
    assert "small" in cache
    assert cache.clear() == 1 and len(cache) == 0


def test_at_least_one_entry() -> None:
    with pytest.raises(ValueError, match="entries"):
        BoundedCache(0)
