"""What the console is given by the gateway (gateway/service.py's Gateway satisfies
it): the running devices and a way to ask for a reload.  The console never imports the
gateway (a higher layer, docs/architecture.md); it reads these attributes, from its own
thread, as snapshots (``tuple(host.devices.values())``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

from ..config import DeviceConfig
from ..driver import DriverModbusRtu


class HostDevice(Protocol):
    """A device file of the folder and the driver running it."""

    @property
    def path(self) -> Path: ...

    @property
    def code(self) -> str: ...

    @property
    def cfg(self) -> DeviceConfig: ...

    @property
    def driver(self) -> DriverModbusRtu: ...


class ConsoleHost(Protocol):
    """The gateway as the console sees it."""

    @property
    def gateway_id(self) -> str: ...

    @property
    def dir(self) -> Path: ...

    @property
    def gateway_file(self) -> Path: ...

    @property
    def devices(self) -> Mapping[Path, HostDevice]: ...

    def request_reload(self) -> None:
        """Re-read the folder soon, on the gateway's own thread (as SIGHUP does)."""
        ...


__all__ = ["ConsoleHost", "HostDevice"]
