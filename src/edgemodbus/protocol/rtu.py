"""Modbus RTU frames as bytes: CRC-16/MODBUS, building and checking frames, function
codes, the length of a request or reply from its header, and cutting requests out of a
byte stream.

An RTU frame (Modbus over Serial Line v1.02, 2.5.1)::

    +-------+----------+---------------------+--------+--------+
    | slave | function | data                | CRC lo | CRC hi |
    +-------+----------+---------------------+--------+--------+
      1 byte   1 byte    0..252 bytes          1 byte   1 byte
            |<------------ PDU ------------->|
    |<------------------ at most 256 bytes ------------------->|

The slave address is 0 for a broadcast (a write nobody answers), 1..247 for one slave,
248..255 reserved (Serial Line 2.2).  A reply carries the address of the slave that
answers and the request's function code, or that code + 0x80 and an exception code.

The CRC is CRC-16/MODBUS: polynomial 0xA001 (reflected 0x8005), initial value 0xFFFF,
no final XOR, sent low byte first (Serial Line 2.5.1.2, generated as in 6.2.2).  A frame
has no length field: on a serial line it ends with a silence of 3.5 character times,
t3.5, fixed at 1.75 ms above 19200 baud (Serial Line 2.5.1.1); over TCP, where silences
do not survive, the length follows from the function code and, for some, a byte count
(Application Protocol v1.1b3, section 6), which :func:`request_length` and
:func:`reply_length` compute.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from .limits import MAX_RTU_ADU, MAX_SLAVE_ID

__all__ = [
    "MASK_WRITE_REGISTER",
    "MAX_FRAME",
    "MAX_SLAVE_ID",
    "NEED_MORE",
    "READ_COILS",
    "READ_DISCRETE_INPUTS",
    "READ_FUNCTIONS",
    "READ_HOLDING_REGISTERS",
    "READ_INPUT_REGISTERS",
    "UNKNOWN",
    "WRITE_FUNCTIONS",
    "WRITE_MULTIPLE_COILS",
    "WRITE_MULTIPLE_REGISTERS",
    "WRITE_SINGLE_COIL",
    "WRITE_SINGLE_REGISTER",
    "crc16",
    "crc_ok",
    "find_known_frame",
    "frame",
    "pack_bits",
    "parse_slave_ids",
    "reply_length",
    "request_length",
    "split_frames",
]

#: Longest RTU frame, slave address and CRC included (Serial Line 2.5.1).  MAX_SLAVE_ID,
#: the highest unicast slave address, is protocol/limits.py's, exported here too.
MAX_FRAME = MAX_RTU_ADU

# Function codes (Application Protocol v1.1b3, 6.1-6.16).
READ_COILS = 0x01
READ_DISCRETE_INPUTS = 0x02
READ_HOLDING_REGISTERS = 0x03
READ_INPUT_REGISTERS = 0x04
WRITE_SINGLE_COIL = 0x05
WRITE_SINGLE_REGISTER = 0x06
WRITE_MULTIPLE_COILS = 0x0F
WRITE_MULTIPLE_REGISTERS = 0x10
MASK_WRITE_REGISTER = 0x16
READ_FUNCTIONS = frozenset(
    {READ_COILS, READ_DISCRETE_INPUTS, READ_HOLDING_REGISTERS, READ_INPUT_REGISTERS}
)
WRITE_FUNCTIONS = frozenset({
    WRITE_SINGLE_COIL,
    WRITE_SINGLE_REGISTER,
    WRITE_MULTIPLE_COILS,
    WRITE_MULTIPLE_REGISTERS,
    MASK_WRITE_REGISTER,
})

#: :func:`request_length` / :func:`reply_length`: the header is not complete yet.
NEED_MORE = -1
#: :func:`request_length` / :func:`reply_length`: a function code of unknown length.
UNKNOWN = -2


# --- CRC-16/MODBUS (Serial Line 2.5.1.2 and 6.2.2) ----------------------------------------


def _make_crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return table


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS of ``data`` as an integer; on the wire it goes low byte first."""
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def frame(slave: int, pdu: bytes | bytearray) -> bytes:
    """The RTU frame (ADU) of ``pdu`` for ``slave``: address + PDU + CRC (low byte first)."""
    if not 0 <= slave <= 0xFF:
        raise ValueError(f"slave address {slave}: must be 0..255 (one byte)")
    body = bytes([slave]) + pdu
    return body + struct.pack("<H", crc16(body))


def crc_ok(frame: bytes | bytearray | memoryview) -> bool:
    """Whether ``frame`` (address, PDU, CRC) is at least 4 bytes with a matching CRC."""
    return len(frame) >= 4 and crc16(frame[:-2]) == frame[-2] | (frame[-1] << 8)


def pack_bits(bits: Sequence[int | bool]) -> bytes:
    """Bits as the data of FC01/02 replies and FC15 requests: the first in the low bit of
    the first byte, the last byte zero-padded (Application Protocol v1.1b3, 6.1, 6.11)."""
    packed = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            packed[i // 8] |= 1 << (i % 8)
    return bytes(packed)


# --- frame lengths (Application Protocol v1.1b3, section 6) ------------------------------


def request_length(buf: bytes | bytearray, i: int = 0) -> int:
    """Length of the request frame starting at ``buf[i]``, computed from its PDU, or
    NEED_MORE (header incomplete) or UNKNOWN (function code of unknown length)."""
    avail = len(buf) - i
    if avail < 2:
        return NEED_MORE
    fc = buf[i + 1]
    if fc in (1, 2, 3, 4, 5, 6):
        return 8  # addr fc a_hi a_lo q_hi q_lo crc crc
    if fc in (WRITE_MULTIPLE_COILS, WRITE_MULTIPLE_REGISTERS):
        if avail < 7:
            return NEED_MORE
        return 9 + buf[i + 6]  # addr fc addr(2) qty(2) byte_count data crc(2)
    if fc == MASK_WRITE_REGISTER:
        return 10  # addr fc addr(2) and(2) or(2) crc(2)
    return UNKNOWN


def reply_length(buf: bytes | bytearray, i: int = 0) -> int:
    """Length of the reply frame starting at ``buf[i]`` as its header claims it, or
    NEED_MORE (header incomplete) or UNKNOWN (function code of unknown length).  The
    byte count of a read reply is taken as it is: whether it fits the request is the
    caller's check."""
    avail = len(buf) - i
    if avail < 2:
        return NEED_MORE
    fc = buf[i + 1]
    if fc & 0x80:
        return 5  # addr fc|0x80 exception_code crc(2)
    if fc in READ_FUNCTIONS:
        if avail < 3:
            return NEED_MORE
        return 5 + buf[i + 2]  # addr fc byte_count data crc(2)
    if fc in (WRITE_SINGLE_COIL, WRITE_SINGLE_REGISTER, WRITE_MULTIPLE_COILS,
              WRITE_MULTIPLE_REGISTERS):
        return 8  # addr fc addr(2) value_or_qty(2) crc(2)
    if fc == MASK_WRITE_REGISTER:
        return 10  # the request echoed
    return UNKNOWN


# --- cutting requests out of a byte stream ----------------------------------------------


def split_frames(buf: bytes | bytearray, idle: bool) -> tuple[list[bytes], int, int]:
    """Cut request frames with a valid CRC out of ``buf``.

    Returns (frames, bytes consumed, bytes discarded as garbage). Without ``idle`` only
    frames whose length the PDU fixes are cut and an incomplete tail is kept; with
    ``idle`` (the line has been silent for t3.5, Serial Line 2.5.1.1) everything left is
    resolved: a frame of unknown function code is the whole remainder if its CRC holds,
    anything else is discarded one byte at a time until a valid frame lines up.
    """
    frames: list[bytes] = []
    i = 0
    discarded = 0
    n = len(buf)
    while i < n:
        if buf[i] > MAX_SLAVE_ID:  # 248..255 are reserved addresses: garbage
            i += 1
            discarded += 1
            continue
        need = request_length(buf, i)
        if need in (NEED_MORE, UNKNOWN):
            if idle:
                rest = bytes(buf[i:])
                if need == UNKNOWN and crc_ok(rest):
                    frames.append(rest)
                    i = n
                else:
                    i += 1
                    discarded += 1
                continue
            if need == UNKNOWN:
                # Perhaps garbage before a frame of known length: look ahead for one.
                j = find_known_frame(buf, i + 1)
                if j >= 0:
                    discarded += j - i
                    i = j
                    continue
            break
        if n - i < need:
            if idle:
                i += 1
                discarded += 1
                continue
            break
        candidate = bytes(buf[i : i + need])
        if crc_ok(candidate):
            frames.append(candidate)
            i += need
        else:
            i += 1
            discarded += 1
    return frames, i, discarded


def find_known_frame(buf: bytes | bytearray, start: int) -> int:
    """Index of the first request frame at or after ``start`` whose length its PDU fixes,
    complete in ``buf`` and with a valid CRC; -1 if there is none."""
    for j in range(start, len(buf)):
        if buf[j] > MAX_SLAVE_ID:
            continue
        need = request_length(buf, j)
        if need > 0 and len(buf) - j >= need and crc_ok(buf[j : j + need]):
            return j
    return -1


def parse_slave_ids(text: str, low: int = 1, high: int = MAX_SLAVE_ID) -> list[int]:
    """Slave ids as people type them on a command line: ``"1-10,17"`` -> [1..10, 17], in
    order, each once.  Raises ValueError naming the bad part and what is allowed (ids
    ``low..high``: 1..247 on an RTU line, Modbus Serial Line 2.2; 0..255 as a Modbus TCP
    unit id)."""
    allowed = f"ids {low}..{high} and ranges, separated by commas, e.g. 1-10,17"
    ids: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        which = f"{text!r}" if part == text.strip() else f"{text!r}: {part!r}"
        first, dash, last = part.partition("-")
        try:
            a = int(first)
            b = int(last) if dash else a
        except ValueError:
            raise ValueError(f"{which} is not a number or range (allowed: {allowed})") from None
        if not (low <= a <= high and low <= b <= high) or a > b:
            raise ValueError(f"{which} is outside {low}..{high} or reversed "
                             f"(allowed: {allowed})")
        ids.extend(range(a, b + 1))
    if not ids:
        raise ValueError(f"{text!r}: no slave ids (allowed: {allowed})")
    return list(dict.fromkeys(ids))
