"""edgemodbus: a Modbus master for edge gateways.

libmodbus does the wire I/O (RTU on serial lines, raw RTU frames over TCP, Modbus TCP),
a C codec turns register blocks into values, and :class:`DriverModbusRtu` polls,
writes and reports with per-slave fault isolation.
"""

from __future__ import annotations

from .datatypes import Area, DataFormat, DataType
from .errors import (
    ModbusConnectionError,
    ModbusError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)

__version__ = "0.1.0"

__all__ = [
    "Area",
    "DataFormat",
    "DataType",
    "ModbusConnectionError",
    "ModbusError",
    "ModbusExceptionResponse",
    "ModbusTimeoutError",
    "ProtocolError",
    "__version__",
]
