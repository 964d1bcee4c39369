"""What a poller reports to: a sink its owner implements, and the delivery to it.

The poller never holds or imports its owner (the driver): the owner hands it a
:class:`PollSink`, the way a protocol stack is given the callbacks of its user.
:class:`Delivery` calls what the sink names: the host's per-item callback as each item
is stored, and the owner's listeners (poll/listeners.py, the seed's batch callback at
their head) with the items of a cycle (or of one write or report) in one batch, with
status changes and with the snapshot.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from ..stats import DeviceStats
from .listeners import BatchCallback, Listener, listener_name

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..datatypes import DeviceDriverStatus

ItemCallback = Callable[["DeviceAddressItem"], None]
SnapshotPublisher = Callable[[str, dict[str, Any]], None]
__all__ = ["BatchCallback", "Delivery", "ItemCallback", "PollSink", "SnapshotPublisher"]


class PollSink(Protocol):
    """The poller's owner, as the poller sees it.  Its callbacks and listeners are asked
    for at each delivery: the host may set, replace, subscribe and unsubscribe them
    while the device is polled."""

    @property
    def source(self) -> object:
        """What the listeners are told they hear from (the driver)."""

    def item_callback(self) -> ItemCallback | None:
        """The callback for each updated item, or None."""

    def listeners(self) -> tuple[Listener[Any], ...]:
        """Who gets the batches, status changes and snapshots, in order (a snapshot
        tuple: the sink replaces it, never changes it); () when nobody does."""

    def snapshot_publisher(self) -> SnapshotPublisher | None:
        """The seed's snapshot publisher, or None."""

    def snapshot(self) -> dict[str, Any]:
        """The owner's snapshot (``driver.snapshot()``)."""


class Delivery:
    """Hands updated items to the sink's callback and listeners.  An exception of a
    callback or listener is logged and counted (``callback_errors``), never raised into
    the poller, and the next listener still runs; the time spent in them is counted too
    (``callback_time``).  Worker thread only."""

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
        """Hand the batch to each listener and start a new one."""
        batch, self.batch = self.batch, []
        if not batch:
            return
        listeners = self.sink.listeners()
        if not listeners:
            return
        source = self.sink.source
        started = time.perf_counter()
        for listener in listeners:
            try:
                listener.on_changes(source, batch)
            except Exception:
                self.counters.callback_errors += 1
                self.log.exception("%s: %s failed (%d items)", self.code,
                                   listener_name(listener), len(batch))
        self.counters.callback_time += time.perf_counter() - started

    def status(self, status: DeviceDriverStatus, reason: str | None) -> None:
        """Tell each listener the device's status changed."""
        listeners = self.sink.listeners()
        if not listeners:
            return
        source = self.sink.source
        started = time.perf_counter()
        for listener in listeners:
            try:
                listener.on_status(source, status, reason)
            except Exception:
                self.counters.callback_errors += 1
                self.log.exception("%s: %s failed on status %s", self.code,
                                   listener_name(listener), status.value)
        self.counters.callback_time += time.perf_counter() - started

    def snapshot_due(self) -> None:
        """Hand the owner's snapshot to the snapshot publisher (a failure logged, as
        ever) and then to each listener (a failure logged and counted)."""
        publisher = self.sink.snapshot_publisher()
        listeners = self.sink.listeners()
        if publisher is None and not listeners:
            return
        snapshot = self.sink.snapshot()
        if publisher is not None:
            try:
                publisher(f"/real/{self.code}", snapshot)
            except Exception:
                self.log.exception("%s: snapshot publisher failed", self.code)
        source = self.sink.source
        for listener in listeners:
            try:
                listener.on_snapshot(source, snapshot)
            except Exception:
                self.counters.callback_errors += 1
                self.log.exception("%s: %s failed on the snapshot", self.code,
                                   listener_name(listener))
