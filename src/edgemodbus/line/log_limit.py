"""Logging that an attacker cannot turn into a flood (the DTU listener faces the internet).

:class:`LogLimiter` logs the first few events of a kind in each interval and folds the
rest into one summary line when the interval ends, with the sources that caused them
("312 connections refused in the last 10 s (too many unregistered): 10.0.0.9 x290,
10.0.0.7 x22").  Memory is bounded too: at most :data:`MAX_SOURCES` sources per kind are
named, the rest are counted as "others".  :func:`hex_prefix` and :func:`short_text`
keep untrusted bytes in a log line short.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

MAX_SOURCES = 64
"""Sources named per kind and interval; more are counted as others."""


def hex_prefix(data: bytes, limit: int = 16) -> str:
    """At most ``limit`` bytes of untrusted ``data`` as hex, with how many were left out."""
    if not data:
        return "nothing"
    shown = data[:limit].hex(" ").upper()
    return shown if len(data) <= limit else f"{shown} ... (+{len(data) - limit} bytes)"


def short_text(text: str, limit: int = 32) -> str:
    """Untrusted text as a short repr."""
    return repr(text) if len(text) <= limit else f"{text[:limit]!r}... ({len(text)} chars)"


@dataclass
class _Kind:
    started: float
    logged: int = 0
    folded: int = 0
    sources: Counter[str] = field(default_factory=Counter)


class LogLimiter:
    """At most ``burst`` lines per kind of event and ``interval``; the rest summarised.

    ``event`` is called from one thread (the listener's); ``flush`` from the same thread,
    on every turn of its loop (cheap when nothing is due)."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0, burst: int = 3,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = logger
        self.interval = interval
        self.burst = burst
        self._clock = clock
        self._kinds: dict[tuple[str, int], _Kind] = {}
        self._due = float("inf")
        self.suppressed = 0  # lines folded into summaries

    def event(self, level: int, kind: str, source: str, msg: str, *args: object) -> None:
        """One event: logged as ``msg % args`` while the kind's burst lasts, else counted
        for the summary, which reads "<n> <kind> in the last <interval> s: <sources>"."""
        now = self._clock()
        key = (kind, level)
        entry = self._kinds.get(key)
        if entry is None:
            entry = self._kinds[key] = _Kind(now)
            self._due = min(self._due, now + self.interval)
        if entry.logged < self.burst:
            entry.logged += 1
            self._log.log(level, msg, *args)
            return
        entry.folded += 1
        self.suppressed += 1
        if source in entry.sources or len(entry.sources) < MAX_SOURCES:
            entry.sources[source] += 1
        else:
            entry.sources["others"] += 1

    def next_due(self) -> float:
        """When :meth:`flush` has a summary to write (monotonic time; inf: none)."""
        return self._due

    def flush(self, force: bool = False) -> None:
        """Write the summaries of the intervals that have ended (all of them: ``force``)."""
        now = self._clock()
        if not force and now < self._due:
            return
        due = float("inf")
        for key, entry in list(self._kinds.items()):
            if not force and now < entry.started + self.interval:
                due = min(due, entry.started + self.interval)
                continue
            del self._kinds[key]
            if entry.folded:
                top = ", ".join(f"{src} x{n}" for src, n in entry.sources.most_common(5))
                more = len(entry.sources) - 5
                self._log.log(key[1], "%d more %s in the last %.0f s: %s%s", entry.folded,
                              key[0], now - entry.started, top,
                              f" and {more} other sources" if more > 0 else "")
        self._due = due


__all__ = ["MAX_SOURCES", "LogLimiter", "hex_prefix", "short_text"]
