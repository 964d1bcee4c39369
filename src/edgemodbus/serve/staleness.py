"""Why a served unit's reads are answered 0B: counted by reason and told in a
rate-limited WARNING, so that an operator sees polling delayed by jobs on the line (or a
device down, or an item Invalid) instead of a silent 0B flood (issue #25).

The C server counts a unit's reads answered 0B by what it saw (csrc/emb_serve.c
``emb_sv_check``): an item Invalid or not read yet, or the unit older than its
``maxAgeMs``.  The server's thread looks at the counts every tick
(:meth:`StaleWatch.look`) and splits the old ones by their cause, the one an operator
acts on:

* ``pollingDelayed``: the line's jobs (forwards, served writes, commands, reads on
  demand) made polling late by more than its cycle within the unit's max age and a
  second (the server's ticks) before (the line's ``pollsDelayed`` grew: line/jobs.py
  ``PollLag``);
* ``deviceDown``: the device is not Running (Offline, Reconnecting, Connecting);
* ``old``: neither (a ``readCycle`` longer than ``maxAgeMs``, a slow slave);
* ``invalid``: an item of the read is Invalid or not read yet (its own reason says why).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

from ..datatypes import DeviceDriverStatus, ItemStatus
from ..driver import DriverModbusRtu
from ..line.log_limit import LogLimiter

log = logging.getLogger("edgemodbus.serve")

REASONS = ("pollingDelayed", "deviceDown", "old", "invalid")
"""The reasons a served read is answered 0B (the ``reason`` label of the metric)."""


@dataclass(eq=False)
class StaleWatch:
    """One served unit's 0B answers (server thread, but :attr:`answered_ns`, which the
    unit's listener sets on the line's worker too: one int, written whole)."""

    unit_id: int
    device: str
    driver: DriverModbusRtu
    max_age: float | None
    answered_ns: int = 0  # the slave last answered (time.monotonic_ns()), as last seen
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REASONS, 0))
    _seen: tuple[int, int] = (0, 0)  # the C counts (old, invalid) at the last look
    _delayed: int = 0  # the line's pollsDelayed at the last look
    _delayed_ns: int = -(1 << 62)  # when that count last grew

    def lag_seen(self, stats: dict[str, Any], now_ns: int) -> None:
        """The driver's ``stats()`` of this tick: note when the line last delayed polling
        (the freshness check reads them every tick for a unit with a max age)."""
        delayed = int(stats.get("line", {}).get("pollsDelayed", 0))
        if delayed != self._delayed:
            self._delayed, self._delayed_ns = delayed, now_ns

    def look(self, seen: tuple[int, int], now_ns: int, limiter: LogLimiter) -> None:
        """The C counts of now: new 0B answers are counted by reason and logged."""
        old, invalid = seen[0] - self._seen[0], seen[1] - self._seen[1]
        if old < 0 or invalid < 0:  # the unit was set again: its counts restarted
            old, invalid = max(seen[0], 0), max(seen[1], 0)
        self._seen = seen
        if old > 0:
            self._old(old, now_ns, limiter)
        if invalid > 0:
            self.counts["invalid"] += invalid
            limiter.event(logging.WARNING, f"reads of unit {self.unit_id} answered 0B",
                          f"unit {self.unit_id}", "serve: unit %d (%s): %d reads answered "
                          "0B: an item is Invalid or not read yet (%s)", self.unit_id,
                          self.device, invalid, self._invalid_reason())
        limiter.flush()

    def _old(self, n: int, now_ns: int, limiter: LogLimiter) -> None:
        max_age = self.max_age or 0.0
        age = (now_ns - self.answered_ns) / 1e9 if self.answered_ns else None
        status = self.driver.device_driver_status
        if status is not DeviceDriverStatus.RUNNING:
            reason, why = "deviceDown", f"the device is {status.value}"
        elif now_ns - self._delayed_ns <= int((max_age + 1.0) * 1e9):
            reason = "pollingDelayed"
            why = (f"polling delayed by jobs on the line (pollsDelayed {self._delayed}: "
                   "forwards, served writes, commands or reads on demand ran while polling "
                   "was due; see the line's jobsAheadOfPolls)")
        else:
            reason, why = "old", "the slave answered no read within maxAgeMs (its readCycle " \
                "or response time is longer)"
        self.counts[reason] += n
        limiter.event(logging.WARNING, f"reads of unit {self.unit_id} answered 0B",
                      f"unit {self.unit_id}", "serve: unit %d (%s): %d reads answered 0B: "
                      "its data is %s old, over maxAgeMs %d: %s", self.unit_id, self.device,
                      n, "never read" if age is None else f"{age:.2f} s",
                      round(max_age * 1000), why)

    def _invalid_reason(self) -> str:
        """The first Invalid item's name and reason (one is enough to act on)."""
        for item in self.driver.address_items:
            if item.status is not ItemStatus.OK:
                return f"e.g. {item.name}: {item.error_reason or item.status.value}"
        return "no item Invalid now"


def stale_limiter() -> LogLimiter:
    """The server's limiter of these lines: three per unit per 10 s, then a summary."""
    return LogLimiter(log, interval=10.0, burst=3, clock=time.monotonic)


__all__ = ["REASONS", "StaleWatch", "stale_limiter"]
