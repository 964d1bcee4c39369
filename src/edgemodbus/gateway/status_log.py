"""The gateway's log line per device status change, from the drivers' status events.

Each started device has a :class:`StatusWatch` subscribed (poll/listeners.py
``on_status``), which only notes the device's file; the service's main loop
(gateway/run.py) logs what :meth:`StatusLog.take` returns.  Before, the loop read every
device's status every ``statusCheckInterval``: with thousands of device files an idle
fleet instance paid for each one twice a second (docs/deploy.md "What the fleet costs")."""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..poll.listeners import Listener

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..datatypes import DeviceDriverStatus
    from ..driver import DriverModbusRtu


log = logging.getLogger("edgemodbus.service")  # as gateway/service.py logs


class Device(Protocol):
    """What the log reads of a device (gateway/service.py ServiceDevice)."""

    code: str
    status: str  # as last logged
    standby: bool

    @property
    def driver(self) -> DriverModbusRtu: ...


class StatusWatch(Listener["DriverModbusRtu"]):
    """One device's subscription: its status changes note its file in the log."""

    __slots__ = ("log", "path")

    def __init__(self, log: StatusLog, path: Path) -> None:
        self.log = log
        self.path = path

    def on_changes(self, source: DriverModbusRtu, items: list[DeviceAddressItem]) -> None:
        return None

    def on_status(self, source: DriverModbusRtu, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        self.log.changed(self.path)

    def on_snapshot(self, source: DriverModbusRtu, snapshot: dict[str, Any]) -> None:
        return None


class StatusLog:
    """The device files whose status changed since the main loop last looked."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._changed: dict[Path, None] = {}  # in the order of the events
        self._watches: dict[int, tuple[DriverModbusRtu, StatusWatch]] = {}

    def watch(self, driver: DriverModbusRtu, path: Path) -> None:
        """Subscribe to ``driver`` (the device of ``path``); once per driver."""
        watch = StatusWatch(self, path)
        driver.subscribe(watch)
        with self._lock:
            self._watches[id(driver)] = (driver, watch)

    def unwatch(self, driver: DriverModbusRtu) -> None:
        """Unsubscribe from ``driver``; nothing when it is not watched."""
        with self._lock:
            found = self._watches.pop(id(driver), None)
        if found is not None and found[0] is driver:
            driver.unsubscribe(found[1])

    def changed(self, path: Path) -> None:
        """Note that the device of ``path`` changed status (its line worker)."""
        with self._lock:
            self._changed[path] = None

    def take(self) -> list[Path]:
        """The files noted since the last call, in the order they were first noted."""
        with self._lock:
            changed, self._changed = self._changed, {}
        return list(changed)

    def log_changes(self, devices: Mapping[Path, Device]) -> None:
        """Log each change of the devices noted since the last call (of ``devices``:
        the running ones by file), once; ``status`` keeps what was logged."""
        for path in self.take():
            dev = devices.get(path)
            if dev is None or dev.standby:
                continue
            status = dev.driver.device_driver_status.value
            if status != dev.status:
                level = logging.WARNING if status in ("Offline", "Reconnecting") else logging.INFO
                log.log(level, "%s: %s -> %s", dev.code, dev.status, status)
                dev.status = status


__all__ = ["Device", "StatusLog", "StatusWatch"]
