"""The service's status log (gateway/status_log.py): a device's change is logged once,
from its event; a device that reported nothing is not looked at (its status is not read)."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.gateway.status_log import StatusLog


class Driver:
    """A driver whose status may be read only when ``readable``."""

    def __init__(self, status: DeviceDriverStatus, readable: bool = True) -> None:
        self.status, self.readable = status, readable
        self.listeners: list[Any] = []

    @property
    def device_driver_status(self) -> DeviceDriverStatus:
        assert self.readable, "a device without an event was looked at"
        return self.status

    def subscribe(self, listener: Any) -> None:
        self.listeners.append(listener)

    def unsubscribe(self, listener: Any) -> None:
        self.listeners.remove(listener)


def test_a_change_is_logged_once_from_its_event(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="edgemodbus.service")
    log = StatusLog()
    busy = Driver(DeviceDriverStatus.CONNECTING)
    idle = Driver(DeviceDriverStatus.CONNECTING, readable=False)
    devices: dict[Path, Any] = {
        Path(name): SimpleNamespace(code=name, status="Connecting", standby=False, driver=drv)
        for name, drv in (("busy", busy), ("idle", idle))}
    log.watch(busy, Path("busy"))  # type: ignore[arg-type]
    log.watch(idle, Path("idle"))  # type: ignore[arg-type]
    log.log_changes(devices)  # nothing reported: nothing read (idle would raise)
    busy.status = DeviceDriverStatus.OFFLINE
    for listener in busy.listeners:
        listener.on_status(busy, busy.status, "no reply")
    log.log_changes(devices)
    log.log_changes(devices)  # once
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["busy: Connecting -> Offline"]
    assert caplog.records[0].levelno == logging.WARNING
    assert devices[Path("busy")].status == "Offline"
    log.unwatch(busy)  # type: ignore[arg-type]
    log.unwatch(busy)  # type: ignore[arg-type]  # twice: nothing
    assert busy.listeners == []
