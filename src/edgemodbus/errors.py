"""Exception hierarchy of edgemodbus.

Every failure of a Modbus transaction is a :class:`ModbusError`; the subclasses say
whether the slave was silent, the link broke, the reply was malformed, or the slave
answered with an exception response (Modbus Application Protocol v1.1b3, section 7).
"""

from __future__ import annotations


class ModbusError(Exception):
    """Base of every edgemodbus transaction error; never raised bare."""


class ModbusTimeoutError(ModbusError, TimeoutError):
    """The slave did not answer within the response timeout (or a frame stopped short)."""


class IncompleteReplyError(ModbusTimeoutError):
    """A reply began but stopped short of a whole frame (the byte timeout ran out):
    something answered, but not in frames we could read (noise, another baud rate)."""


class ModbusConnectionError(ModbusError, ConnectionError):
    """The link is down: refused, reset, closed, serial I/O error, or not open."""


class LineBusyError(ModbusError):
    """The line has as many jobs waiting as it takes (the line's or one master's
    bound): nothing was queued; a gateway answers exception 06, server device busy."""


class TargetBackoffError(ModbusTimeoutError):
    """A recent request to this slave timed out, so requests to it fail at once for a
    backoff interval instead of costing the line a timeout each (a gateway answers 0B)."""


class ProtocolError(ModbusError):
    """A reply that is not a valid answer to the request: bad CRC, wrong slave id,
    wrong function, wrong length or byte count, or a write echo that does not match."""


class CrcError(ProtocolError):
    """The reply's CRC does not match its contents (a corrupted frame)."""


class ModbusExceptionResponse(ModbusError):
    """The slave answered with an exception response; ``code`` is the exception code."""

    code: int = 0
    label: str = "exception"

    def __init__(self, message: str = "", code: int | None = None) -> None:
        if code is not None:
            self.code = code
        super().__init__(message or f"exception {self.code:#04x} ({self.label})")


class IllegalFunction(ModbusExceptionResponse):
    code, label = 0x01, "illegal function"


class IllegalDataAddress(ModbusExceptionResponse):
    code, label = 0x02, "illegal data address"


class IllegalDataValue(ModbusExceptionResponse):
    code, label = 0x03, "illegal data value"


class SlaveDeviceFailure(ModbusExceptionResponse):
    code, label = 0x04, "slave device failure"


class Acknowledge(ModbusExceptionResponse):
    code, label = 0x05, "acknowledge"


class SlaveDeviceBusy(ModbusExceptionResponse):
    code, label = 0x06, "slave device busy"


class NegativeAcknowledge(ModbusExceptionResponse):
    code, label = 0x07, "negative acknowledge"


class MemoryParityError(ModbusExceptionResponse):
    code, label = 0x08, "memory parity error"


class GatewayPathUnavailable(ModbusExceptionResponse):
    code, label = 0x0A, "gateway path unavailable"


class GatewayTargetFailedToRespond(ModbusExceptionResponse):
    code, label = 0x0B, "gateway target device failed to respond"


EXCEPTION_CLASSES: dict[int, type[ModbusExceptionResponse]] = {
    cls.code: cls
    for cls in (
        IllegalFunction,
        IllegalDataAddress,
        IllegalDataValue,
        SlaveDeviceFailure,
        Acknowledge,
        SlaveDeviceBusy,
        NegativeAcknowledge,
        MemoryParityError,
        GatewayPathUnavailable,
        GatewayTargetFailedToRespond,
    )
}


def exception_for_code(code: int, context: str = "") -> ModbusExceptionResponse:
    """The typed exception for a Modbus exception code; undefined codes keep the base class."""
    cls = EXCEPTION_CLASSES.get(code)
    if cls is None:
        err = ModbusExceptionResponse(
            f"{context}: undefined exception code {code:#04x}" if context else "", code
        )
        err.label = "undefined exception code"
        return err
    suffix = f"exception {code:#04x} ({cls.label})"
    return cls(f"{context}: {suffix}" if context else suffix)
