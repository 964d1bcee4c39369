"""The worker's view of an open line: one request at a time, blocking.

Used only by the worker thread that opened it, a link keeps the inter-frame silence,
settles the line after a timeout (RTU has no transaction id) and drains it after other
errors, and counts all in :class:`~edgemodbus.stats.LineStats`.  :class:`Link`, the
interface, holds what does not depend on the I/O (timing, pacing, counters, frame trace,
writes); :class:`ContextLink` does the I/O through the libmodbus context and our C
(csrc/emb_io.c, which checks every reply with csrc/emb_check.c; csrc/emb_stream.c for DTU
streams: heartbeats skipped, wrapped reports queued for :meth:`Link.flush_reports` and
:meth:`Link.pump`).
"""

from __future__ import annotations

import logging
import socket
import struct
import time
from collections.abc import Callable, Sequence

from .._ffi import Block, Context, StreamCounters, check
from .._ffi.engine import EV_DEADLINE, Engine, EngineDevice, Waker
from .._ffi.outcomes import Clean, LineCounters
from ..datatypes import Area
from ..errors import (
    CrcError,
    ModbusConnectionError,
    ModbusError,
    ModbusTimeoutError,
    ProtocolError,
    exception_for_code,
)
from ..protocol.limits import MAX_WRITE_BITS, MAX_WRITE_REGISTERS
from ..protocol.wrapped import Report, report_of
from ..stats import LineStats
from .endpoint import Endpoint, LineTiming, SerialPort, TcpEndpoint

log = logging.getLogger("edgemodbus.line")  # the frame trace goes to the line worker's logger

# Silence that ends the discarding of a stray frame, at least: a slave or DTU that
# trickles a late reply slower than the byte timeout must still be drained whole.
QUIET_FLOOR = 0.05
_MBAP_LEN = 7  # transaction id, protocol id, length, unit id (Modbus Messaging on TCP/IP 3.1.3)
READ_FC = {area: area.read_function for area in Area}  # a dict beats the enum property


class Link:
    """An open line as the worker thread sees it: one request at a time, blocking.

    The base of the two backends, never used on its own: a backend implements
    :meth:`read`, :meth:`set_response_timeout`, :meth:`close`,
    :meth:`transact` and ``_write_op`` (a request and its checked reply) and ``_fail``
    (count an error, clean the line).  Every method raises a :class:`ModbusError`; a
    :class:`ModbusConnectionError` means the link is closed (the worker reconnects).
    """

    idle_fd: int | None = None
    """A link that receives unsolicited frames (wrapped reports) sets this: the worker
    then watches the fd while idle and calls :meth:`pump`."""
    owed: bool = False  # after run_engine: the read owed to polling is still owed
    gate: Callable[[], None] | None = None  # may refuse a request (line/worker.py: a lease)

    def __init__(self, endpoint: Endpoint, timing: LineTiming, stats: LineStats, fd: int, *,
                 mbap: bool = False, on_close: Callable[[], None] | None = None) -> None:
        """``fd``: what the line reads from; ``mbap``: Modbus TCP framing (frame trace,
        write-reply check); ``on_close``: called on close, before the socket closes."""
        self.endpoint = endpoint
        self.timing = timing
        self.stats = stats
        self._fd = fd
        self._on_close = on_close
        self._mbap = mbap
        self._gap = endpoint.frame_gap if isinstance(endpoint, SerialPort) else 0.0
        self._quiet = max(timing.byte_timeout, 2 * self._gap, QUIET_FLOOR)
        # a stray frame still arriving when the settle time runs out is drained whole,
        # but a line that never falls quiet does not hold the worker for ever
        self._settle_limit = timing.settle + max(timing.settle, 0.5) + endpoint.max_frame_time
        self._drain_limit = self._quiet + 0.5 + endpoint.max_frame_time
        self._pace = self._gap + timing.request_interval
        self._ready_at = 0.0
        self.is_open = True
        self.close_reason: str | None = None  # the link error that closed it
        self._trace = log.isEnabledFor(logging.DEBUG)

    # -- the backend's part ------------------------------------------------------------
    def read(self, slave: int, area: Area, address: int, count: int) -> Block:
        """Read ``count`` bits or registers (FC01-04).  The returned block may be the
        backend's buffer: use it before the next request."""
        raise NotImplementedError

    def set_response_timeout(self, seconds: float) -> None:
        """Use ``seconds`` as the response timeout from now on (a per-device setting)."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def _write_op(self, slave: int, function: int, address: int, values: Sequence[int]) -> None:
        """A write (function 5, 6, 15, 16 or 22 of ``values``) and its checked reply;
        slave 0: broadcast, no reply."""
        raise NotImplementedError

    def transact(self, slave: int, pdu: bytes,
                 timeout: float | None = None, early: Callable[[ModbusError], None] | None = None
                 ) -> bytes:
        """A request to ``slave`` (not 0) and its reply ADU, checked in C as every reply
        (csrc/emb_check.c); ``timeout``: the response timeout of this request only;
        ``early``: called with a failure before the line is settled or drained."""
        raise NotImplementedError

    def reply_pdu(self, adu: bytes) -> bytes:  # without the MBAP header, or id and CRC
        return adu[_MBAP_LEN:] if self._mbap else adu[1:-2]

    def _fail(self, exc: ModbusError) -> ModbusError:
        raise NotImplementedError

    def run_engine(self, waker: Waker, counters: LineCounters, devices: Sequence[EngineDevice],
                   until: float, owed: bool = False) -> tuple[int, int, int]:
        """Run ``devices``' passes in C until something needs Python or ``until``: the
        event, the device's index and an errno (_ffi/engine.py). ``owed``: a job ran
        since the last read: the next waits for a due block's read (:attr:`owed`)."""
        raise NotImplementedError

    def read_failed(self, err: int, slave: int, area: Area, address: int,
                    count: int) -> ModbusError:
        """The link failed (errno ``err``) on an engine's read: count it, close the link."""
        raise NotImplementedError

    def take_ended(self) -> list[int]:  # devices (by index) whose passes ended for Python
        return []

    def pump(self) -> None:  # read and dispatch what arrived unsolicited (``idle_fd``)
        pass

    def flush_reports(self) -> None:
        """Dispatch the reports that came behind the last reply, once it was applied
        (they are newer; links that take reports only)."""

    # -- pacing -----------------------------------------------------------------------
    def _wait_turn(self) -> None:
        """Keep the inter-frame silence, the request interval and the turnaround delay."""
        if self._ready_at:
            delay = self._ready_at - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self._ready_at = 0.0

    def _done(self, extra_delay: float = 0.0) -> None:
        if self._pace or extra_delay:
            self._ready_at = time.monotonic() + self._pace + extra_delay

    # -- writes (Modbus Application Protocol v1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16) ------
    def write_coil(self, slave: int, address: int, value: bool) -> None:
        self._write_op(slave, 5, address, (1 if value else 0,))

    def write_register(self, slave: int, address: int, value: int) -> None:
        self._write_op(slave, 6, address, (value,))

    def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> None:
        n = len(values)
        if not 1 <= n <= MAX_WRITE_BITS:
            raise ValueError(f"write of {n} coils: must be 1..{MAX_WRITE_BITS}")
        self._write_op(slave, 15, address, values)

    def write_registers(self, slave: int, address: int, values: Sequence[int]) -> None:
        n = len(values)
        if not 1 <= n <= MAX_WRITE_REGISTERS:
            raise ValueError(f"write of {n} registers: must be 1..{MAX_WRITE_REGISTERS}")
        self._write_op(slave, 16, address, values)

    def mask_write_register(self, slave: int, address: int, and_mask: int, or_mask: int) -> None:
        self._write_op(slave, 22, address, (and_mask, or_mask))

    # -- reply check -------------------------------------------------------------------
    def _check_write_reply(self, slave: int, pdu: bytes, adu: bytes) -> None:
        """Check a write's reply ADU held in Python (the reply fuzzer's entry,
        tests/unit/ffi/test_fuzz_reply.py) with the C check every transaction makes
        (csrc/emb_check.c: unit, MBAP protocol id and length, function, exception, the
        echo that libmodbus 3.1.6 does not check); raises what it found."""
        what = f"slave {slave} FC{pdu[0]:02d} @{struct.unpack_from('>H', pdu, 1)[0]}"
        verdict = check.check_reply_adu(self._mbap, slave, pdu, adu)
        if verdict.exception >= 0:
            raise exception_for_code(verdict.exception, what)
        if verdict.ok:
            return
        body = adu[_MBAP_LEN - 1:] if self._mbap else adu[:-2]  # unit id and reply PDU
        if self._mbap and len(adu) < _MBAP_LEN + 2:
            why = f"reply of {len(adu)} bytes is too short"
        elif verdict.error == check.E_PROTOCOL_ID:
            why = f"MBAP protocol id {struct.unpack_from('>H', adu, 2)[0]}, expected 0"
        elif verdict.error == check.E_MBAP_LENGTH:
            why = f"MBAP length {struct.unpack_from('>H', adu, 4)[0]}, frame has {len(adu) - 6}"
        elif not body or body[0] != slave:
            why = f"reply from unit {body[0] if body else -1}"
        elif len(body) < 2:
            why = "empty reply"
        elif body[1] != pdu[0]:
            why = f"reply has function code {body[1]:#04x}"
        else:  # the echo (or its length)
            echo = pdu[1:7] if pdu[0] == 22 else pdu[1:5]
            why = f"echo {body[2:].hex(' ')} does not match the request {echo.hex(' ')}"
        raise ProtocolError(f"{what}: {why}")


class ContextLink(Link):
    """The link: the line's libmodbus context (and, on TCP, the socket we own) and our C
    do the I/O.  On a DTU stream (``ctx.is_stream``) the wrapped reports the engine did
    not apply in C (csrc/emb_report.c) go to ``on_report``: those that came before a
    reply as soon as the transaction returns, the others by :meth:`flush_reports` once
    the reply was applied (they are newer)."""

    def __init__(self, ctx: Context, endpoint: Endpoint, timing: LineTiming,
                 stats: LineStats, sock: socket.socket | None,
                 on_close: Callable[[], None] | None = None, *,
                 timeouts: tuple[float, float] = (-1.0, -1.0),
                 on_report: Callable[[Report], None] | None = None) -> None:
        """``timeouts``: the (response, byte) timeouts already set on ``ctx``."""
        super().__init__(endpoint, timing, stats, ctx.fd, on_close=on_close,
                         mbap=isinstance(endpoint, TcpEndpoint) and endpoint.transport == "tcp")
        self._ctx = ctx
        self._sock = sock
        self._timeouts = timeouts
        self._on_report = on_report
        self._stream = ctx.is_stream
        if ctx.wrapped:
            self.idle_fd = ctx.fd  # reports come while idle too: the worker pumps
        self._engine: Engine | None = None
        ctx.set_trace(self._trace)  # the frames go into a ring in C; _log_trace logs them

    # -- the engine --------------------------------------------------------------------
    def run_engine(self, waker: Waker, counters: LineCounters, devices: Sequence[EngineDevice],
                   until: float, owed: bool = False) -> tuple[int, int, int]:
        """See :meth:`Link.run_engine`; when it comes back the frames it traced are
        logged, a DTU stream's counters taken and the wrapped reports that came before
        the last reply dispatched (they are older than it; the worker dispatches the rest
        once the reply was applied: :meth:`flush_reports`).  A closed link: EV_DEADLINE
        at once (the worker reconnects)."""
        if not self.is_open:
            return EV_DEADLINE, -1, 0
        engine = self._engine
        if engine is None or engine.waker is not waker:
            engine = self.new_engine(waker, counters)
        engine.set_devices(devices)
        event = engine.run(until, owed)
        self.owed = engine.owed
        self.collect()
        return event, engine.event_device, engine.event_errno

    def new_engine(self, waker: Waker, counters: LineCounters) -> Engine:
        """A new engine on this link, its pacing from now on (loop workers: line/loop.py)."""
        ready, self._engine = self._ready_at, Engine(
            self._ctx, waker, counters, self._pace, self.idle_fd,
            Clean(self.timing.settle, self._settle_limit, self._quiet, self._drain_limit))
        self._engine.ready_at = ready
        return self._engine

    context = property(lambda self: self._ctx, doc="The link's libmodbus context.")

    def _log_trace(self) -> None:
        """Log the frames our C traced (csrc/emb_io.c, in the line engine too) at DEBUG:
        the time each was sent or received, then its bytes on the wire, e.g.
        "TX 01 03 00 00 00 0A C5 CD" (Modbus TCP: the whole ADU, MBAP header included)."""
        frames, lost = self._ctx.take_trace()
        if not (frames or lost):
            return
        where = self.endpoint.describe()
        offset = time.time() - time.monotonic()  # the frames' times, as wall-clock times
        second, clock = -1, ""
        for frame in frames:
            at = frame.at + offset
            if int(at) != second:  # frames come in bursts: one strftime per second
                second = int(at)
                clock = time.strftime("%H:%M:%S", time.localtime(second))
            log.debug("%s %s.%06d %s %s", where, clock, int(at % 1 * 1e6),
                      "TX" if frame.tx else "RX", frame.frame.hex(" ").upper())
        if lost:
            log.debug("%s: %d frames not traced (the trace ring was full)", where, lost)

    @property
    def _ready_at(self) -> float:
        """No request before this: the engine's (one clock for its reads and ours)."""
        engine = getattr(self, "_engine", None)
        return engine.ready_at if engine is not None else self._ready_py

    @_ready_at.setter
    def _ready_at(self, at: float) -> None:
        engine = getattr(self, "_engine", None)
        if engine is not None:
            engine.ready_at = at
        else:
            self._ready_py = at

    def read_failed(self, err: int, slave: int, area: Area, address: int,
                    count: int) -> ModbusError:
        return self._fail(self._ctx.read_error(err, slave, READ_FC[area], address, count))

    def take_ended(self) -> list[int]:
        return self._engine.take_ended() if self._engine is not None else []

    # -- DTU streams -----------------------------------------------------------------
    def flush_reports(self) -> None:
        """Dispatch the reports waiting (behind the last reply, or from a settle)."""
        if self._stream and self._ctx.reports_waiting:
            self._dispatch(self._ctx.take_reports())

    def pump(self) -> None:
        """Read what arrived while idle: reports are dispatched, heartbeats counted."""
        self.flush_reports()
        if not self.is_open:
            return
        try:
            self._ctx.pump()
        except ModbusConnectionError as exc:
            self._fail(exc)
        finally:
            self.collect()
        self.flush_reports()

    def feed(self, data: bytes) -> None:
        """Bytes that came on the socket before the link (after a DTU's registration):
        taken as if received now, nothing having been asked yet (reports queued,
        heartbeats counted; on a plain RTU link they answer nothing: discarded)."""
        if not data:
            return
        if not self._stream:
            log.debug("%s: %d bytes after the registration discarded: %s",
                      self.endpoint.describe(), len(data), data.hex(" ").upper())
        self._ctx.feed(data)
        self.collect()

    def _dispatch(self, raws: list[bytes]) -> None:
        self.stats.reports += len(raws)
        on_report = self._on_report
        if on_report is not None:
            for raw in raws:
                on_report(report_of(raw))

    def collect(self) -> None:
        """Take the C side's counters into the line's stats; dispatch the reports that
        came before the last reply (older than it)."""
        ctx = self._ctx
        self.stats.discarded_bytes += ctx.take_discarded()
        if self._trace:
            self._log_trace()
        if not self._stream:
            return
        counts = ctx.take_counters()
        if counts is not None:
            self._count(counts)
        before = ctx.reports_before
        if before:
            self._dispatch(ctx.take_reports(before))

    def _count(self, counts: StreamCounters) -> None:
        stats = self.stats
        stats.heartbeats += counts.heartbeats
        stats.dropped_frames += counts.dropped + counts.lost
        where = self.endpoint.describe()
        if counts.dropped:
            log.warning("%s: %d wrapped frame(s) dropped (bad header, length, tail or CRC, "
                        "or noise); the last began %s", where, counts.dropped,
                        counts.last_drop.hex(" ").upper())
        if counts.lost:
            log.warning("%s: %d wrapped report(s) lost: the link's report queue was full",
                        where, counts.lost)

    # -- bookkeeping -----------------------------------------------------------------
    def set_response_timeout(self, seconds: float) -> None:
        """Use ``seconds`` as the response timeout from now on (a per-device setting).
        The engine sets each device's own on the same context: what it set last counts."""
        engine = self._engine
        if engine is not None and engine.timeout_ms >= 0:
            self._timeouts = (engine.timeout_ms / 1000, self._timeouts[1])
        wanted = (seconds, self.timing.byte_timeout)
        if wanted != self._timeouts:
            self._ctx.set_timeouts(*wanted)
            self._timeouts = wanted
            if engine is not None:
                engine.timeout_ms = -1  # the engine sets the device's own again

    def close(self) -> None:
        if not self.is_open:
            return
        self.is_open = False
        self._ctx.close()
        if self._on_close is not None:
            self._on_close()  # e.g. the DTU slot forgets the socket before it is closed
        if self._sock is not None:
            self._sock.close()

    def _fail(self, exc: ModbusError) -> ModbusError:
        """Count an error and clean the line so the next request starts clean."""
        stats = self.stats
        if isinstance(exc, ModbusConnectionError):
            stats.link_errors += 1
            self.close_reason = str(exc)
            self.close()
            return exc
        try:
            if isinstance(exc, ModbusTimeoutError):
                # RTU has no transaction id: a reply that comes late must not be taken
                # for the answer to the next request, so wait it out (settle) first
                stats.timeouts += 1
                if self.timing.settle > 0:  # a late wrapped frame is a report: kept
                    stats.discarded_bytes += self._ctx.discard(
                        self.timing.settle, self._quiet, self._settle_limit
                    )
            else:
                if isinstance(exc, ProtocolError):
                    stats.responses += 1
                    if isinstance(exc, CrcError):
                        stats.crc_errors += 1
                    else:
                        stats.protocol_errors += 1
                    # the rest of a bad frame may still be on its way
                    stats.discarded_bytes += self._ctx.discard(
                        self._quiet, self._quiet, self._drain_limit
                    )
                else:  # an exception response is a complete, valid frame
                    stats.responses += 1
                    code = getattr(exc, "code", 0)
                    stats.exceptions[code] = stats.exceptions.get(code, 0) + 1
        except ModbusConnectionError as link_exc:
            stats.link_errors += 1
            self.close_reason = str(link_exc)
            self.close()
            return link_exc
        return exc

    # -- reads -----------------------------------------------------------------------
    def read(self, slave: int, area: Area, address: int, count: int) -> Block:
        """Read ``count`` bits or registers (FC01-04) into the context's buffer (use the
        block before the next request); the engine makes the polls, never this."""
        return self._read(slave, area, address, count)

    def _read(self, slave: int, area: Area, address: int, count: int) -> Block:
        self._begin()
        stats = self.stats
        start = time.monotonic()
        try:
            block = self._ctx.read(slave, READ_FC[area], address, count)
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            self.collect()
            if self._pace:
                self._done()
        stats.responses += 1
        stats.rtt_total += time.monotonic() - start
        return block

    # -- writes ----------------------------------------------------------------------
    def _write_op(self, slave: int, function: int, address: int, values: Sequence[int]) -> None:
        """One C call: encoded, sent, its reply received and checked (csrc/emb_io.c
        emb_write); a broadcast (slave 0) gets no reply (Modbus over Serial Line v1.02,
        2.1) and keeps the turnaround delay."""
        self._begin()
        start = time.monotonic()
        try:
            self._ctx.write(slave, function, address, values)
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            self.collect()
            self._done(0.0 if slave else self.timing.turnaround_delay)
        if slave:
            self.stats.responses += 1
            self.stats.rtt_total += time.monotonic() - start

    def transact(self, slave: int, pdu: bytes,
                 timeout: float | None = None, early: Callable[[ModbusError], None] | None = None
                 ) -> bytes:
        """One C call, ``timeout`` included (csrc/emb_io.c emb_request sets it for this
        request and puts the context's back)."""
        self._begin()
        start = time.monotonic()
        try:
            adu = self._ctx.transact(slave, pdu, -1 if timeout is None
                                     else max(1, round(timeout * 1000)))
        except ModbusError as exc:
            if early is not None:
                early(exc)
            raise self._fail(exc) from None
        finally:
            self.collect()
            self._done()
        self.stats.responses += 1
        self.stats.rtt_total += time.monotonic() - start
        return adu

    def _begin(self) -> None:
        if not self.is_open:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: link is down")
        self._wait_turn()
        if self.gate is not None:  # after the wait, right before the request goes out
            self.gate()
        self.stats.requests += 1

