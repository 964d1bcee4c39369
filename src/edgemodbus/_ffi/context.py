"""One libmodbus context and the transactions of csrc/emb_io.c on it (DTU streams:
csrc/emb_stream.c); discarding input."""

from __future__ import annotations

import errno as _errno
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from ..errors import ModbusConnectionError, ModbusError, ProtocolError
from .block import Block
from .errors import error_from_errno
from .native import (
    MAX_ADU_LENGTH,
    MAX_HEARTBEAT,
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    ffi,
    lib,
)


@dataclass(frozen=True, slots=True)
class StreamCounters:
    """What a stream link counted since the last :meth:`Context.take_counters`."""

    heartbeats: int = 0
    dropped: int = 0  # wrapped frames dropped (bad header, length, tail, CRC, noise)
    lost: int = 0  # reports the full ring could not take
    last_drop: bytes = b""  # the first bytes of the last frame dropped, for the log


class TracedFrame(NamedTuple):
    """A frame of the trace: sent (``tx``) or received, when (``time.monotonic()``
    seconds, the clock of csrc/emb_util.c), its bytes on the wire (for a wrapped link, the
    RTU frame inside)."""

    tx: bool
    at: float
    frame: bytes


class Context:
    """One libmodbus context (``modbus_t``), used by exactly one thread.

    ``Context.rtu`` opens a serial port itself; ``Context.on_socket`` drives a socket
    that the caller connected and keeps owning (RTU framing without MBAP, or Modbus
    TCP): libmodbus never closes it, so the socket's lifetime stays explicit.
    """

    def __init__(self, ptr: Any, label: str, owns_fd: bool) -> None:
        if ptr == ffi.NULL:
            raise ModbusConnectionError(
                f"{label}: libmodbus could not create a context ({os.strerror(ffi.errno)})"
            )
        self._ptr = ptr
        self.label = label
        self._owns_fd = owns_fd
        self.registers = Block(ffi.new("uint16_t[]", MAX_READ_REGISTERS), bits=False)
        self.bits = Block(ffi.new("uint8_t[]", MAX_READ_BITS), bits=True)
        self._rsp = ffi.new("uint8_t[]", MAX_ADU_LENGTH)
        self._req = ffi.new("uint8_t[]", MAX_ADU_LENGTH)
        self._link = ffi.new("emb_link *")  # per-line state of csrc/emb_io.c
        self._report: Any = None  # a taken report: made at the first (wrapped links only)
        self._stream_buf: Any = None  # a DTU stream's buffers, which _link.sb points at
        self._ring: Any = None  # a wrapped link's report ring, which _link.ring points at
        self._header = 1  # bytes before the PDU in a reply: slave id, or the MBAP header
        self._trace: Any = None  # the frame trace ring, which _link.trace points at when on
        # a taken frame, made with the ring (a link per DTU: docs/scale.md "Memory per DTU")
        self._trace_out: Any = None
        self._trace_dir: Any = None
        self._trace_ns: Any = None

    # -- construction ----------------------------------------------------------------
    @classmethod
    def rtu(cls, port: str, baud: int, parity: str, data_bits: int, stop_bits: int) -> Context:
        ptr = lib.modbus_new_rtu(port.encode(), baud, parity.encode(), data_bits, stop_bits)
        return cls(ptr, port, owns_fd=True)

    @classmethod
    def on_socket(cls, fd: int, label: str, mbap: bool) -> Context:
        """A context on a connected socket: MBAP framing if ``mbap``, else raw RTU frames.
        Any fd number will do: csrc/emb_io.c waits with poll(), never libmodbus's select()."""
        if mbap:
            ptr = lib.modbus_new_tcp(b"127.0.0.1", 502)  # address unused: we own the socket
        else:
            ptr = lib.modbus_new_rtu(b"/dev/null", 9600, b"N", 8, 1)  # settings unused
        ctx = cls(ptr, label, owns_fd=False)
        lib.modbus_set_socket(ctx._ptr, fd)
        if mbap:
            ctx._link.mbap = 1
            ctx._header = 7
        return ctx

    def set_echo(self, on: bool) -> None:
        """The line echoes every request (a 2-wire RS-485 adapter without echo
        suppression): read the request's own bytes back before each reply.  RTU only."""
        if on and self._link.mbap:
            raise ValueError(f"{self.label}: the echo option applies to RTU framing only")
        self._link.echo = 1 if on else 0

    def set_stream(self, heartbeat: bytes, wrapped: bool) -> None:
        """A DTU stream (RTU over a socket): skip and count ``heartbeat`` wherever a
        frame could begin; ``wrapped``: edge-MCU frames (requests go out wrapped, frames
        other than the reply are queued as reports: :meth:`take_reports`)."""
        if self._link.mbap:
            raise ValueError(f"{self.label}: heartbeats and wrapped frames are RTU only")
        if len(heartbeat) > MAX_HEARTBEAT:
            raise ValueError(f"{self.label}: a heartbeat of {len(heartbeat)} bytes; at most "
                             f"{MAX_HEARTBEAT}")
        if heartbeat or wrapped:  # the 512 B receive buffer: stream links only
            self.ensure_stream_buffers()
        if wrapped and self._ring is None:  # the 4 KB report ring: wrapped links only
            self._ring = ffi.new("uint8_t[]", int(lib.EMB_RING_SIZE))
            self._link.ring = self._ring
        ffi.memmove(self._link.hb, heartbeat, len(heartbeat))
        self._link.hb_len = len(heartbeat)
        self._link.wrapped = 1 if wrapped else 0

    @property
    def echo(self) -> bool:
        return bool(self._link.echo)

    def ensure_stream_buffers(self) -> None:
        """Give the link its stream buffers: the loop engine (_ffi/loop.py) frames every
        DTU stream in them, with heartbeats or without."""
        if self._stream_buf is None:
            self._stream_buf = ffi.new("emb_stream_buf *")
        self._link.sb = self._stream_buf

    @property
    def is_stream(self) -> bool:
        return bool(self._link.wrapped or self._link.hb_len)

    @property
    def mbap(self) -> bool:
        """Modbus TCP framing (an MBAP header with our transaction ids)."""
        return bool(self._link.mbap)

    @property
    def wrapped(self) -> bool:
        return bool(self._link.wrapped)

    def set_char_time(self, seconds: float) -> None:
        """A serial line's time per character on the wire: the reader sleeps while the
        rest of a frame is on its way instead of waking for every byte (0: a socket)."""
        self._link.char_ns = max(0, round(seconds * 1e9))

    def take_discarded(self) -> int:
        """Bytes thrown away since the last call (stale input, echoes, superseded
        frames), counted by the C transaction helpers."""
        n = int(self._link.discarded)
        if n:
            self._link.discarded = 0
        return n

    @property
    def syscalls(self) -> int:
        """System calls the plain RTU and Modbus TCP transactions made on this context
        so far (csrc/emb_rtu.c counts them: stale input dropped, request sent, waits,
        reads, the pending check); what one read costs the kernel, for tests and
        bench/syscalls.py."""
        return int(self._link.syscalls)

    def take_counters(self) -> StreamCounters | None:
        """Heartbeats, dropped frames and lost reports counted since the last call (None:
        nothing)."""
        lk = self._link
        if not (lk.heartbeats or lk.dropped or lk.reports_lost):
            return None
        counts = StreamCounters(int(lk.heartbeats), int(lk.dropped), int(lk.reports_lost),
                                bytes(ffi.buffer(lk.last_drop, lk.last_drop_len)))
        lk.heartbeats = lk.dropped = lk.reports_lost = 0
        return counts

    @property
    def reports_waiting(self) -> int:
        """Wrapped reports queued (csrc/emb_stream.c's ring)."""
        return int(self._link.n_reports)

    @property
    def reports_before(self) -> int:
        """How many of the reports waiting came before the reply of the last transaction
        (they are older than it: apply them first)."""
        return int(self._link.n_before)

    def take_reports(self, limit: int | None = None) -> list[bytes]:
        """The oldest reports (whole wrapped frames, checked), at most ``limit``."""
        out: list[bytes] = []
        n = self.reports_waiting if limit is None else min(limit, self.reports_waiting)
        if n and self._report is None:
            self._report = ffi.new("uint8_t[]", lib.EMB_REPORT_MAX)
        for _ in range(n):
            size = lib.emb_report_take(self._link, self._report)
            if not size:
                break
            out.append(bytes(ffi.buffer(self._report, size)))
        return out

    def pump(self) -> int:
        """Take in what is readable now without waiting (reports queued, heartbeats
        counted, stale bytes dropped); returns the reports waiting.  Raises
        :class:`ModbusConnectionError` when the link failed or the peer closed it."""
        n = lib.emb_pump(self._ptr, self._link)
        if n == -1:
            raise error_from_errno(ffi.errno, f"{self.label}: reading")
        return int(n)

    def feed(self, data: bytes) -> int:
        """Bytes that came before the link was made (after a DTU's registration), taken
        as if received now; returns the reports waiting."""
        n = lib.emb_feed(self._link, data, len(data))
        if n == -1:
            raise error_from_errno(ffi.errno, f"{self.label}: taking initial bytes")
        return int(n)

    def discard(self, total_s: float, quiet_s: float, limit_s: float) -> int:
        """:func:`discard_input` on this context's fd; on a stream link what comes is
        framed (a late wrapped frame is a report, heartbeats are counted).  Returns the
        bytes dropped."""
        n = lib.emb_link_discard(self._ptr, self._link, round(total_s * 1000),
                                 max(1, round(quiet_s * 1000)), round(limit_s * 1000))
        if n == -1:
            raise error_from_errno(ffi.errno, f"{self.label}: discarding input")
        return int(n)

    # -- the frame trace (csrc/emb_link.h emb_trace) -----------------------------------
    def set_trace(self, on: bool) -> None:
        """Trace every frame sent and received into the link's ring (csrc/emb_io.c
        writes it, in the line engine too); :meth:`take_trace` empties it."""
        if on and self._trace is None:
            self._trace = ffi.new("emb_trace *")
            self._trace_out = ffi.new("uint8_t[]", MAX_ADU_LENGTH)
            self._trace_dir = ffi.new("int *")
            self._trace_ns = ffi.new("int64_t *")
        self._link.trace = self._trace if on else ffi.NULL

    @property
    def traced(self) -> int:
        """Frames waiting in the trace ring (0 when the trace is off)."""
        return int(self._trace.n) if self._link.trace != ffi.NULL else 0

    def take_trace(self) -> tuple[list[TracedFrame], int]:
        """The frames traced since the last call, oldest first, and how many the full
        ring lost meanwhile."""
        t = self._trace
        if t is None:
            return [], 0
        frames: list[TracedFrame] = []
        direction, at = self._trace_dir, self._trace_ns
        for _ in range(int(t.n)):
            size = lib.emb_trace_take(t, self._trace_out, direction, at)
            if not size:
                break
            frames.append(TracedFrame(direction[0] == lib.EMB_TRACE_TX, int(at[0]) / 1e9,
                                      bytes(ffi.buffer(self._trace_out, size))))
        lost = int(t.lost)
        t.lost = 0
        return frames, lost

    def last_reply(self) -> bytes:
        """The reply ADU of the last transaction (for frame traces and error details);
        empty when none was received whole."""
        return bytes(ffi.buffer(self._rsp, self._link.rsp_len))

    def connect(self, rs485: str = "none", rts_delay_us: int | None = None) -> None:
        """Open the serial port of an ``rtu`` context and set its RS-485 mode."""
        if lib.modbus_connect(self._ptr) == -1:
            err = ffi.errno
            if err == _errno.ENOENT:
                msg = "does not exist (check the device path; is the adapter plugged in?)"
            elif err == _errno.EACCES:
                msg = (
                    "permission denied: add the user to the 'dialout' group "
                    "(usermod -aG dialout USER, then log in again) or run with access to it"
                )
            else:
                msg = os.strerror(err)
            raise ModbusConnectionError(f"serial port {self.label}: {msg}")
        if rs485 == "kernel" and lib.modbus_rtu_set_serial_mode(self._ptr, 1) == -1:
            err = ffi.errno
            lib.modbus_close(self._ptr)
            raise ModbusConnectionError(
                f"serial port {self.label}: the driver refused RS-485 mode "
                f"(TIOCSRS485: {os.strerror(err)}); use rs485 'none' or 'rts-up'/'rts-down'"
            )
        if rs485 in ("rts-up", "rts-down"):
            mode = lib.MODBUS_RTU_RTS_UP if rs485 == "rts-up" else lib.MODBUS_RTU_RTS_DOWN
            lib.modbus_rtu_set_rts(self._ptr, mode)
            if rts_delay_us is not None:
                lib.modbus_rtu_set_rts_delay(self._ptr, rts_delay_us)

    @property
    def fd(self) -> int:
        return int(lib.modbus_get_socket(self._ptr))

    def set_timeouts(self, response_s: float, byte_s: float) -> None:
        """Response timeout (first byte) and byte timeout (between bytes of one frame)."""
        for setter, seconds in (
            (lib.modbus_set_response_timeout, response_s),
            (lib.modbus_set_byte_timeout, byte_s),
        ):
            usec = max(0, round(seconds * 1_000_000))
            if setter(self._ptr, usec // 1_000_000, usec % 1_000_000) == -1:
                raise ValueError(f"{self.label}: invalid timeout {seconds!r} s")

    def close(self) -> None:
        """Free the context; closes the fd only if libmodbus opened it (serial)."""
        if self._ptr is None:
            return
        if self._owns_fd:
            lib.modbus_close(self._ptr)
        else:
            lib.modbus_set_socket(self._ptr, -1)
        lib.modbus_free(self._ptr)
        self._ptr = None

    # -- transactions ----------------------------------------------------------------
    def read(self, slave: int, function: int, address: int, count: int) -> Block:
        """FC01-04 into this context's buffer; returns the (reused) :class:`Block`."""
        block = self.bits if function in (1, 2) else self.registers
        rc = lib.emb_read(self._ptr, self._link, slave, function, address, count, block._ptr,
                          self._rsp)
        if rc == -1:
            raise self.read_error(ffi.errno, slave, function, address, count)
        block.count = rc
        return block

    def read_libmodbus(self, slave: int, address: int, count: int) -> Block:
        """FC03 through libmodbus's own send and receive path (``modbus_read_registers``),
        not ours.  The benchmark baseline only (bench/test_bench_serial.py, the floor of
        bench/test_bench_driver.py, bench/syscalls.py): on a serial line libmodbus wakes
        once per byte of the reply, on a socket it makes a select() and a read() per
        phase of the reply, and it checks less than :meth:`read` does (see
        csrc/emb_io.c); the driver never calls this."""
        block = self.registers
        if lib.modbus_set_slave(self._ptr, slave) == -1:
            raise error_from_errno(ffi.errno, f"slave {slave}")
        rc = lib.modbus_read_registers(self._ptr, address, count, block._ptr)
        if rc == -1:
            raise error_from_errno(ffi.errno, f"slave {slave} FC03 @{address}+{count}")
        block.count = rc
        return block

    def read_error(self, err: int, slave: int, function: int, address: int,
                   count: int) -> ModbusError:
        """The typed error of a read that failed with errno ``err`` (here or in the
        engine), with what the rejected reply held."""
        return self._error(err, f"slave {slave} FC{function:02d} @{address}+{count}",
                           function, 2 * count if function > 2 else (count + 7) // 8)

    def transact(self, slave: int, pdu: bytes, timeout_ms: int = -1) -> bytes:
        """Send ``pdu`` (function code first) to ``slave`` and return the reply ADU, in
        one C call (csrc/emb_io.c ``emb_request``); ``timeout_ms``: the response timeout of
        this request only (-1: the context's); slave 0 is a broadcast (no reply: b"").

        The C side checks the reply as every reply (csrc/emb_check.c: slave id, or MBAP
        transaction id, protocol id, length and unit id; the function code, a read's byte
        count, a write's echo, the length) and raises exception responses.
        """
        n = len(pdu)
        ffi.memmove(self._req, pdu, n)
        rc = lib.emb_request(self._ptr, self._link, slave, self._req, n, timeout_ms,
                             self._rsp)
        if rc == -1:
            raise self._request_error(ffi.errno, slave, pdu)
        return bytes(ffi.buffer(self._rsp, rc))

    def write(self, slave: int, function: int, address: int, values: Sequence[int],
              timeout_ms: int = -1) -> int:
        """A write encoded, sent, received and checked in one C call (csrc/emb_io.c
        ``emb_write``): FC05 and FC15 (``values``: each non-zero is ON), FC06, FC16, FC22
        (``values``: the AND and the OR mask).  Modbus Application Protocol v1.1b3, 6.5,
        6.6, 6.11, 6.12, 6.16.  Returns the reply ADU's length (:meth:`last_reply`; 0 for
        a broadcast, slave 0); raises as :meth:`transact`."""
        vals = values if isinstance(values, (list, tuple)) else list(values)
        try:
            rc = lib.emb_write(self._ptr, self._link, slave, function, address, len(vals),
                               vals, timeout_ms, self._req, self._rsp)
        except OverflowError:
            raise ValueError(f"{self.label}: FC{function:02d} @{address}: a value of "
                             f"{[v for v in vals if not 0 <= v <= 0xFFFF][:1]} is not a "
                             "register (0..65535)") from None
        if rc == -1:
            err = ffi.errno
            if err == _errno.EINVAL:
                raise ValueError(f"{self.label}: FC{function:02d} @{address} of {len(vals)} "
                                 "values: the function must be 5, 6, 15, 16 or 22, the "
                                 "address 0..65535 and the count what the function allows")
            pdu = bytes(ffi.buffer(self._req, _write_pdu_len(function, len(vals))))
            raise self._request_error(err, slave, pdu)
        return int(rc)

    def _request_error(self, err: int, slave: int, pdu: bytes) -> ModbusError:
        """The typed error of a request ``pdu`` that failed with errno ``err``."""
        if slave == 0:
            return error_from_errno(err, f"broadcast FC{pdu[0]:02d}")
        if err == lib.EMB_EWECHO:  # worded as before the check moved into C
            return self._echo_error(slave, pdu)
        qty = int.from_bytes(pdu[3:5], "big")  # a read's quantity (6.1-6.4, 6.17)
        count = (qty + 7) // 8 if pdu[0] in (1, 2) else 2 * qty
        return self._error(err, f"slave {slave} FC{pdu[0]:02d}", pdu[0], count)

    def _echo_error(self, slave: int, pdu: bytes) -> ProtocolError:
        """The error of a write whose reply does not echo the request (6.5, 6.6, 6.11,
        6.12, 6.16): what came, and what the request holds."""
        adu = self.last_reply()
        reply = adu[self._header:] if self._header > 1 else adu[1:-2]
        echo = pdu[1:7] if pdu[0] == 0x16 else pdu[1:5]
        return ProtocolError(
            f"slave {slave} FC{pdu[0]:02d} @{int.from_bytes(pdu[1:3], 'big')}: echo "
            f"{reply[1:].hex(' ')} does not match the request {echo.hex(' ')}")

    def send(self, slave: int, pdu: bytes) -> None:
        """Send without waiting for a reply (broadcast)."""
        n = len(pdu)
        ffi.memmove(self._req, pdu, n)
        if lib.emb_send(self._ptr, self._link, slave, self._req, n) == -1:
            raise error_from_errno(ffi.errno, f"broadcast FC{pdu[0]:02d}")

    def _error(self, err: int, what: str, function: int, count: int) -> ModbusError:
        """The typed error for ``err``, with what the rejected reply held when it says
        more than the errno (which byte count, which unit, which function code)."""
        rsp = self.last_reply()
        return worded_error(err, what, function, count, rsp, len(rsp), self._header)


def _write_pdu_len(function: int, n: int) -> int:
    """The length of the request PDU csrc/emb_io.c's emb_write_pdu makes (6.5-6.16)."""
    if function == 15:
        return 6 + (n + 7) // 8
    return 6 + 2 * n if function == 16 else (7 if function == 22 else 5)


def read_error_of(err: int, slave: int, function: int, address: int, count: int,
                  reply: bytes, length: int, header: int) -> ModbusError:
    """The typed error of a read of ``count`` at ``address`` that failed with errno
    ``err``, worded as :meth:`Context.read_error` words it; ``reply``: the first bytes of
    the reply rejected (``length`` long, ``header`` bytes before its PDU), as the
    engine's fault policy keeps them (csrc/emb_fault.c)."""
    return worded_error(err, f"slave {slave} FC{function:02d} @{address}+{count}", function,
                        2 * count if function > 2 else (count + 7) // 8, reply, length,
                        header)


def worded_error(err: int, what: str, function: int, count: int, rsp: bytes, length: int,
                 h: int) -> ModbusError:
    """The typed error for ``err`` about ``what``; ``rsp``: the rejected reply (its first
    bytes at least), ``length``: its whole length, ``h``: its header size."""
    exc = error_from_errno(err, what)
    if length < h + 2 or len(rsp) < h + 2:
        return exc
    detail = ""
    if err == lib.EMB_ECOUNT:
        detail = f"{rsp[h + 1]}, expected {count}"
    elif err == lib.EMB_ESLAVE:
        detail = f"{rsp[h - 1]}"
    elif err == lib.EMB_EFUNCTION:
        detail = f"{rsp[h]:#04x}, expected {function:#04x}"
    elif err == lib.EMB_EOTHEREXC:
        detail = f"{rsp[h]:#04x} code {rsp[h + 1]:#04x}"
    elif err == lib.EMB_EPROTOID:
        detail = f"{rsp[2] << 8 | rsp[3]:#06x}"
    elif err == lib.EMB_EMBAPLEN:
        detail = f"{rsp[4] << 8 | rsp[5]}, frame has {length - 6}"
    elif err == lib.EMB_ELENGTH:
        detail = f"{length - h - (0 if h > 1 else 2)} bytes of PDU"
    if detail:
        return type(exc)(f"{exc} ({detail})")
    return exc


def discard_input(fd: int, total_s: float, quiet_s: float, limit_s: float | None = None) -> int:
    """Throw away input on ``fd``: wait up to ``total_s`` for stray bytes; once bytes
    come, go on until ``quiet_s`` of silence, but never past ``limit_s`` (default
    ``total_s`` + 1 s).  0 for both takes only what is pending.  Returns the byte count;
    raises :class:`ModbusConnectionError` if the link failed or was closed."""
    limit = total_s + 1.0 if limit_s is None else limit_s
    n = lib.emb_discard_input(fd, round(total_s * 1000), max(1, round(quiet_s * 1000)),
                              round(limit * 1000))
    if n == -1:
        raise error_from_errno(ffi.errno, f"fd {fd}: discarding input")
    return int(n)
