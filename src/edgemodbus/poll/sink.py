"""What a poller reports to: a sink its owner implements, and the delivery to it.

The poller never holds or imports its owner (the driver): the owner hands it a
:class:`PollSink`, the way a protocol stack is given the callbacks of its user.
:class:`Delivery` calls the host's callbacks the sink names: each updated item as it is
stored, and the items of a cycle (or of one write or report) in one batch.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from ..stats import DeviceStats

if TYPE_CHECKING:
    from ..config import DeviceAddressItem

ItemCallback = Callable[["DeviceAddressItem"], None]
BatchCallback = Callable[[list["DeviceAddressItem"]], None]


class PollSink(Protocol):
    """The poller's owner, as the poller sees it.  The callbacks are asked for at each
    delivery: the host may set or replace them while the device is polled."""

    def item_callback(self) -> ItemCallback | None:
        """The callback for each updated item, or None."""

    def batch_callback(self) -> BatchCallback | None:
        """The callback for the items updated together (a cycle, a write, a report)."""

    def snapshot_due(self) -> None:
        """A cycle ended and the snapshot interval elapsed: publish the snapshot."""


class Delivery:
    """Hands updated items to the sink's callbacks.  A callback's exception is logged
    and counted (``callback_errors``), never raised into the poller; the time spent in
    the callbacks is counted too (``callback_time``).  Worker thread only."""

    __slots__ = ("batch", "code", "counters", "log", "sink")

    def __init__(self, sink: PollSink, counters: DeviceStats, log: logging.Logger,
                 code: str) -> None:
        self.sink = sink
        self.counters = counters
        self.log = log
        self.code = code
        self.batch: list[DeviceAddressItem] = []

    def report(self, items: list[DeviceAddressItem]) -> None:
        """Add items to this cycle's batch and call the per-item callback for each."""
        self.batch += items
        self.notify(items)

    def notify(self, items: list[DeviceAddressItem]) -> None:
        """Call the per-item callback for each item."""
        callback = self.sink.item_callback()
        if callback is None:
            return
        started = time.perf_counter()
        for item in items:
            try:
                callback(item)
            except Exception:
                self.counters.callback_errors += 1
                self.log.exception("%s: address_updated_callback failed for item %r",
                                   self.code, item.name)
        self.counters.callback_time += time.perf_counter() - started

    def flush(self) -> None:
        """Hand the batch to the batch callback and start a new one."""
        batch, self.batch = self.batch, []
        callback = self.sink.batch_callback()
        if not batch or callback is None:
            return
        started = time.perf_counter()
        try:
            callback(batch)
        except Exception:
            self.counters.callback_errors += 1
            self.log.exception("%s: addresses_updated_callback failed (%d items)",
                               self.code, len(batch))
        self.counters.callback_time += time.perf_counter() - started
