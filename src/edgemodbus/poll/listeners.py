"""Subscribers of a device: the :class:`Listener` protocol and the list that holds them.

A driver keeps a list of listeners, as python-can's ``Notifier`` keeps its listeners,
instead of one callback attribute that each subscriber replaces and chains by hand (a
chain breaks when a subscriber in its middle restores what it replaced).  Subscribing
and unsubscribing copy the list (:class:`Subscribers`, under a lock); the line worker
reads one attribute, a tuple, and iterates it without a lock.  Delivery, with each
listener's exception caught, logged and counted, is :class:`~edgemodbus.poll.sink.Delivery`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..datatypes import DeviceDriverStatus

Source = TypeVar("Source", contravariant=True)
"""What a listener is subscribed to (the driver: :class:`edgemodbus.DriverModbusRtu`)."""
T = TypeVar("T")


class Listener(Protocol[Source]):
    """A subscriber of a driver (``driver.subscribe(listener)``).  Every method runs on
    the driver's line worker: keep it short (queue and return); an exception is logged
    and counted in the driver's ``callbackErrors`` and the other listeners still run.
    A class that subclasses ``Listener`` inherits no-op :meth:`on_status` and
    :meth:`on_snapshot`."""

    def on_changes(self, source: Source, items: list[DeviceAddressItem]) -> None:
        """The items reported together: a cycle's changes (every item read, in
        ``reportMode: "cycle"``) with its period reports (``reportEvery``), one confirmed
        write, one wrapped report, one read on demand (docs/reporting.md).  Never empty.
        The list is shared by every listener of the driver: do not change it."""
        ...

    def on_status(self, source: Source, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        """The device's status changed on its line (Running, Offline, Reconnecting);
        ``reason`` says why it is not Running (None when it is)."""
        return None

    def on_snapshot(self, source: Source, snapshot: dict[str, Any]) -> None:
        """The snapshot (``driver.snapshot()``) every ``snapshotInterval``."""
        return None


BatchCallback = Callable[[list["DeviceAddressItem"]], None]


class BatchCallbackListener:
    """The seed's ``addresses_updated_callback`` as a listener: the head of every
    driver's list.  ``get`` reads the callback at each delivery (the host may set or
    replace it while the device is polled)."""

    __slots__ = ("_get",)

    def __init__(self, get: Callable[[], BatchCallback | None]) -> None:
        self._get = get

    def on_changes(self, source: object, items: list[DeviceAddressItem]) -> None:
        callback = self._get()
        if callback is not None:
            callback(items)

    def on_status(self, source: object, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        return None

    def on_snapshot(self, source: object, snapshot: dict[str, Any]) -> None:
        return None

    def __repr__(self) -> str:
        return "addresses_updated_callback"


def listener_name(listener: object) -> str:
    """How log lines name a listener."""
    if isinstance(listener, BatchCallbackListener):
        return repr(listener)
    return f"listener {type(listener).__qualname__}"


class Subscribers(Generic[T]):
    """A copy-on-write list of listeners behind a fixed head listener.

    ``listeners`` (the subscribers, in subscription order) and ``with_head`` (the head,
    then the same) are tuples replaced whole under the lock, so a reader on another
    thread iterates a consistent snapshot without locking.  A listener is one object
    (compared by identity): subscribing it twice is an error, as is unsubscribing one
    that is not subscribed; removing one never drops another."""

    __slots__ = ("_lock", "head", "listeners", "with_head")

    def __init__(self, head: Listener[T]) -> None:
        self._lock = threading.Lock()
        self.head = head
        self.listeners: tuple[Listener[T], ...] = ()
        self.with_head: tuple[Listener[T], ...] = (head,)

    def add(self, listener: Listener[T]) -> None:
        """Append ``listener``; ValueError when it is already subscribed."""
        for method in ("on_changes", "on_status", "on_snapshot"):
            if not callable(getattr(listener, method, None)):
                raise ValueError(f"listener {listener!r}: has no method {method}() "
                                 "(edgemodbus.Listener: on_changes, on_status, on_snapshot)")
        with self._lock:
            if any(known is listener for known in self.listeners):
                raise ValueError(f"listener {listener!r} is already subscribed "
                                 "(each listener object is subscribed once)")
            self._set((*self.listeners, listener))

    def remove(self, listener: Listener[T]) -> None:
        """Remove ``listener``; ValueError when it is not subscribed."""
        with self._lock:
            kept = tuple(known for known in self.listeners if known is not listener)
            if len(kept) == len(self.listeners):
                raise ValueError(f"listener {listener!r} is not subscribed")
            self._set(kept)

    def _set(self, listeners: tuple[Listener[T], ...]) -> None:
        self.listeners = listeners
        self.with_head = (self.head, *listeners)
