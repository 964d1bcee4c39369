"""The live tag stream: a driver's listener that exists only while a browser watches.

The first stream of a device subscribes a :class:`DeviceFeed` to its driver
(``driver.subscribe``, poll/listeners.py); the last one to close unsubscribes it, so a
gateway nobody looks at pays nothing per cycle.  On the line worker the feed copies the
changed items' fields (value, status, reason, time) into a dict by name and, if none is
pending, posts one wake-up to the console's loop; there each stream merges them into
its own pending dict (by name: a slow browser gets the latest value of each tag, never
an unbounded queue) and sends them as one server-sent event, at most
:data:`MIN_INTERVAL` apart."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from typing import TYPE_CHECKING, Any

from ..driver import DriverModbusRtu
from .views import change_row

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..datatypes import DeviceDriverStatus

MIN_INTERVAL = 0.2  # seconds between two events of one stream: at most 5 per second


class Stream:
    """One browser's stream of one device: what it has not been sent yet."""

    def __init__(self, feed: DeviceFeed) -> None:
        self.feed = feed
        self.rows: dict[str, dict[str, Any]] = {}
        self.status: dict[str, Any] | None = None
        self.ready = asyncio.Event()

    def offer(self, rows: dict[str, dict[str, Any]], status: dict[str, Any] | None) -> None:
        self.rows.update(rows)
        if status is not None:
            self.status = status
        self.ready.set()

    def take(self) -> dict[str, Any]:
        """The event to send: the rows and the status since the last one."""
        event: dict[str, Any] = {"rows": list(self.rows.values())}
        if self.status is not None:
            event["status"] = self.status
        self.rows, self.status = {}, None
        self.ready.clear()
        return event


class DeviceFeed:
    """The listener of one driver while it has streams (see the module's docstring)."""

    def __init__(self, driver: DriverModbusRtu, loop: asyncio.AbstractEventLoop) -> None:
        self.driver = driver
        self.loop = loop
        self.streams: set[Stream] = set()
        self._lock = threading.Lock()
        self._rows: dict[str, dict[str, Any]] = {}
        self._status: dict[str, Any] | None = None
        self._posted = False

    # -- the line worker's side (poll/listeners.py Listener) ----------------------------
    def on_changes(self, source: object, items: list[DeviceAddressItem]) -> None:
        rows = [change_row(item) for item in items]
        with self._lock:
            for row in rows:
                self._rows[row["name"]] = row
            self._post()

    def on_status(self, source: object, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        with self._lock:
            self._status = {"status": status.value, "reason": reason}
            self._post()

    def on_snapshot(self, source: object, snapshot: dict[str, Any]) -> None:
        return None

    def _post(self) -> None:
        """Under the lock: one wake-up of the loop for any number of changes."""
        if self._posted:
            return
        self._posted = True
        try:
            self.loop.call_soon_threadsafe(self._deliver)
        except RuntimeError:  # the loop closed: the console is stopping
            self._posted = False

    # -- the console's loop -------------------------------------------------------------
    def _deliver(self) -> None:
        with self._lock:
            rows, status = self._rows, self._status
            self._rows, self._status, self._posted = {}, None, False
        for stream in self.streams:
            stream.offer(rows, status)


class Feeds:
    """The feeds of the drivers being watched; used on the console's loop only."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._feeds: dict[int, DeviceFeed] = {}

    def open(self, driver: DriverModbusRtu) -> Stream:
        """A stream of ``driver``; its first subscribes the driver's feed."""
        feed = self._feeds.get(id(driver))
        if feed is None or feed.driver is not driver:
            feed = DeviceFeed(driver, self.loop)
            driver.subscribe(feed)
            self._feeds[id(driver)] = feed
        stream = Stream(feed)
        feed.streams.add(stream)
        return stream

    def close(self, stream: Stream) -> None:
        """The stream ended; the last of a driver unsubscribes its feed."""
        feed = stream.feed
        feed.streams.discard(stream)
        if not feed.streams and self._feeds.get(id(feed.driver)) is feed:
            del self._feeds[id(feed.driver)]
            with contextlib.suppress(ValueError):  # already gone with its driver
                feed.driver.unsubscribe(feed)

    @property
    def subscribed(self) -> int:
        """Drivers with a feed subscribed now (tests: none while no stream is open)."""
        return len(self._feeds)

    @property
    def streams(self) -> int:
        return sum(len(feed.streams) for feed in self._feeds.values())


__all__ = ["MIN_INTERVAL", "DeviceFeed", "Feeds", "Stream"]
