"""The queues between the threads that produce messages (line workers, the command thread,
attach and detach) and the MQTT thread that sends them; producers never touch paho."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterable, MutableMapping
from typing import TYPE_CHECKING, Any, NamedTuple

from .devices import AttachedDevice

if TYPE_CHECKING:
    from ...config import DeviceAddressItem

Row = tuple[str, Any, Any, Any, Any]  # item name, value, status, updateTs, errorReason


class Message(NamedTuple):
    """One MQTT message on its way to the broker (control messages wait as these; item
    updates and snapshots become these when the MQTT thread sends them)."""

    device: str | None  # the device it is about; None: the gateway's own
    topic: str
    payload: bytes
    qos: int
    retain: bool


_CONTROL_LIMIT = 10_000


class Report:
    """What one device reported in one cycle (its batch callback): the unit of the batch
    mode's messages.  Trimming (an outage) may drop its oldest rows."""

    __slots__ = ("dev", "rows")

    def __init__(self, dev: AttachedDevice, rows: list[Row]) -> None:
        self.dev = dev
        self.rows = rows


class Outbox:
    """Item updates (bounded, see :meth:`limit`), the latest snapshot of each device,
    control messages (statuses, replies), actions for the MQTT thread, and the publisher's
    counters, all under one lock; a socket pair wakes the MQTT thread's select() when
    something arrives."""

    def __init__(self, queue_size: int) -> None:
        self.queue_size = queue_size
        self.lock = threading.Lock()
        self.reports: deque[Report] = deque()
        self.queued = 0  # item updates in self.reports
        self.burst = 0  # the largest report of each attached device, summed
        self.outage = False  # a connect failed or the connection was lost, no CONNACK since
        self.spooling = False  # store-and-forward: an outage goes to the spool instead
        self.spool_memory = 0  # store-and-forward's memoryQueueSize: the outage's margin
        self.snapshots: dict[str, tuple[AttachedDevice, dict[str, Any]]] = {}
        self.control: deque[Message] = deque()
        self.actions: deque[Callable[[], None]] = deque()
        self.counts: dict[str, int] = dict.fromkeys(
            ("connects", "disconnects", "connectFailures", "published", "batchesPublished",
             "acknowledged", "dropped", "publishErrors", "lostOnDisconnect",
             "snapshotsPublished",
             "snapshotsCoalesced", "commands", "commandErrors", "controlDropped"), 0)
        self.wake_r, self._wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._wake_pending = False
        # devices whose status changed (or whose DTU arrived): the MQTT thread looks at
        # these only, never at every device per tick (an idle fleet instance costs nothing)
        self.status_due: dict[str, AttachedDevice] = {}

    def limit(self) -> int:
        """How many item updates may wait (under the lock).  During an outage,
        ``queueSize``.  Otherwise also one full report of every attached device (its
        largest so far: at start-up every item's first read), so that a burst is never
        dropped while the broker takes what we send; the bound is still there against a
        broker too slow for the updates.  With store-and-forward (``spooling``) an
        outage keeps the normal limit plus ``memoryQueueSize``: the MQTT thread moves
        reports to the spool, and the margin covers the seconds it may be kept from
        running (a slow disk, a loaded machine) without dropping any."""
        if self.spooling:
            return self.queue_size + self.burst + self.spool_memory
        if self.outage:
            return self.queue_size
        return self.queue_size + self.burst

    def offer_items(self, dev: AttachedDevice, items: list[DeviceAddressItem]) -> None:
        rows = [(it.name, it.value, it.status, it.update_ts, it.error_reason) for it in items]
        status = dev.driver.device_driver_status  # a cheap look: did the status change?
        with self.lock:
            if status is not dev.seen_status:
                dev.seen_status = status
                self.status_due[dev.code] = dev
            if len(rows) > dev.largest and dev.attached:
                self.burst += len(rows) - dev.largest
                dev.largest = len(rows)
            self.reports.append(Report(dev, rows))
            self.queued += len(rows)
            self._trim()
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self.wake()

    def _trim(self) -> None:
        """Drop the oldest updates beyond the limit (under the lock): a newer update of an
        item supersedes them."""
        over = self.queued - self.limit()
        if over <= 0:
            return
        self.counts["dropped"] += over
        self.queued -= over
        reports = self.reports
        while over:
            first = reports[0]
            if len(first.rows) <= over:
                reports.popleft()
                first.dev.dropped += len(first.rows)
                over -= len(first.rows)
            else:
                first.dev.dropped += over
                first.rows = first.rows[over:]
                over = 0

    def set_outage(self, outage: bool) -> None:
        """The broker became unreachable (True: the queue shrinks to ``queueSize`` at once,
        oldest dropped) or took our connection (False)."""
        with self.lock:
            self.outage = outage
            self._trim()

    def forget(self, dev: AttachedDevice) -> None:
        """A detached device's burst no longer counts (under the lock)."""
        dev.attached = False
        self.burst -= dev.largest
        self.status_due.pop(dev.code, None)

    def take_reports(self, room: int, split: bool) -> list[Report]:
        """The oldest reports (under the lock), at most ``room`` messages' worth: one
        message a report, or with ``split`` one a row (a report is cut to fit)."""
        taken: list[Report] = []
        reports = self.reports
        while room > 0 and reports:
            first = reports[0]
            if not split:
                taken.append(reports.popleft())
                self.queued -= len(first.rows)
                room -= 1
            elif len(first.rows) <= room:
                taken.append(reports.popleft())
                self.queued -= len(first.rows)
                room -= len(first.rows)
            else:
                taken.append(Report(first.dev, first.rows[:room]))
                first.rows = first.rows[room:]
                self.queued -= room
                room = 0
        return taken

    def put_back(self, reports: list[Report]) -> None:
        """Reports (or their remainders) not taken by paho, to the front, oldest first
        (under the lock)."""
        for report in reversed(reports):
            self.reports.appendleft(report)
            self.queued += len(report.rows)

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

    def push_control(self, message: Message) -> None:
        with self.lock:
            if len(self.control) >= _CONTROL_LIMIT:
                self.counts["controlDropped"] += 1
                return
            self.control.append(message)
        self.wake()

    def count(self, key: str, n: int = 1) -> None:
        with self.lock:
            self.counts[key] += n

    def status_changed(self, dev: AttachedDevice) -> None:
        """Have the MQTT thread look at ``dev``'s status (any thread)."""
        with self.lock:
            self.status_due[dev.code] = dev
        self.wake()

    def take_status_due(self, held: MutableMapping[str, AttachedDevice]
                        ) -> list[AttachedDevice]:
        """The devices to look at: those :meth:`status_changed` named since the last
        call, then the ``held`` ones (a fleet's DTUs connected here) not among them; only
        attached ones (a device detached while held leaves ``held`` here: the MQTT
        thread's, as is this call)."""
        with self.lock:
            due, self.status_due = self.status_due, {}
            for code in [code for code, dev in held.items() if not dev.attached]:
                del held[code]
            return [dev for dev in (*due.values(), *(d for code, d in held.items()
                                                     if code not in due)) if dev.attached]

    def look_at(self, devices: Iterable[AttachedDevice]) -> None:
        """Have the MQTT thread look at each of ``devices`` (a connection, an arrival)."""
        with self.lock:
            self.status_due.update((dev.code, dev) for dev in devices)
        self.wake()

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
