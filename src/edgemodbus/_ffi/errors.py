"""errno -> exception: what libmodbus (or our csrc helpers) left in errno after a failed
call, as a typed error of :mod:`edgemodbus.errors`.  ``modbus_strerror`` is never called:
it is not thread-safe in libmodbus 3.1.6 and our workers run concurrently."""

from __future__ import annotations

import errno as _errno
import os

from ..errors import (
    CrcError,
    IncompleteReplyError,
    ModbusConnectionError,
    ModbusError,
    ModbusTimeoutError,
    ProtocolError,
    exception_for_code,
)
from .native import lib

_ENOBASE: int = lib.MODBUS_ENOBASE
_EMBXGTAR = _ENOBASE + 11
_PROTOCOL_ERRNOS = {
    _EMBXGTAR + 2: "bad data (a byte count too large for a frame, or a wrong length)",
    _EMBXGTAR + 3: "exception response does not match the request",
    _EMBXGTAR + 4: "unknown exception code",
    _EMBXGTAR + 5: "too many data",
    _EMBXGTAR + 6: "response from the wrong slave id",
}
_CONNECTION_ERRNOS = {
    _errno.ECONNRESET,
    _errno.ECONNREFUSED,
    _errno.ECONNABORTED,
    _errno.EPIPE,
    _errno.EIO,
    _errno.EBADF,
    _errno.ENOTCONN,
    _errno.ENETUNREACH,
    _errno.EHOSTUNREACH,
    _errno.ENXIO,
    _errno.ENODEV,
}


# errnos of our own reply checks (csrc/emb_check.c, csrc/emb_io.c): what each says about
# the reply
_EMB_EXCEPTION: int = lib.EMB_EEXCEPTION
_EMB_PARTIAL: int = lib.EMB_EPARTIAL
_EMB_PROTOCOL_ERRNOS = {
    lib.EMB_EECHO: "the bytes read back as the echo of the request (option 'echo') "
    "differ from it; does this line echo?",
    lib.EMB_EECHOSEEN: "the reply starts with our own request: the line echoes requests "
    "(an RS-485 adapter without echo suppression); set the 'echo' option",
    lib.EMB_ESLAVE: "response from the wrong slave id",
    lib.EMB_EFUNCTION: "function code of the reply is not the request's",
    lib.EMB_EOTHEREXC: "exception response for another function code",
    lib.EMB_ECOUNT: "byte count does not match the request",
    lib.EMB_ETID: "only replies with another MBAP transaction id came (skipped as stale)",
    lib.EMB_EPROTOID: "MBAP protocol id is not 0",
    lib.EMB_EMBAPLEN: "MBAP length does not match the frame",
    lib.EMB_EWECHO: "the reply does not echo the request",
    lib.EMB_ELENGTH: "reply length does not match the request",
}


def error_from_errno(err: int, what: str) -> ModbusError:
    """Map an errno left by libmodbus (or by our csrc helpers) to a typed error."""
    if err == _errno.ETIMEDOUT:
        return ModbusTimeoutError(f"{what}: no response (timeout)")
    if err == _EMB_PARTIAL:
        return IncompleteReplyError(f"{what}: incomplete reply (byte timeout)")
    if _EMB_EXCEPTION <= err <= _EMB_EXCEPTION + 255:
        return exception_for_code(err - _EMB_EXCEPTION, what)
    if err in _EMB_PROTOCOL_ERRNOS:
        return ProtocolError(f"{what}: {_EMB_PROTOCOL_ERRNOS[err]}")
    if _ENOBASE < err <= _EMBXGTAR:
        return exception_for_code(err - _ENOBASE, what)
    if err == _EMBXGTAR + 1:
        return CrcError(f"{what}: CRC error")
    if err in _PROTOCOL_ERRNOS:
        return ProtocolError(f"{what}: {_PROTOCOL_ERRNOS[err]}")
    if err in _CONNECTION_ERRNOS:
        return ModbusConnectionError(f"{what}: link error: {os.strerror(err)}")
    if err == 0:
        return ModbusConnectionError(f"{what}: failed without an error code")
    return ModbusConnectionError(f"{what}: {os.strerror(err)} (errno {err})")
