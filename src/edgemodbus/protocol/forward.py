"""Forwarded requests (gateway forward mode): which request PDUs may be forwarded onto a
line, whether a reply answers one, and which exception code a gateway answers for a
failure.

A PDU here is the function code and its data, without slave id, CRC or MBAP header
(Modbus Application Protocol v1.1b3, 4.1).  Only functions whose reply length the line
can frame (csrc/emb_io.c, emb_reply_length) are forwarded: 01-06, 0F, 10, 11, 16 and
17.
Pure bytes: no I/O, no state (the reply check is csrc/emb_check.c's, through _ffi).

The public contract a Modbus TCP server builds on:

* :func:`check_request` raises :class:`UnsupportedFunctionError` (answer exception 01,
  Illegal Function) or :class:`InvalidRequestError` (answer 03, Illegal Data Value);
  both are :class:`ForwardRequestError`, a ``ValueError`` with ``exception_code``;
* :func:`exception_code_for` gives the exception code to answer for any failure of a
  forwarded request (a refused request, a timeout, a bad reply, a line down).
"""

from __future__ import annotations

import struct

from .._ffi import check
from ..errors import (
    LineBusyError,
    ModbusConnectionError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)
from .limits import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_RW_READ_REGISTERS,
    MAX_RW_WRITE_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
)

#: The function codes forward mode sends (6.1-6.6, 6.11-6.13, 6.16, 6.17).
FORWARD_FUNCTIONS: frozenset[int] = frozenset({0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F,
                                               0x10, 0x11, 0x16, 0x17})
REPORT_SERVER_ID = 0x11  # 6.13: no data; the reply's byte count says its length

# Exception codes (Modbus Application Protocol v1.1b3, 7)
ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_VALUE = 0x03
SERVER_DEVICE_FAILURE = 0x04
SERVER_DEVICE_BUSY = 0x06
GATEWAY_PATH_UNAVAILABLE = 0x0A
GATEWAY_TARGET_FAILED = 0x0B

# quantity limits of the request (6.1-6.4, 6.11, 6.12, 6.17: protocol/limits.py)
_READ_LIMITS = {0x01: MAX_READ_BITS, 0x02: MAX_READ_BITS, 0x03: MAX_READ_REGISTERS,
                0x04: MAX_READ_REGISTERS}
# fixed request lengths, function code included
_FIXED_LENGTH = {0x01: 5, 0x02: 5, 0x03: 5, 0x04: 5, 0x05: 5, 0x06: 5, 0x11: 1, 0x16: 7}


class ForwardRequestError(ValueError):
    """A request PDU that is not forwarded; ``exception_code`` is the Modbus exception
    code a gateway answers with."""

    exception_code: int = ILLEGAL_DATA_VALUE


class UnsupportedFunctionError(ForwardRequestError):
    """The function code is not one forward mode sends (exception 01, Illegal Function)."""

    exception_code = ILLEGAL_FUNCTION


class InvalidRequestError(ForwardRequestError):
    """The request's length, byte count, quantity or value is not what its function
    allows (exception 03, Illegal Data Value)."""

    exception_code = ILLEGAL_DATA_VALUE


def check_request(pdu: bytes) -> None:
    """Raise a :class:`ForwardRequestError` unless ``pdu`` is a well-formed request of a
    function in :data:`FORWARD_FUNCTIONS` (Modbus Application Protocol v1.1b3, 6).
    Addresses are the slave's business (it answers exception 02)."""
    if not pdu:
        raise InvalidRequestError("empty request PDU: no function code")
    fc = pdu[0]
    if fc not in FORWARD_FUNCTIONS:
        raise UnsupportedFunctionError(
            f"function code {fc:#04x} is not forwarded; allowed: "
            + ", ".join(f"{f:#04x}" for f in sorted(FORWARD_FUNCTIONS))
        )
    n = len(pdu)
    name = f"FC{fc:#04x}"
    fixed = _FIXED_LENGTH.get(fc)
    if fixed is not None:
        if n != fixed:
            raise InvalidRequestError(f"{name} request of {n} bytes: must be {fixed}")
        if fc in _READ_LIMITS:
            qty = struct.unpack_from(">H", pdu, 3)[0]
            _check_quantity(name, "quantity", qty, _READ_LIMITS[fc])
        elif fc == 0x05:  # 6.5: ON is FF00, OFF is 0000, any other value is illegal
            value = struct.unpack_from(">H", pdu, 3)[0]
            if value not in (0x0000, 0xFF00):
                raise InvalidRequestError(
                    f"{name} coil value {value:#06x}: must be 0xff00 (on) or 0x0000 (off)")
        return
    if fc in (0x0F, 0x10):
        if n < 6:
            raise InvalidRequestError(f"{name} request of {n} bytes: at least 6 with its "
                                      "address, quantity and byte count")
        _addr, qty, count = struct.unpack_from(">HHB", pdu, 1)
        if fc == 0x0F:
            _check_quantity(name, "quantity of coils", qty, MAX_WRITE_BITS)
            want = (qty + 7) // 8
        else:
            _check_quantity(name, "quantity of registers", qty, MAX_WRITE_REGISTERS)
            want = 2 * qty
        _check_count(name, count, want, n - 6)
        return
    # 0x17: read address, read quantity, write address, write quantity, byte count
    if n < 10:
        raise InvalidRequestError(f"{name} request of {n} bytes: at least 10 with its "
                                  "addresses, quantities and byte count")
    _ra, read_qty, _wa, write_qty, count = struct.unpack_from(">HHHHB", pdu, 1)
    _check_quantity(name, "quantity to read", read_qty, MAX_RW_READ_REGISTERS)
    _check_quantity(name, "quantity to write", write_qty, MAX_RW_WRITE_REGISTERS)
    _check_count(name, count, 2 * write_qty, n - 10)


def _check_quantity(name: str, what: str, qty: int, limit: int) -> None:
    if not 1 <= qty <= limit:
        raise InvalidRequestError(f"{name} {what} {qty}: must be 1..{limit}")


def _check_count(name: str, count: int, want: int, data: int) -> None:
    if count != want:
        raise InvalidRequestError(f"{name} byte count {count}: the quantity needs {want}")
    if data != count:
        raise InvalidRequestError(f"{name} byte count {count}, but {data} data bytes follow")


def expected_reply_length(request: bytes) -> int:
    """The length of the normal reply PDU to a valid ``request`` (6.1-6.17); for Report
    Server ID (6.13), whose length the slave chooses, the shortest (byte count 1)."""
    fc = request[0]
    if fc == REPORT_SERVER_ID:
        return 3
    qty = int.from_bytes(request[3:5], "big")  # the (read) quantity of 6.1-6.4, 6.17
    if fc in (0x01, 0x02):
        return 2 + (qty + 7) // 8
    if fc in (0x03, 0x04, 0x17):
        return 2 + 2 * qty
    return 7 if fc == 0x16 else 5


def check_reply(request: bytes, reply: bytes) -> None:
    """Raise :class:`ProtocolError` unless ``reply`` is the normal reply to ``request``
    or an exception reply (``function | 0x80``, one code, chapter 7): the function, the
    byte count of a read, the echo of a write (6.5, 6.6, 6.11, 6.12, 6.16).  The check is
    the one every transaction makes in C (csrc/emb_check.c); this words what it found."""
    fc = request[0]
    what = f"forwarded FC{fc:#04x}"
    verdict = check.check_reply_pdu(request, reply)
    if verdict.ok:
        return
    if not reply:
        why = "empty reply"
    elif reply[0] == fc | 0x80:
        why = f"exception reply of {len(reply)} bytes, not 2"
    elif reply[0] != fc:
        why = f"reply has function code {reply[0]:#04x}"
    elif fc == REPORT_SERVER_ID:  # 6.13: byte count, server id, run indicator, more data
        why = (f"reply of {len(reply)} bytes with byte count "
               f"{reply[1] if len(reply) > 1 else 'none'}")
    elif len(reply) != expected_reply_length(request):
        why = f"reply of {len(reply)} bytes, expected {expected_reply_length(request)}"
    elif verdict.error == check.E_COUNT:
        why = f"byte count {reply[1]}, expected {expected_reply_length(request) - 2}"
    else:
        echo = request[1:expected_reply_length(request)]
        why = f"echo {reply[1:].hex(' ')} does not match the request {echo.hex(' ')}"
    raise ProtocolError(f"{what}: {why}")


def read_span(request: bytes) -> tuple[int, int, int] | None:
    """``(function, address, quantity)`` of a valid read request (01-04, 6.1-6.4), or
    None for any other function: what read coalescing may answer from a polled block."""
    if request[0] not in _READ_LIMITS:
        return None
    address, qty = struct.unpack_from(">HH", request, 1)
    return request[0], address, qty


def read_reply(function: int, values: list[int]) -> bytes:
    """The normal reply PDU of read function ``function`` (01-04) carrying ``values``:
    bits packed first bit in the low bit of the first byte (6.1, 6.2), registers
    big-endian (6.3, 6.4), after the byte count."""
    if function in (0x01, 0x02):
        packed = bytearray((len(values) + 7) // 8)
        for i, bit in enumerate(values):
            if bit:
                packed[i // 8] |= 1 << (i % 8)
        data = bytes(packed)
    else:
        data = struct.pack(f">{len(values)}H", *values)
    return bytes((function, len(data))) + data


def exception_code_for(exc: BaseException) -> int:
    """The Modbus exception code a gateway answers for a forwarded request that failed
    with ``exc`` (Modbus Application Protocol v1.1b3, 7):

    * :class:`ForwardRequestError`: its ``exception_code`` (01 unsupported function, 03
      bad length, quantity, byte count or value);
    * :class:`~edgemodbus.errors.ModbusTimeoutError` (no answer in time) and
      :class:`~edgemodbus.errors.ProtocolError` (a CRC-bad or malformed answer): 0B,
      gateway target device failed to respond;
    * :class:`~edgemodbus.errors.ModbusConnectionError` (the line is down, not running,
      or the device is stopped): 0A, gateway path unavailable;
    * :class:`~edgemodbus.errors.LineBusyError` (too many jobs waiting on the line): 06,
      server device busy;
    * :class:`~edgemodbus.errors.ModbusExceptionResponse` (not raised by forward, which
      passes exception replies through as bytes): its code;
    * anything else: 04, server device failure.
    """
    if isinstance(exc, ForwardRequestError):
        return exc.exception_code
    if isinstance(exc, ModbusTimeoutError | ProtocolError):
        return GATEWAY_TARGET_FAILED
    if isinstance(exc, ModbusConnectionError):
        return GATEWAY_PATH_UNAVAILABLE
    if isinstance(exc, LineBusyError):
        return SERVER_DEVICE_BUSY
    if isinstance(exc, ModbusExceptionResponse):
        return exc.code
    return SERVER_DEVICE_FAILURE
