"""A link whose RTU framing is done in Python, for byte streams libmodbus cannot frame.

Two cases need it, both on RTU-over-TCP sockets (client or listen mode):

* DTU heartbeats ("HB", 0xFE, ...) that a DTU sends on an idle link can arrive between
  a request and its reply; libmodbus' RTU receive would take them for the start of the
  reply and fail.  Here they are skipped wherever they arrive and counted.
* Wrapped report frames of an edge MCU (:mod:`edgemodbus.protocol.wrapped`): requests go out
  wrapped (``FF AA`` + register address + RTU frame + ``0D``), the reply is the frame
  with the same slave, function and address and, for a read, the byte count the request
  asks for; all other frames, also while a request waits (and while idle: the line
  worker watches :attr:`idle_fd`), are unsolicited reports and go to the line's devices.

The checks are those of the libmodbus path (csrc/emb_io.c): CRC, slave id, function
code, exception responses, the byte count of a read, the echo of a write; after a
timeout the line is settled, after other errors drained (plain RTU: no transaction id).
Polling a socket (not select) means no fd limit here.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections.abc import Callable

from .._ffi import Block
from ..codec import BlockDecoder, Change
from ..datatypes import Area
from ..errors import (
    CrcError,
    ModbusConnectionError,
    ModbusError,
    ModbusTimeoutError,
    ProtocolError,
    exception_for_code,
)
from ..protocol import rtu
from ..protocol.wrapped import Report, ReportParser, wrap
from ..stats import LineStats
from .endpoint import DtuEndpoint, LineTiming, TcpEndpoint
from .link import READ_FC, Link, log

_POLL_IN = select.POLLIN | select.POLLERR | select.POLLHUP


class StreamLink(Link):
    """The Python-framed backend: RTU over a socket (heartbeat skipping, or wrapped
    frames).  Never on a serial line, so there is no inter-frame gap to keep."""

    def __init__(
        self,
        sock: socket.socket,
        endpoint: TcpEndpoint | DtuEndpoint,
        timing: LineTiming,
        stats: LineStats,
        *,
        heartbeat: bytes = b"",
        wrapped: bool = False,
        on_report: Callable[[Report], None] | None = None,
        on_close: Callable[[], None] | None = None,
        initial: bytes = b"",
    ) -> None:
        """``initial``: bytes that came on the socket before the link (after a DTU's
        registration): taken as if received now (reports dispatched, heartbeats
        counted), nothing having been asked yet."""
        super().__init__(endpoint, timing, stats, sock.fileno(), on_close=on_close)
        self._conn = sock
        self._response_timeout = timing.response_timeout
        self._heartbeat = heartbeat
        self._wrapped = wrapped
        self._parser = ReportParser(heartbeat) if wrapped else None
        self._on_report = on_report
        self._behind_reply: list[Report] = []  # reports that came after a reply
        self._poll = select.poll()
        self._poll.register(self._fd, _POLL_IN)
        self.idle_fd = self._fd if wrapped else None
        sock.setblocking(False)
        if initial:
            self._take(initial, None)

    # -- bookkeeping ---------------------------------------------------------------------
    def set_response_timeout(self, seconds: float) -> None:
        self._response_timeout = seconds

    def close(self) -> None:
        if not self.is_open:
            return
        self.is_open = False
        if self._on_close is not None:
            self._on_close()
        self._conn.close()

    def flush_reports(self) -> None:
        behind, self._behind_reply = self._behind_reply, []
        if self._on_report is not None:
            for report in behind:
                self._on_report(report)

    def pump(self) -> None:
        """Read what arrived while idle: reports are dispatched, heartbeats counted."""
        self.flush_reports()
        try:
            self._take(self._recv_now(), None)
        except ModbusConnectionError as exc:
            self._lost(exc)

    # -- socket helpers --------------------------------------------------------------------
    def _lost(self, exc: ModbusConnectionError) -> ModbusConnectionError:
        self.stats.link_errors += 1
        self.close_reason = str(exc)
        self.close()
        return exc

    def _recv_now(self) -> bytes:
        """Whatever is readable now (b"" if nothing); a closed peer is a link error."""
        chunks: list[bytes] = []
        while True:
            try:
                data = self._conn.recv(4096)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                raise ModbusConnectionError(
                    f"{self.endpoint.describe()}: link error: {exc.strerror or exc}"
                ) from None
            if not data:
                raise ModbusConnectionError(f"{self.endpoint.describe()}: peer closed the link")
            chunks.append(data)
            if len(data) < 4096:
                break
        return b"".join(chunks)

    def _wait(self, seconds: float) -> bool:
        return bool(self._poll.poll(max(0, int(seconds * 1000 + 0.999))))

    def _send(self, data: bytes) -> None:
        try:
            self._conn.setblocking(True)
            self._conn.sendall(data)
        except OSError as exc:
            raise ModbusConnectionError(
                f"{self.endpoint.describe()}: send failed: {exc.strerror or exc}"
            ) from None
        finally:
            if self.is_open:
                self._conn.setblocking(False)

    def _strip(self, data: bytes) -> bytes:
        """Plain RTU: count and remove heartbeat packets (they arrive whole, between
        frames)."""
        hb = self._heartbeat
        if hb and hb in data:
            n = data.count(hb)
            self.stats.heartbeats += n
            data = data.replace(hb, b"")
        return data

    def _take(self, data: bytes, want: Callable[[Report], bool] | None) -> Report | None:
        """Wrapped: parse ``data``; return the first report ``want`` accepts and
        dispatch the others as unsolicited reports: those before it at once (they are
        older than the reply), those behind it once the reply was applied
        (:meth:`flush_reports`)."""
        parser = self._parser
        if parser is None:
            if data:
                rest = self._strip(data)
                self.stats.discarded_bytes += len(rest)
            return None
        if not data:
            return None
        hb0, drop0 = parser.heartbeats, parser.dropped
        reports = parser.feed(data)
        self.stats.heartbeats += parser.heartbeats - hb0
        self.stats.dropped_frames += parser.dropped - drop0
        found: Report | None = None
        for report in reports:
            if found is None and want is not None and want(report):
                found = report
                continue
            self.stats.reports += 1
            if found is not None:
                self._behind_reply.append(report)
            elif self._on_report is not None:
                self._on_report(report)
        return found

    # -- transactions --------------------------------------------------------------------
    def read_decode(self, slave: int, area: Area, address: int, count: int,
                    decoder: BlockDecoder, report_all: bool) -> tuple[Block, list[Change]]:
        """Framed in Python: read, then decode (no combined C call on this path)."""
        block = self.read(slave, area, address, count)
        return block, decoder.decode(block, report_all)

    def read(self, slave: int, area: Area, address: int, count: int) -> Block:
        if not self.is_open:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: link is down")
        if self._ready_at:
            self._wait_turn()
        self.stats.requests += 1
        fc = READ_FC[area]
        nbytes = (count + 7) // 8 if area.is_bit else 2 * count
        start = time.monotonic()
        try:
            body = self._exchange(slave, struct.pack(">BHH", fc, address, count), nbytes)
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            if self._pace:
                self._done()
        self.stats.responses += 1
        self.stats.rtt_total += time.monotonic() - start
        data = body[3:]
        if area.is_bit:
            bits = [(data[i // 8] >> (i % 8)) & 1 for i in range(count)]
            return Block.from_values(bits, bits=True)
        return Block.from_values(struct.unpack(f">{count}H", data), bits=False)

    def _write(self, slave: int, pdu: bytes) -> None:
        if not self.is_open:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: link is down")
        self._wait_turn()
        self.stats.requests += 1
        if slave == 0:  # broadcast: no reply (Modbus over Serial Line v1.02, 2.1)
            try:
                self._send(self._frame(slave, pdu))
            except ModbusError as exc:
                raise self._fail(exc) from None
            finally:
                self._done(self.timing.turnaround_delay)
            return
        start = time.monotonic()
        try:
            body = self._exchange(slave, pdu, None)
            self._check_write_reply(slave, pdu, body + b"\0\0")
        except ModbusError as exc:
            raise self._fail(exc) from None
        finally:
            self._done()
        self.stats.responses += 1
        self.stats.rtt_total += time.monotonic() - start

    def _frame(self, slave: int, pdu: bytes) -> bytes:
        if self._wrapped:
            return wrap(struct.unpack_from(">H", pdu, 1)[0], slave, pdu)
        return rtu.frame(slave, pdu)

    def _exchange(self, slave: int, pdu: bytes, nbytes: int | None) -> bytes:
        """Send ``pdu`` and return the checked reply without its CRC (slave id first).
        ``nbytes``: the byte count a read reply must carry; None for a write."""
        what = f"slave {slave} FC{pdu[0]:02d} @{struct.unpack_from('>H', pdu, 1)[0]}"
        # stale input first: heartbeats and unsolicited reports are taken, the rest dropped
        self.flush_reports()
        if self._wait(0):
            self._take(self._recv_now(), None)
        self._send(self._frame(slave, pdu))
        if self._wrapped:
            return self._receive_wrapped(slave, pdu, nbytes, what)
        return self._receive_rtu(slave, pdu, nbytes, what)

    def _receive_wrapped(self, slave: int, pdu: bytes, nbytes: int | None, what: str) -> bytes:
        """The reply is the wrapped frame of our slave, function and address and, for a
        read, with the byte count the request asks for (``nbytes``); every other frame
        that comes meanwhile, also one of our slave, function and address with another
        count (the MCU reporting a range that starts where we read), is an unsolicited
        report, and the reply is still awaited.  No reply within the response timeout is
        a timeout (a write then counts as not confirmed)."""
        fc = pdu[0]
        address = struct.unpack_from(">H", pdu, 1)[0]

        def ours(report: Report) -> bool:
            if report.slave != slave or report.address != address:
                return False
            if report.function == fc | 0x80:
                return True
            return report.function == fc and (nbytes is None or report.data[0] == nbytes)

        deadline = time.monotonic() + self._response_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not self._wait(left):
                raise ModbusTimeoutError(f"{what}: no wrapped reply (timeout)")
            report = self._take(self._recv_now(), ours)
            if report is None:
                continue
            if report.function & 0x80:
                raise exception_for_code(report.data[0], what)
            return bytes([report.slave, report.function]) + report.data

    def _receive_rtu(self, slave: int, pdu: bytes, nbytes: int | None, what: str) -> bytes:
        fc = pdu[0]
        buf = b""
        hb = self._heartbeat
        deadline = time.monotonic() + self._response_timeout
        while True:
            if buf:
                need = _reply_length(buf)
                if need is not None and len(buf) >= need:
                    break
                wait = self.timing.byte_timeout
            else:
                wait = deadline - time.monotonic()
            if wait <= 0 or not self._wait(wait):
                if buf:
                    raise ModbusTimeoutError(f"{what}: incomplete reply (byte timeout)")
                raise ModbusTimeoutError(f"{what}: no response (timeout)")
            buf += self._recv_now()
            while hb and buf.startswith(hb):  # a heartbeat before (or instead of) the reply
                buf = buf[len(hb):]
                self.stats.heartbeats += 1
            if hb and buf and len(buf) < len(hb) and hb.startswith(buf):
                continue  # maybe the first part of a heartbeat
        assert need is not None
        frame, rest = buf[:need], buf[need:]
        rest = self._strip(rest)
        if rest:  # more than one frame: whatever follows ours is stale
            self.stats.discarded_bytes += len(rest)
        if rtu.crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
            raise CrcError(f"{what}: CRC error")
        if frame[0] != slave:
            raise ProtocolError(f"{what}: response from the wrong slave id ({frame[0]})")
        if frame[1] == fc | 0x80:
            raise exception_for_code(frame[2], what)
        if frame[1] != fc:
            raise ProtocolError(f"{what}: function code of the reply is not the request's")
        if nbytes is not None and frame[2] != nbytes:
            raise ProtocolError(f"{what}: byte count does not match the request")
        return frame[:-2]

    def _fail(self, exc: ModbusError) -> ModbusError:
        """Count the error; settle after a timeout (plain RTU), drain after others."""
        stats = self.stats
        if isinstance(exc, ModbusConnectionError):
            return self._lost(exc)
        try:
            if isinstance(exc, ModbusTimeoutError):
                stats.timeouts += 1
                if self.timing.settle > 0:
                    # wrapped frames carry their address: a late one is a valid report
                    self._discard(self.timing.settle, self._settle_limit)
            else:
                stats.responses += 1
                if isinstance(exc, CrcError):
                    stats.crc_errors += 1
                elif isinstance(exc, ProtocolError):
                    stats.protocol_errors += 1
                else:
                    code = getattr(exc, "code", 0)
                    stats.exceptions[code] = stats.exceptions.get(code, 0) + 1
                    return exc
                self._discard(self._quiet, self._drain_limit)
        except ModbusConnectionError as link_exc:
            return self._lost(link_exc)
        return exc

    def _discard(self, total: float, limit: float) -> None:
        """Take in what arrives for ``total`` seconds, and once bytes came until the line
        is quiet, at most ``limit`` seconds."""
        start = time.monotonic()
        last = 0.0
        while True:
            now = time.monotonic()
            until = max(start + total, last + self._quiet) if last else start + total
            wait = min(until, start + limit) - now
            if wait <= 0 or not self._wait(wait):
                return
            self._take(self._recv_now(), None)
            last = time.monotonic()


def _reply_length(buf: bytes) -> int | None:
    """Length of the RTU reply at the start of ``buf`` (:func:`rtu.reply_length`), None
    while too few bytes came to tell.  A function code other than the request's is framed
    by what it claims to be; a frame that cannot be one takes what has come (the check
    then fails on it)."""
    need = rtu.reply_length(buf)
    if need == rtu.NEED_MORE:
        return None
    if need == rtu.UNKNOWN:
        log.debug("reply with function code %#04x: taking %d bytes", buf[1], len(buf))
        return len(buf)
    return need
