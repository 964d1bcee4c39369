"""Wrapped report frames of edge MCUs (the edge gateway requirement's report protocol).

An MCU between the device and a transparent DTU polls locally and pushes changes to
the platform, wrapping each raw RTU frame so that the register address travels with it:

    FF AA | register address (2 bytes, big-endian) | RTU frame with its CRC | 0D

e.g. ``FFAA 0001 010302030578B7 0D`` reports holding register 1 = 773 of slave 1.  Writes
go down wrapped the same way and the device echoes them, wrapped, as confirmation.
This module parses such a byte stream incrementally (frames split over or packed into
TCP segments) and builds wrapped requests; bad frames are dropped, logged with their
hex and counted, and parsing resynchronises on the next header.  The simulator frames
with it; the master frames in C by the same rules (csrc/emb_stream.c).

Counting: each bad frame, and each run of noise between frames, is one drop.  After a
frame whose end is known (its length and 0D tail agree, the CRC does not) the bytes up to
that end belong to it; after one whose end is unknown, the bytes up to the next header
do.  Such bytes are discarded without being counted again.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass

from .limits import MAX_RTU_ADU
from .rtu import crc16
from .rtu import frame as rtu_frame

log = logging.getLogger("edgemodbus.wrapped")

HEADER = b"\xff\xaa"
TAIL = 0x0D
_PREFIX = 4  # header + register address


@dataclass(frozen=True, slots=True)
class Report:
    """One wrapped frame: the wrapper's register address and the RTU frame inside."""

    address: int
    slave: int
    function: int
    data: bytes  # the PDU after the function code, CRC stripped
    raw: bytes  # the whole wrapped frame, for logs

    @property
    def exception_code(self) -> int | None:
        return self.data[0] if self.function & 0x80 else None

    @property
    def registers(self) -> list[int]:
        """Registers of a read reply (FC03/04): byte count, then big-endian words."""
        n = self.data[0] // 2
        return list(struct.unpack_from(f">{n}H", self.data, 1))

    @property
    def bits(self) -> list[int]:
        """Bits of a read reply (FC01/02), first in the low bit of the first byte; the
        byte count carries whole bytes, so the caller knows how many are meaningful."""
        return [(byte >> i) & 1 for byte in self.data[1:] for i in range(8)]


def report_of(raw: bytes) -> Report:
    """The :class:`Report` of one whole wrapped frame whose header, length, tail and CRC
    were checked (by :class:`ReportParser`, or by the master's C framing,
    csrc/emb_stream.c)."""
    rtu = raw[_PREFIX:-1]
    return Report(struct.unpack_from(">H", raw, 2)[0], rtu[0], rtu[1], rtu[2:-2], raw)


def wrap(address: int, slave: int, pdu: bytes) -> bytes:
    """A wrapped request: header, register address, RTU frame (CRC added), tail."""
    if not 0 <= address <= 0xFFFF:
        raise ValueError(f"register address {address}: must be 0..65535")
    return HEADER + struct.pack(">H", address) + rtu_frame(slave, pdu) + bytes([TAIL])


def _rtu_length(buf: bytearray, start: int) -> int | None:
    """Length of the RTU frame at ``start`` from its function code (Application
    Protocol v1.1b3, section 6), None if more bytes are needed, 0 if it cannot be one."""
    if len(buf) < start + 2:
        return None
    function = buf[start + 1]
    if function & 0x80:
        return 5  # slave, function, exception code, CRC
    if function in (1, 2, 3, 4):
        if len(buf) < start + 3:
            return None
        count = buf[start + 2]
        if count == 0 or (function in (3, 4) and count % 2):
            return 0
        return 3 + count + 2
    if function in (5, 6, 15, 16):
        return 8  # slave, function, address, value or quantity, CRC
    if function == 22:
        return 10
    return 0


class ReportParser:
    """Incremental parser of a wrapped-report byte stream."""

    def __init__(self, heartbeat: bytes = b"") -> None:
        self._buf = bytearray()
        self.heartbeat = heartbeat
        self.frames = 0
        self.dropped = 0
        self.heartbeats = 0
        # bytes after the current position that belong to the last dropped frame (not
        # another drop): a count, or None for "up to the next header"
        self._absorb: int | None = 0

    def feed(self, data: bytes) -> list[Report]:
        """Add received bytes; return the complete, valid frames found so far."""
        buf = self._buf
        buf += data
        reports: list[Report] = []
        while buf:
            if self.heartbeat and buf.startswith(self.heartbeat):
                del buf[: len(self.heartbeat)]
                self.heartbeats += 1
                continue
            start = buf.find(HEADER)
            if start != 0:
                if start < 0:
                    # keep a trailing 0xFF (maybe the first half of a header) or a
                    # heartbeat's beginning; drop the rest as noise
                    keep = 1 if buf.endswith(HEADER[:1]) else 0
                    keep = max(keep, _partial(buf, self.heartbeat))
                    noise = len(buf) - keep
                    if noise:
                        self._noise(bytes(buf[:noise]))
                        del buf[:noise]
                    break
                self._noise(bytes(buf[:start]))
                del buf[:start]
            self._absorb = 0  # a header: a new frame begins
            length = _rtu_length(buf, _PREFIX)
            if length is None:
                break
            if length == 0 or length > MAX_RTU_ADU:
                self._bad(bytes(buf[:_PREFIX + 2]), "not a Modbus reply", None)
                continue
            end = _PREFIX + length + 1
            if len(buf) < end:
                break
            frame = bytes(buf[:end])
            rtu = frame[_PREFIX:-1]
            if frame[-1] != TAIL:
                self._bad(frame, "no 0D tail (length does not add up)", None)
                continue
            if crc16(rtu[:-2]) != int.from_bytes(rtu[-2:], "little"):
                self._bad(frame, "CRC error", end)
                continue
            del buf[:end]
            self.frames += 1
            reports.append(report_of(frame))
        return reports

    def _bad(self, raw: bytes, why: str, end: int | None) -> None:
        """Drop the frame at the start of the buffer: count it, then skip its header
        only (a real header may follow inside it); the rest of it, up to ``end`` if known,
        else up to the next header, is not counted again."""
        self._drop(raw, why)
        del self._buf[:2]
        self._absorb = None if end is None else end - 2

    def _noise(self, raw: bytes) -> None:
        """Discard bytes before a header: the rest of the last dropped frame, or noise
        (one drop per run, however it is split over segments)."""
        absorb = self._absorb
        if absorb is None:
            log.debug("wrapped report: %d more bytes of a dropped frame: %s", len(raw),
                      raw.hex(" ").upper())
            return
        if len(raw) <= absorb:
            self._absorb = absorb - len(raw)
            return
        self._drop(raw[absorb:], "no FF AA header")
        self._absorb = None  # the run of noise goes on up to the next header

    def _drop(self, raw: bytes, why: str) -> None:
        self.dropped += 1
        log.warning("wrapped report dropped (%s): %s", why, raw.hex(" ").upper())


def _partial(buf: bytearray, pattern: bytes) -> int:
    """How many trailing bytes of ``buf`` are a proper prefix of ``pattern``."""
    for n in range(min(len(pattern) - 1, len(buf)), 0, -1):
        if buf.endswith(pattern[:n]):
            return n
    return 0
