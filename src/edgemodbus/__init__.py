"""edgemodbus: a Modbus master for edge gateways.

libmodbus does the wire I/O (RTU on serial lines, raw RTU frames over TCP, Modbus TCP),
a C codec turns register blocks into values, and :class:`DriverModbusRtu` polls,
writes and reports with per-slave fault isolation, to its callbacks and to the
:class:`Listener` objects subscribed to it.

The public names are imported on first use (module ``__getattr__``, PEP 562): ``import
edgemodbus`` costs no pydantic model, no driver and no cffi extension, so a command that
needs none of them (``edgemodbus --version``, ``descriptor``) starts as fast as Python
(docs/benchmarks.md, "Start-up of the command line").  ``from edgemodbus import
DriverModbusRtu`` and ``em.DriverModbusRtu`` work as before.
"""

from __future__ import annotations

import importlib

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (6 ms)
if TYPE_CHECKING:  # what the names are, for type checkers and IDEs
    from typing import Any

    from .config import (
        ConfigError,
        DeviceAddressItem,
        DeviceConfig,
        DeviceOrganizationParameter,
        DriverModbusRtuParameter,
        Parity,
        load_communication,
        load_device_config,
    )
    from .datatypes import (
        Area,
        DataFormat,
        DataFormat64,
        DataType,
        DeviceDriverStatus,
        ItemStatus,
    )
    from .descriptor import driver_descriptor
    from .driver import DriverModbusRtu
    from .errors import (
        ModbusConnectionError,
        ModbusError,
        ModbusExceptionResponse,
        ModbusTimeoutError,
        ProtocolError,
    )
    from .poll.listeners import Listener
    from .protocol.address import Address, parse_address

__version__ = "0.1.0"

#: Each public name and the module that defines it (imported on first use).
_HOMES: dict[str, str] = {
    "Address": ".protocol.address",
    "Area": ".datatypes",
    "ConfigError": ".config",
    "DataFormat": ".datatypes",
    "DataFormat64": ".datatypes",
    "DataType": ".datatypes",
    "DeviceAddressItem": ".config",
    "DeviceConfig": ".config",
    "DeviceDriverStatus": ".datatypes",
    "DeviceOrganizationParameter": ".config",
    "DriverModbusRtu": ".driver",
    "DriverModbusRtuParameter": ".config",
    "ItemStatus": ".datatypes",
    "Listener": ".poll.listeners",
    "ModbusConnectionError": ".errors",
    "ModbusError": ".errors",
    "ModbusExceptionResponse": ".errors",
    "ModbusTimeoutError": ".errors",
    "Parity": ".config",
    "ProtocolError": ".errors",
    "driver_descriptor": ".descriptor",
    "load_communication": ".config",
    "load_device_config": ".config",
    "parse_address": ".protocol.address",
}

__all__ = [
    "Address",
    "Area",
    "ConfigError",
    "DataFormat",
    "DataFormat64",
    "DataType",
    "DeviceAddressItem",
    "DeviceConfig",
    "DeviceDriverStatus",
    "DeviceOrganizationParameter",
    "DriverModbusRtu",
    "DriverModbusRtuParameter",
    "ItemStatus",
    "Listener",
    "ModbusConnectionError",
    "ModbusError",
    "ModbusExceptionResponse",
    "ModbusTimeoutError",
    "Parity",
    "ProtocolError",
    "__version__",
    "driver_descriptor",
    "load_communication",
    "load_device_config",
    "parse_address",
]


def __getattr__(name: str) -> Any:
    """A public name on first use: import its module, keep the name here (the next
    lookup is a plain attribute); anything else is an AttributeError as usual."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(home, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
