"""edgemodbus: a Modbus master for edge gateways.

libmodbus does the wire I/O (RTU on serial lines, raw RTU frames over TCP, Modbus TCP),
a C codec turns register blocks into values, and :class:`DriverModbusRtu` polls,
writes and reports with per-slave fault isolation, to its callbacks and to the
:class:`Listener` objects subscribed to it.
"""

from __future__ import annotations

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
from .datatypes import Area, DataFormat, DataFormat64, DataType, DeviceDriverStatus, ItemStatus
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
