"""A small cache of immutable compiled things that many devices share.

A gateway started from one template runs thousands of devices with the same address
list: their read plans (poll/plan_cache.py) and their blocks' compiled codec layouts
(codec/decoder.py) are equal, so each is compiled once and shared.  Only what is never
written after it is built goes in here; a device's state (decoder change tracking, item
values) stays its own.

Bounded: the ``keep`` most recently used entries are held; older ones stay reachable
only while something else holds them (``weak``: by weak reference; else they are
dropped), so a value is never compiled twice while a device still uses it.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

V = TypeVar("V")


class _Key:
    """A key whose hash is computed once (a template's key is a tuple of many specs)."""

    __slots__ = ("hash", "key")

    def __init__(self, key: Hashable) -> None:
        self.key = key
        self.hash = hash(key)

    def __hash__(self) -> int:
        return self.hash

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Key) and self.hash == other.hash and self.key == other.key


class SharedCache(Generic[V]):
    """``get(key, make)``: the value cached under ``key``, else ``make()``'s (cached).
    Thread-safe; ``make`` runs outside the lock (two threads may both make a value the
    first time; one of them is kept).  ``hits`` and ``misses`` count the lookups."""

    def __init__(self, keep: int, weak: bool = True) -> None:
        if not (isinstance(keep, int) and keep >= 1):
            raise ValueError(f"SharedCache keep {keep!r} is not allowed (an int >= 1)")
        self.keep = keep
        self._lock = threading.Lock()
        self._recent: OrderedDict[Hashable, V] = OrderedDict()
        self._weak: weakref.WeakValueDictionary[Hashable, V] | None = (
            weakref.WeakValueDictionary() if weak else None)
        self.hits = 0
        self.misses = 0

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        key = _Key(key)  # hashed once here, not at each of the dicts below
        with self._lock:
            value = self._found(key)
            if value is not None:
                return value
            self.misses += 1
        value = make()
        with self._lock:
            if self._weak is not None:
                value = self._weak.setdefault(key, value)
            self._hold(key, value)
        return value

    def peek(self, key: Hashable) -> V | None:
        """The value cached under ``key`` (counted as a hit), else None (not counted:
        the caller makes it and :meth:`get` it later, or not at all)."""
        with self._lock:
            return self._found(_Key(key))

    def _found(self, key: Hashable) -> V | None:
        """The value under ``key``, held as the most recent and counted as a hit; else
        None (under the lock)."""
        value = self._recent.get(key)
        if value is None and self._weak is not None:
            value = self._weak.get(key)
        if value is not None:
            self.hits += 1
            self._hold(key, value)
        return value

    def _hold(self, key: Hashable, value: V) -> None:
        recent = self._recent
        recent[key] = value
        recent.move_to_end(key)
        while len(recent) > self.keep:
            recent.popitem(last=False)

    def __len__(self) -> int:
        """Entries reachable now (held, or alive elsewhere)."""
        with self._lock:
            if self._weak is not None:
                return len(self._weak)
            return len(self._recent)

    def clear(self) -> None:
        """Forget every entry (values in use stay with their users)."""
        with self._lock:
            self._recent.clear()
            if self._weak is not None:
                self._weak.clear()
