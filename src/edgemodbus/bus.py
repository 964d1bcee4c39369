"""One physical line (a serial port, or a TCP endpoint) served by one worker thread.

The worker thread creates, uses and frees the line's libmodbus context: libmodbus
contexts are not thread-safe.  Other threads reach the line through a queue
(:meth:`Bus.submit` and the request helpers, which return ``concurrent.futures.Future``
objects), and pollers (the driver's devices) are called on the worker when they are due.
Queued requests (writes) run before the next poll step, so they jump ahead of reads.

RTU frames carry no transaction id, so a late reply could be taken as the answer to
the next request (seen with libmodbus 3.1.6: wrong data, rc OK).  After a timeout the
line is therefore settled (stray input discarded for up to one more response timeout)
before anything else is sent; after other errors pending input is drained.
"""

from __future__ import annotations

import asyncio
import logging
import operator
import queue
import random
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

from . import _binding
from ._binding import Block, Context
from .datatypes import Area
from .errors import (
    CrcError,
    ModbusConnectionError,
    ModbusError,
    ModbusTimeoutError,
    ProtocolError,
    exception_for_code,
)

log = logging.getLogger("edgemodbus.bus")
T = TypeVar("T")

TRANSPORTS = ("rtu", "rtu-over-tcp", "tcp")
# Silence that ends the discarding of a stray frame, at least: a slave or DTU that
# trickles a late reply slower than the byte timeout must still be drained whole.
_QUIET_FLOOR = 0.05
_IDLE_SLICE = 0.05  # links with unsolicited frames: longest wait before checking the queue
_MAX_IDLE = 3600.0  # a poller due "never" (report-only) still gets an idle step per hour
_MBAP_LEN = 7  # transaction id, protocol id, length, unit id (Modbus Messaging on TCP/IP 3.1.3)


@dataclass(frozen=True)
class SerialPort:
    """Settings of a serial line (Modbus over Serial Line v1.02, 2.5)."""

    port: str
    baudrate: int = 9600
    parity: str = "N"  # N, E or O
    data_bits: int = 8
    stop_bits: int = 1
    rs485: str = "none"  # none | kernel (TIOCSRS485) | rts-up | rts-down
    echo: bool = False  # the adapter echoes every request (2-wire, no echo suppression)

    @property
    def key(self) -> tuple[str, ...]:
        return ("rtu", self.port)

    @property
    def char_time(self) -> float:
        """Seconds per character: start + data + parity + stop bits."""
        bits = 1 + self.data_bits + (0 if self.parity == "N" else 1) + self.stop_bits
        return bits / self.baudrate

    @property
    def frame_gap(self) -> float:
        """Silence between frames: 3.5 characters, fixed at 1.75 ms above 19200 baud
        (Modbus over Serial Line v1.02, 2.5.1.1)."""
        return 0.00175 if self.baudrate > 19200 else 3.5 * self.char_time

    def describe(self) -> str:
        return (
            f"{self.port} {self.baudrate} {self.data_bits}{self.parity}{self.stop_bits}"
            f" rs485={self.rs485}" + (" echo" if self.echo else "")
        )

    @property
    def max_frame_time(self) -> float:
        """Seconds to transmit the largest RTU frame (256 bytes, Serial Line 2.5.1)."""
        return 256 * self.char_time


@dataclass(frozen=True)
class TcpEndpoint:
    """A TCP peer: raw RTU frames without MBAP ("rtu-over-tcp") or Modbus TCP ("tcp")."""

    host: str
    port: int
    transport: str = "rtu-over-tcp"
    echo: bool = False  # RTU over TCP: the serial side echoes every request
    framing: str = "rtu"  # rtu | wrapped-report (RTU over TCP only)
    heartbeat: bytes = b""  # a DTU's idle heartbeat packet, skipped (RTU over TCP only)

    def __post_init__(self) -> None:
        if self.transport not in ("rtu-over-tcp", "tcp"):
            raise ValueError(
                f"transport {self.transport!r}: a TCP endpoint uses 'rtu-over-tcp' or 'tcp'"
            )
        if self.echo and self.transport == "tcp":
            raise ValueError("echo: a Modbus TCP (MBAP) link has no request echo; "
                             "the option is for RTU lines")
        if not 1 <= self.port <= 65535:
            raise ValueError(f"tcpPort {self.port}: must be 1..65535")
        if self.transport == "tcp" and (self.framing != "rtu" or self.heartbeat):
            raise ValueError(f"framing {self.framing!r}/heartbeat: Modbus TCP (MBAP) has its "
                             "own framing; use transport rtu-over-tcp or rtu-over-tcp-server")

    @property
    def key(self) -> tuple[str, ...]:
        return (self.transport, self.host, str(self.port))

    def describe(self) -> str:
        return f"{self.transport}://{self.host}:{self.port}" + (
            " echo" if self.echo else "") + (
            " wrapped" if self.framing == "wrapped-report" else "")

    @property
    def max_frame_time(self) -> float:
        return 0.0


@dataclass(frozen=True)
class DtuEndpoint:
    """One DTU that dials in to our listen port (``rtu-over-tcp-server``): raw RTU
    frames (or wrapped reports) over a TCP connection the DTU opened."""

    listen_host: str
    listen_port: int
    dtu_id: str  # "" with registration none: the port's only DTU
    echo: bool = False
    framing: str = "rtu"  # rtu | wrapped-report
    heartbeat: bytes = b""

    @property
    def key(self) -> tuple[str, ...]:
        return ("dtu", self.listen_host, str(self.listen_port), self.dtu_id)

    def describe(self) -> str:
        name = self.dtu_id or "(single)"
        return f"dtu {name}@{self.listen_host}:{self.listen_port}" + (
            " echo" if self.echo else "") + (
            " wrapped" if self.framing == "wrapped-report" else "")

    @property
    def max_frame_time(self) -> float:
        return 0.0


Endpoint = SerialPort | TcpEndpoint | DtuEndpoint


@dataclass(frozen=True)
class LineTiming:
    """Timeouts and pacing of a line, in seconds."""

    response_timeout: float = 1.0
    byte_timeout: float = 0.2
    settle_timeout: float | None = None  # None: the response timeout; 0 disables settling
    connect_timeout: float = 3.0
    reconnect_interval: float = 5.0  # first wait after a lost link or failed connect
    max_backoff: float = 60.0  # the wait doubles per failed connect up to this
    request_interval: float = 0.0  # extra silence between requests, for slow devices
    turnaround_delay: float = 0.1  # after a broadcast, before the next request

    @property
    def settle(self) -> float:
        return self.response_timeout if self.settle_timeout is None else self.settle_timeout


@dataclass
class LineStats:
    """Counters of one line, updated by its worker only."""

    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)
    link_errors: int = 0
    connects: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    discarded_bytes: int = 0
    heartbeats: int = 0  # DTU heartbeat packets discarded
    reports: int = 0  # wrapped report frames received unsolicited
    dropped_frames: int = 0  # wrapped frames dropped (bad header, tail, CRC, length)
    rtt_total: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "requests": self.requests,
            "responses": self.responses,
            "timeouts": self.timeouts,
            "crcErrors": self.crc_errors,
            "protocolErrors": self.protocol_errors,
            "exceptions": dict(self.exceptions),
            "linkErrors": self.link_errors,
            "connects": self.connects,
            "reconnects": self.reconnects,
            "connectFailures": self.connect_failures,
            "discardedBytes": self.discarded_bytes,
            "heartbeats": self.heartbeats,
            "reports": self.reports,
            "droppedFrames": self.dropped_frames,
            "avgRoundTrip": self.rtt_total / self.responses if self.responses else 0.0,
        }


class Link:
    """An open line as the worker thread sees it: one request at a time, blocking.

    Every method raises a :class:`ModbusError` subclass; a :class:`ModbusConnectionError`
    means the link is closed and the bus will reconnect.  Only the bus worker calls it.
    """

    idle_fd: int | None = None
    """A link that receives unsolicited frames (wrapped reports) sets this: the worker
    then watches the fd while idle and calls :meth:`pump`."""

    def __init__(self, ctx: Context, endpoint: Endpoint, timing: LineTiming,
                 stats: LineStats, sock: socket.socket | None,
                 on_close: Callable[[], None] | None = None) -> None:
        self._ctx = ctx
        self._sock = sock
        self._on_close = on_close
        self.endpoint = endpoint
        self.timing = timing
        self.stats = stats
        self._fd = ctx.fd
        self._mbap = isinstance(endpoint, TcpEndpoint) and endpoint.transport == "tcp"
        self._gap = endpoint.frame_gap if isinstance(endpoint, SerialPort) else 0.0
        self._quiet = max(timing.byte_timeout, 2 * self._gap, _QUIET_FLOOR)
        # a stray frame still arriving when the settle time runs out is drained whole,
        # but a line that never falls quiet does not hold the worker for ever
        self._settle_limit = timing.settle + max(timing.settle, 0.5) + endpoint.max_frame_time
        self._drain_limit = self._quiet + 0.5 + endpoint.max_frame_time
        self._pace = self._gap + timing.request_interval
        self._ready_at = 0.0
        self._timeouts = (-1.0, -1.0)
        self.is_open = True
        self.close_reason: str | None = None  # the link error that closed it
        self._trace = log.isEnabledFor(logging.DEBUG)

    # -- bookkeeping -----------------------------------------------------------------
    def set_response_timeout(self, seconds: float) -> None:
        """Use ``seconds`` as the response timeout from now on (a per-device setting)."""
        wanted = (seconds, self.timing.byte_timeout)
        if wanted != self._timeouts:
            self._ctx.set_timeouts(*wanted)
            self._timeouts = wanted

    def close(self) -> None:
        if not self.is_open:
            return
        self.is_open = False
        self._ctx.close()
        if self._on_close is not None:
            self._on_close()  # e.g. the DTU slot forgets the socket before it is closed
        if self._sock is not None:
            self._sock.close()

    def pump(self) -> None:
        """Read and dispatch what arrived unsolicited (links with ``idle_fd``)."""

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
                if self.timing.settle > 0:
                    stats.discarded_bytes += _binding.discard_input(
                        self._fd, self.timing.settle, self._quiet, self._settle_limit
                    )
            else:
                if isinstance(exc, ProtocolError):
                    stats.responses += 1
                    if isinstance(exc, CrcError):
                        stats.crc_errors += 1
                    else:
                        stats.protocol_errors += 1
                    # the rest of a bad frame may still be on its way
                    stats.discarded_bytes += _binding.discard_input(
                        self._fd, self._quiet, self._quiet, self._drain_limit
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
        """Read ``count`` bits or registers (FC01-04).  The returned block is the
        context's buffer: use it before the next request."""
        if not self.is_open:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: link is down")
        if self._ready_at:
            self._wait_turn()
        stats = self.stats
        stats.requests += 1
        if self._trace:
            self._log_frame("TX", slave, struct.pack(">BHH", _READ_FC[area], address, count))
        start = time.monotonic()
        try:
            block = self._ctx.read(slave, _READ_FC[area], address, count)
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            stats.discarded_bytes += self._ctx.take_discarded()
            if self._trace:
                self._log_reply()
            if self._pace:
                self._done()
        stats.responses += 1
        stats.rtt_total += time.monotonic() - start
        return block

    # -- writes (Modbus Application Protocol v1.1b3, 6.5, 6.6, 6.11, 6.12, 6.16) ------
    def write_coil(self, slave: int, address: int, value: bool) -> None:
        self._write(slave, struct.pack(">BHH", 5, address, 0xFF00 if value else 0x0000))

    def write_register(self, slave: int, address: int, value: int) -> None:
        self._write(slave, struct.pack(">BHH", 6, address, value))

    def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> None:
        n = len(values)
        if not 1 <= n <= _binding.MAX_WRITE_BITS:
            raise ValueError(f"write of {n} coils: must be 1..{_binding.MAX_WRITE_BITS}")
        packed = _pack_bits(values)
        self._write(slave, struct.pack(">BHHB", 15, address, n, len(packed)) + packed)

    def write_registers(self, slave: int, address: int, values: Sequence[int]) -> None:
        n = len(values)
        if not 1 <= n <= _binding.MAX_WRITE_REGISTERS:
            raise ValueError(
                f"write of {n} registers: must be 1..{_binding.MAX_WRITE_REGISTERS}"
            )
        pdu = struct.pack(f">BHHB{n}H", 16, address, n, 2 * n, *values)
        self._write(slave, pdu)

    def mask_write_register(self, slave: int, address: int, and_mask: int, or_mask: int) -> None:
        self._write(slave, struct.pack(">BHHH", 22, address, and_mask, or_mask))

    def _write(self, slave: int, pdu: bytes) -> None:
        if not self.is_open:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: link is down")
        self._wait_turn()
        self.stats.requests += 1
        if self._trace:
            self._log_frame("TX", slave, pdu)
        if slave == 0:  # broadcast: no reply (Modbus over Serial Line v1.02, 2.1)
            try:
                self._ctx.send(0, pdu)
            except ModbusError as exc:
                raise self._fail(exc) from None
            finally:
                self.stats.discarded_bytes += self._ctx.take_discarded()
                self._done(self.timing.turnaround_delay)
            return
        start = time.monotonic()
        try:
            adu = self._ctx.transact(slave, pdu)
            self._check_write_reply(slave, pdu, adu)
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            self.stats.discarded_bytes += self._ctx.take_discarded()
            if self._trace:
                self._log_reply()
            self._done()
        self.stats.responses += 1
        self.stats.rtt_total += time.monotonic() - start

    def _log_frame(self, direction: str, slave: int, pdu: bytes) -> None:
        """Frame trace at DEBUG: the bytes on the wire, e.g. "TX 01 03 00 00 00 0A C5 CD".
        MBAP headers of requests, whose transaction id the C side picks, are shown as
        the unit id only."""
        frame = bytes([slave]) + pdu
        if self._mbap:
            text = f"[MBAP unit {slave}] {pdu.hex(' ').upper()}"
        else:
            text = (frame + crc16(frame)).hex(" ").upper()
        log.debug("%s %s %s", self.endpoint.describe(), direction, text)

    def _log_reply(self) -> None:
        reply = self._ctx.last_reply()
        if reply:
            log.debug("%s RX %s", self.endpoint.describe(), reply.hex(" ").upper())

    def _check_write_reply(self, slave: int, pdu: bytes, adu: bytes) -> None:
        """Check a write's reply: unit, function, and the echo that libmodbus 3.1.6 does
        not check (address/value for FC05/06, address/quantity for FC15/16, the whole
        request for FC22).  The C side has checked the header and function code already;
        this check stands on its own (it is what the reply fuzzer exercises)."""
        what = f"slave {slave} FC{pdu[0]:02d} @{struct.unpack_from('>H', pdu, 1)[0]}"
        if self._mbap:
            if len(adu) < _MBAP_LEN + 2:
                raise ProtocolError(f"{what}: reply of {len(adu)} bytes is too short")
            _tid, proto, length, unit = struct.unpack_from(">HHHB", adu)
            if proto != 0:
                raise ProtocolError(f"{what}: MBAP protocol id {proto}, expected 0")
            if length != len(adu) - 6:
                raise ProtocolError(f"{what}: MBAP length {length}, frame has {len(adu) - 6}")
            body = adu[_MBAP_LEN - 1:]
        else:
            body = adu[:-2]  # strip the CRC, checked by libmodbus
            unit = body[0] if body else -1
        if unit != slave:
            raise ProtocolError(f"{what}: reply from unit {unit}")
        reply = body[1:]
        if not reply:
            raise ProtocolError(f"{what}: empty reply")
        function = pdu[0]
        if reply[0] == function | 0x80 and len(reply) == 2:
            raise exception_for_code(reply[1], what)
        if reply[0] != function:
            raise ProtocolError(f"{what}: reply has function code {reply[0]:#04x}")
        echo_len = 6 if function == 22 else 4
        if reply[1:] != pdu[1:1 + echo_len]:
            raise ProtocolError(
                f"{what}: echo {reply[1:].hex(' ')} does not match the request "
                f"{pdu[1:1 + echo_len].hex(' ')}"
            )


def crc16(frame: bytes) -> bytes:
    """CRC-16/MODBUS of an RTU frame, low byte first (Modbus over Serial Line v1.02,
    6.2.2).  Used for the frame trace only: libmodbus checks real frames."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def _pack_bits(values: Sequence[int | bool]) -> bytes:
    """Bits, first in the low bit of the first byte (Application Protocol 6.1, 6.11)."""
    packed = bytearray((len(values) + 7) // 8)
    for i, bit in enumerate(values):
        if bit:
            packed[i // 8] |= 1 << (i % 8)
    return bytes(packed)


_DUE = operator.attrgetter("due")
_READ_FC = {area: area.read_function for area in Area}  # a dict beats the enum property


class Poller(Protocol):
    """Something the bus worker calls when due: the driver's device polling."""

    due: float
    """``time.monotonic()`` of the next step (read by the worker on every step)."""

    def poll_step(self, link: Link) -> None:
        """Do one request (one block read) on the worker thread."""
        ...

    def link_changed(self, up: bool, reason: str | None) -> None:
        """The line went up or down (called on the worker thread)."""
        ...


class Connector(Protocol):
    """How a bus gets its link, for endpoints the bus cannot open itself (a DTU that
    dials in: the listener hands its socket over)."""

    def open(self, bus: Bus) -> Link:
        """Return an open link, or raise :class:`ModbusConnectionError` (worker thread)."""
        ...


@dataclass
class _Job:
    fn: Callable[[Link], Any]
    future: Future[Any]


_STOP = object()


class Bus:
    """A line and its worker thread.  Created by :class:`BusRegistry` (shared by every
    user of the same endpoint) or directly; ``start()`` then ``stop()``."""

    def __init__(self, endpoint: Endpoint, timing: LineTiming | None = None,
                 connector: Connector | None = None) -> None:
        self.endpoint = endpoint
        self.timing = timing or LineTiming()
        self.connector = connector
        self._connect_now = False  # a connector has a new link ready: take it at once
        self.stats = LineStats()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._pollers: list[Poller] = []
        self._pollers_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._link: Link | None = None
        self.link_up = False
        self.last_link_error: str | None = None

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._run, name=f"edgemodbus-bus {self.endpoint.describe()}", daemon=True
        )
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Fail pending requests, join the worker, close the link (idempotent)."""
        thread = self._thread
        if thread is None:
            return
        self._stopping.set()
        self._queue.put(_STOP)
        if thread is not threading.current_thread():
            wait = timeout if timeout is not None else (
                self.timing.response_timeout + self.timing.settle + self.timing.connect_timeout
                + 5.0
            )
            thread.join(wait)
            if thread.is_alive():
                raise RuntimeError(f"bus {self.endpoint.describe()}: worker did not stop")
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stopping.is_set()

    # -- pollers ---------------------------------------------------------------------
    def attach(self, poller: Poller) -> None:
        with self._pollers_lock:
            if poller not in self._pollers:
                self._pollers = [*self._pollers, poller]
        self._queue.put(None)  # wake the worker to reschedule

    def detach(self, poller: Poller) -> None:
        with self._pollers_lock:
            self._pollers = [p for p in self._pollers if p is not poller]

    @property
    def pollers(self) -> tuple[Poller, ...]:
        return tuple(self._pollers)

    def dispatch_report(self, report: Any) -> None:
        """Hand an unsolicited wrapped report to every poller that takes reports (the
        devices pick theirs by slave id and area).  Worker thread."""
        for poller in self._pollers:
            on_report = getattr(poller, "on_report", None)
            if on_report is None:
                continue
            try:
                on_report(report)
            except Exception:
                log.exception("%s: poller on_report failed", self.endpoint.describe())

    def connect_now(self) -> None:
        """A new link is ready (a DTU dialled in, maybe replacing its old connection):
        drop the current link, if any, and open the new one without waiting for the
        reconnect interval.  Any thread."""
        self._connect_now = True
        self._queue.put(None)

    # -- requests from any thread ------------------------------------------------------
    def submit(self, fn: Callable[[Link], T]) -> Future[T]:
        """Run ``fn(link)`` on the worker, before the next poll step."""
        future: Future[T] = Future()
        if self._stopping.is_set() or self._thread is None:
            future.set_exception(
                ModbusConnectionError(f"bus {self.endpoint.describe()} is not running")
            )
            return future
        self._queue.put(_Job(fn, future))
        return future

    async def submit_async(self, fn: Callable[[Link], T]) -> T:
        return await asyncio.wrap_future(self.submit(fn))

    def read(self, slave: int, area: Area, address: int, count: int) -> Future[list[int]]:
        """Read registers (ints) or bits (0/1 ints) from one slave."""
        return self.submit(lambda link: link.read(slave, area, address, count).to_list())

    def write_coil(self, slave: int, address: int, value: bool) -> Future[None]:
        return self.submit(lambda link: link.write_coil(slave, address, value))

    def write_register(self, slave: int, address: int, value: int) -> Future[None]:
        return self.submit(lambda link: link.write_register(slave, address, value))

    def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> Future[None]:
        values = list(values)
        return self.submit(lambda link: link.write_coils(slave, address, values))

    def write_registers(self, slave: int, address: int, values: Sequence[int]) -> Future[None]:
        values = list(values)
        return self.submit(lambda link: link.write_registers(slave, address, values))

    def mask_write_register(self, slave: int, address: int, and_mask: int,
                            or_mask: int) -> Future[None]:
        return self.submit(lambda link: link.mask_write_register(slave, address, and_mask,
                                                                 or_mask))

    # -- the worker ------------------------------------------------------------------
    def _run(self) -> None:
        next_connect = 0.0
        failures = 0  # failed connects in a row
        try:
            while not self._stopping.is_set():
                link = self._link
                if link is not None and link.is_open and self._connect_now:
                    link.close_reason = "replaced by a new connection"
                    link.close()
                if link is None or not link.is_open:
                    if link is not None:
                        if self._connect_now and self._connect():
                            continue  # replaced: the pollers see one "up", no "down"
                        self._link_lost(link)
                        next_connect = time.monotonic() + self._reconnect_delay(0)
                    if self._connect_now or time.monotonic() >= next_connect:
                        if self._connect():
                            failures = 0
                            continue
                        failures += 1
                        next_connect = time.monotonic() + self._reconnect_delay(failures)
                    self._serve_queue_while_down(next_connect)
                    continue
                self._serve(link)
        finally:
            self._shutdown()

    def _reconnect_delay(self, failures: int) -> float:
        """Wait before the next connect: reconnectInterval, doubled per failed connect
        in a row up to maxBackoff, with +-20 % jitter so that lines do not reconnect
        in step."""
        timing = self.timing
        base = timing.reconnect_interval * 2.0 ** max(0, min(failures - 1, 30))
        base = max(timing.reconnect_interval, min(base, timing.max_backoff))
        return base * random.uniform(0.8, 1.2)

    def _serve(self, link: Link) -> None:
        """One step while the link is up: a queued request, else the most overdue poller."""
        if not self._queue.empty():
            self._handle(self._queue.get_nowait(), link)
            return
        pollers = self._pollers
        if not pollers:
            self._handle(self._queue.get(), link)
            return
        poller = min(pollers, key=_DUE)
        wait = poller.due - time.monotonic()
        if wait > 0:
            if link.idle_fd is not None:
                self._idle_reads(link, wait)
                return
            try:
                item = self._queue.get(timeout=min(wait, _MAX_IDLE))
            except queue.Empty:
                return
            self._handle(item, link)
            return
        try:
            poller.poll_step(link)
        except Exception:  # a poller bug must not kill the line
            log.exception("%s: poller failed", self.endpoint.describe())

    def _idle_reads(self, link: Link, wait: float) -> None:
        """Idle on a link that receives unsolicited frames: watch its socket in slices
        of at most 50 ms, checking the queue between them (near zero CPU when quiet)."""
        fd = link.idle_fd
        assert fd is not None
        poller = select.poll()
        poller.register(fd, select.POLLIN | select.POLLERR | select.POLLHUP)
        deadline = time.monotonic() + min(wait, _MAX_IDLE)
        while link.is_open and self._queue.empty() and not self._connect_now:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            if poller.poll(1000 * min(left, _IDLE_SLICE)):
                link.pump()
        if not self._queue.empty():
            self._handle(self._queue.get_nowait(), link)

    def _handle(self, item: Any, link: Link | None) -> None:
        if item is None or item is _STOP:
            return
        job: _Job = item
        if not job.future.set_running_or_notify_cancel():
            return
        if link is None or not link.is_open:
            job.future.set_exception(ModbusConnectionError(
                f"{self.endpoint.describe()}: link is down ({self.last_link_error})"
            ))
            return
        try:
            result = job.fn(link)
        except BaseException as exc:
            job.future.set_exception(exc)
        else:
            job.future.set_result(result)

    def _serve_queue_while_down(self, until: float) -> None:
        """While disconnected: fail queued requests at once, sleep until the next try."""
        while not self._stopping.is_set() and not self._connect_now:
            wait = until - time.monotonic()
            if wait <= 0:
                return
            try:
                item = self._queue.get(timeout=wait)
            except queue.Empty:
                return
            self._handle(item, None)

    def _connect(self) -> bool:
        first = self.stats.connects == 0 and self.stats.reconnects == 0
        self._connect_now = False
        try:
            try:
                link = self.connector.open(self) if self.connector is not None else self._open()
            except ModbusError:
                raise
            except OSError as os_exc:  # e.g. EMFILE: no fd left for a socket
                raise ModbusConnectionError(
                    f"{self.endpoint.describe()}: cannot open the line: {os_exc}"
                ) from None
        except ModbusError as exc:
            repeated = self.connector is not None and str(exc) == self.last_link_error
            self.last_link_error = str(exc)
            self.stats.connect_failures += 1
            # exc names the line; a connector's same failure again (a DTU that has not
            # dialled in yet) is not repeated at WARNING on every try
            log.log(logging.DEBUG if repeated else logging.WARNING, "connect failed: %s", exc)
            self._notify(False, str(exc))
            return False
        self._link = link
        self.link_up = True
        self.last_link_error = None
        if first:
            self.stats.connects += 1
        else:
            self.stats.reconnects += 1
        log.info("%s: link up", self.endpoint.describe())
        self._notify(True, None)
        return True

    def _open(self) -> Link:
        ep = self.endpoint
        timing = self.timing
        if isinstance(ep, DtuEndpoint):
            raise ModbusConnectionError(f"{ep.describe()}: a DTU link needs a connector")
        if isinstance(ep, SerialPort):
            ctx = Context.rtu(ep.port, ep.baudrate, ep.parity, ep.data_bits, ep.stop_bits)
            try:
                ctx.connect(ep.rs485)
            except ModbusError:
                ctx.close()
                raise
            sock = None
        else:
            sock = _connect_tcp(ep, timing.connect_timeout)
            if ep.transport == "rtu-over-tcp" and (ep.framing != "rtu" or ep.heartbeat):
                from .streamlink import StreamLink  # RTU framed in Python

                return StreamLink(sock, ep, timing, self.stats, heartbeat=ep.heartbeat,
                                  wrapped=ep.framing == "wrapped-report",
                                  on_report=self.dispatch_report)
            try:
                ctx = Context.on_socket(sock.fileno(), ep.describe(), mbap=ep.transport == "tcp")
            except ModbusError:
                sock.close()
                raise
        try:
            ctx.set_timeouts(timing.response_timeout, timing.byte_timeout)
            ctx.set_echo(ep.echo)
        except ValueError:
            ctx.close()
            if sock is not None:
                sock.close()
            raise
        link = Link(ctx, ep, timing, self.stats, sock)
        link._timeouts = (timing.response_timeout, timing.byte_timeout)
        return link

    def _link_lost(self, link: Link) -> None:
        self._link = None
        self.link_up = False
        if link.close_reason:
            self.last_link_error = link.close_reason
        reason = self.last_link_error or "link closed"
        log.warning("%s: link down: %s", self.endpoint.describe(), reason)
        self._notify(False, reason)

    def _notify(self, up: bool, reason: str | None) -> None:
        for poller in self._pollers:
            try:
                poller.link_changed(up, reason)
            except Exception:
                log.exception("%s: poller link_changed failed", self.endpoint.describe())

    def _shutdown(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None
        self.link_up = False
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _Job) and item.future.set_running_or_notify_cancel():
                item.future.set_exception(
                    ModbusConnectionError(f"bus {self.endpoint.describe()} stopped")
                )


def _connect_tcp(ep: TcpEndpoint, timeout: float) -> socket.socket:
    """Connect with a bounded time, then hand a blocking, no-delay socket to libmodbus."""
    try:
        sock = socket.create_connection((ep.host, ep.port), timeout=timeout)
    except TimeoutError:
        raise ModbusConnectionError(
            f"{ep.describe()}: connect timed out after {timeout:g} s"
        ) from None
    except OSError as exc:
        raise ModbusConnectionError(f"{ep.describe()}: connect failed: {exc.strerror or exc}") \
            from None
    sock.settimeout(None)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    return sock


def open_socket_link(sock: socket.socket, endpoint: Endpoint, timing: LineTiming,
                     stats: LineStats, on_close: Callable[[], None] | None = None) -> Link:
    """A libmodbus RTU link on a connected socket we own (RTU over TCP, no MBAP).  On
    failure the socket is left to the caller."""
    ctx = Context.on_socket(sock.fileno(), endpoint.describe(), mbap=False)
    try:
        ctx.set_timeouts(timing.response_timeout, timing.byte_timeout)
        ctx.set_echo(endpoint.echo)
    except ValueError:
        ctx.close()
        raise
    link = Link(ctx, endpoint, timing, stats, sock, on_close)
    link._timeouts = (timing.response_timeout, timing.byte_timeout)
    return link


class BusRegistry:
    """Shares one :class:`Bus` among every user of the same endpoint (many slaves on one
    RS-485 line, many devices behind one serial server port)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._buses: dict[tuple[str, ...], tuple[Bus, int]] = {}

    def acquire(self, endpoint: Endpoint, timing: LineTiming | None = None,
                connector: Callable[[], Connector] | None = None) -> Bus:
        """The bus of ``endpoint``, started on first use; ``connector`` makes the
        connector of a new bus (DTU links)."""
        with self._lock:
            entry = self._buses.get(endpoint.key)
            if entry is not None:
                bus, users = entry
                if bus.endpoint != endpoint:
                    raise ValueError(
                        f"line {endpoint.key[-1]} is already open as "
                        f"'{bus.endpoint.describe()}'; this device asks for "
                        f"'{endpoint.describe()}': devices on one line must agree"
                    )
                self._buses[endpoint.key] = (bus, users + 1)
                return bus
            bus = Bus(endpoint, timing, connector() if connector is not None else None)
            bus.start()
            self._buses[endpoint.key] = (bus, 1)
            return bus

    def release(self, bus: Bus) -> None:
        with self._lock:
            entry = self._buses.get(bus.endpoint.key)
            if entry is None or entry[0] is not bus:
                return
            _, users = entry
            if users > 1:
                self._buses[bus.endpoint.key] = (bus, users - 1)
                return
            del self._buses[bus.endpoint.key]
        bus.stop()

    def buses(self) -> list[Bus]:
        with self._lock:
            return [bus for bus, _ in self._buses.values()]


registry = BusRegistry()

