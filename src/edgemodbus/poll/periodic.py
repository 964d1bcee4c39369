"""Report by change, by period, or both: each item's effective ``reportMode`` and
``reportEvery`` (the item's, else the device's; docs/reporting.md), and the period
reports of a device's items that use them.

The engine reports changes only (csrc/emb_codec.c, ``EMB_MODE_TRACK``) or every item
of every read (``EMB_MODE_ALL``, when every item of the device reports by cycle).  An
item that reports by change with a ``reportEvery``, or by cycle on a device whose other
items report by change, is reported again at a pass end once its last report (its
``updateTs``) is older than its period.  Only those items are looked at, in a heap by
due time, and only at the pass ends where the earliest of them is due: the poller asks
the engine for that pass (``notify_at``); devices without such items have no heap, and
their passes never enter Python for it.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import TYPE_CHECKING

from ..config import DriverModbusRtuParameter
from .items import ItemState

if TYPE_CHECKING:
    from ..config import DeviceAddressItem

#: A pass end may come this share of the item's scan rate early and still count as
#: the due one (the engine's own tolerance for due blocks, csrc/emb_engine.c: a tenth).
TOLERANCE = 0.1


def report_mode(item: DeviceAddressItem, params: DriverModbusRtuParameter) -> str:
    """The item's reportMode: its own, else "change" when it has a reportEvery of its
    own (a period is a rule for reports by change), else the device's."""
    if item.report_mode is not None:
        return item.report_mode
    return "change" if item.report_every is not None else params.report_mode


def reports_all(states: Sequence[ItemState], params: DriverModbusRtuParameter) -> bool:
    """Whether the device reports every item at every read (the engine's ALL mode, no
    per-item work): its reportMode is cycle and no item reports by change."""
    return params.report_mode == "cycle" and all(
        report_mode(s.item, params) == "cycle" for s in states)


def report_period(item: DeviceAddressItem, rate: int,
                  params: DriverModbusRtuParameter) -> int | None:
    """The item's period in ms (``rate``: its scan rate), or None: reported by change
    only.  By cycle: its scan rate (each read); by change: its reportEvery, else the
    device's.  An item that is not polled (rate 0, or -1: on demand) has none."""
    if rate <= 0:
        return None
    if report_mode(item, params) == "cycle":
        return rate
    return item.report_every if item.report_every is not None else params.report_every


class PeriodicReports:
    """The items of one device reported by period, in a heap by due time (monotonic).
    Worker thread only."""

    __slots__ = ("_heap",)

    def __init__(self, entries: Sequence[tuple[DeviceAddressItem, float]], now: float) -> None:
        """``entries``: each item with the age (s) at which it is reported again."""
        self._heap = [(now + every, seq, item, every)
                      for seq, (item, every) in enumerate(entries)]
        heapq.heapify(self._heap)

    @staticmethod
    def build(states: Sequence[ItemState], rates: Sequence[int],
              params: DriverModbusRtuParameter, now: float) -> PeriodicReports | None:
        """The period reports of ``states`` (``rates``: their scan rates, ms), or None
        when none of them has a period (nothing to check, ever)."""
        if reports_all(states, params):
            return None
        entries = []
        for state, rate in zip(states, rates, strict=True):
            period = report_period(state.item, rate, params)
            if period is not None:
                entries.append((state.item, (period - TOLERANCE * rate) / 1000))
        return PeriodicReports(entries, now) if entries else None

    @property
    def next_due(self) -> float:
        """When the earliest item is due (``time.monotonic()``)."""
        return self._heap[0][0]

    def __len__(self) -> int:
        return len(self._heap)

    def due(self, now: float, stamp: datetime | None = None) -> list[DeviceAddressItem]:
        """The items due at ``now`` whose last report is at least their period old,
        stamped with the time of this report (``stamp``, default the wall clock's now);
        the others are due again when their last report (a change) will be that old."""
        heap = self._heap
        reported: list[DeviceAddressItem] = []
        if heap[0][0] > now:
            return reported
        stamp = datetime.now(timezone.utc) if stamp is None else stamp
        while heap[0][0] <= now:
            _, seq, item, every = heap[0]
            last = item.update_ts
            if last is None:  # never read: nothing to report again yet
                wait = every
            else:
                age = (stamp - last).total_seconds()
                if age >= every:
                    item.update_ts = stamp
                    reported.append(item)
                    wait = every
                else:  # reported since (a change); a clock set back: one period
                    wait = min(every - age, every)
            heapq.heapreplace(heap, (now + wait, seq, item, every))
        return reported
