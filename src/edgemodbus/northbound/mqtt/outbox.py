"""The queues between the threads that produce messages (line workers, the command thread,
attach and detach) and the MQTT thread that sends them; producers never touch paho."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from .devices import AttachedDevice

if TYPE_CHECKING:
    from ...config import DeviceAddressItem

Row = tuple[AttachedDevice, str, Any, Any, Any, Any]  # device, name, value, status, ts, error
Control = tuple[str, bytes, int, bool]  # topic, payload, qos, retain

_CONTROL_LIMIT = 10_000


class Outbox:
    """Item updates (bounded: the oldest are dropped and counted), the latest snapshot of
    each device, control messages (statuses, replies), actions for the MQTT thread, and
    the publisher's counters, all under one lock; a socket pair wakes the MQTT thread's
    select() when something arrives."""

    def __init__(self, queue_size: int) -> None:
        self.queue_size = queue_size
        self.lock = threading.Lock()
        self.rows: deque[Row] = deque()
        self.snapshots: dict[str, tuple[AttachedDevice, dict[str, Any]]] = {}
        self.control: deque[Control] = deque()
        self.actions: deque[Callable[[], None]] = deque()
        self.counts: dict[str, int] = dict.fromkeys(
            ("connects", "disconnects", "connectFailures", "published", "dropped",
             "publishErrors", "snapshotsPublished", "snapshotsCoalesced", "commands",
             "commandErrors", "controlDropped"), 0)
        self.wake_r, self._wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._wake_pending = False
        self.status_dirty = False  # a device's status changed: check the statuses now

    def offer_items(self, dev: AttachedDevice, items: list[DeviceAddressItem]) -> None:
        rows = [(dev, it.name, it.value, it.status, it.update_ts, it.error_reason)
                for it in items]
        limit = self.queue_size
        status = dev.driver.device_driver_status  # a cheap look: did the status change?
        with self.lock:
            if status is not dev.seen_status:
                dev.seen_status = status
                self.status_dirty = True
            queue = self.rows
            queue.extend(rows)
            over = len(queue) - limit
            if over > 0:  # drop the oldest: a newer update of an item supersedes it
                self.counts["dropped"] += over
                for _ in range(over):
                    queue.popleft()[0].dropped += 1
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self.wake()

    def offer_snapshot(self, dev: AttachedDevice, snapshot: dict[str, Any]) -> None:
        with self.lock:
            if dev.code in self.snapshots:
                dev.snapshots_coalesced += 1
                self.counts["snapshotsCoalesced"] += 1
            self.snapshots[dev.code] = (dev, snapshot)
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self.wake()

    def push_control(self, topic: str, payload: bytes, qos: int, retain: bool) -> None:
        with self.lock:
            if len(self.control) >= _CONTROL_LIMIT:
                self.counts["controlDropped"] += 1
                return
            self.control.append((topic, payload, qos, retain))
        self.wake()

    def count(self, key: str, n: int = 1) -> None:
        with self.lock:
            self.counts[key] += n

    def act(self, action: Callable[[], None]) -> None:
        with self.lock:
            self.actions.append(action)
        self.wake()

    def wake(self) -> None:
        with contextlib.suppress(OSError):  # full (already woken) or closed
            self._wake_w.send(b"\0")

    def take_actions(self) -> list[Callable[[], None]]:
        with self.lock:
            actions = list(self.actions)
            self.actions.clear()
        return actions

    def woken(self) -> None:
        """The MQTT thread woke up: empty the wake-up socket."""
        with self.lock:
            self._wake_pending = False
        with contextlib.suppress(OSError):
            while self.wake_r.recv(4096):
                pass

    def close(self) -> None:
        for sock in (self.wake_r, self._wake_w):
            sock.close()
