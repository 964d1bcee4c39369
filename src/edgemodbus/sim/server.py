"""A multi-slave Modbus RTU slave with fault injection, for the demo and for tests.

One :class:`Simulator` plays every slave of one RS-485 "line". It serves raw RTU frames
(slave id + PDU + CRC-16/MODBUS, no MBAP header) over TCP, as a transparent DTU or serial
server would, and over a pseudo-terminal whose slave side a master opens as a serial
port. Every TCP connection is a line of its own (its own receive buffer); the slaves and
their data are shared by all lines.

Values start DERIVED FROM THEIR ADDRESS (:func:`default_register`, :func:`default_bit`),
so a value that came from the wrong request is detectable. Per-slave movers make values
change over time (computed lazily from the clock at request time), and per-slave
:class:`Faults` knobs, settable at runtime from any thread, misbehave on the wire in the
ways real slaves, adapters and DTUs do.

One background thread runs a ``selectors`` loop for every listener, connection and pty;
delayed and chunked replies are scheduled on a timer heap, never slept on, so a slow
slave does not hold up other connections, and an idle simulator blocks in ``select``.

This module is pure Python (stdlib only) and never touches libmodbus, so it can check
the master library from the outside.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import heapq
import itertools
import logging
import os
import random
import selectors
import signal
import socket
import struct
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from ..datatypes import Area
from ..protocol import rtu
from .movers import add_demo_movers
from .slave import DEFAULT_SIZE, Slave, _Action, _Reset

__all__ = [
    "DtuClient",
    "Simulator",
    "main",
]

log = logging.getLogger("edgemodbus.simulator")  # one logger name for the whole package

_RX_LIMIT = 4096  # a request is at most 256 bytes (Serial Line 2.5.1); more is garbage


# --- the line loop --------------------------------------------------------------------


class _Line:
    """One half-duplex "line": a TCP client connection or a pty master."""

    def __init__(
        self,
        name: str,
        silence: float,
        sock: socket.socket | None = None,
        fds: tuple[int, int] | None = None,
    ) -> None:
        self.name = name
        self.silence = silence
        self.sock = sock
        self.fds = fds  # pty (master, slave); the slave end is held open so that the
        # master never sees a hangup (EIO) between two clients
        self.path = ""  # pty: the slave side's path
        self.link = ""  # pty: a symlink to it made by serve_pty(link=...)
        self.rx = bytearray()
        self.out = bytearray()
        self.last_rx = 0.0
        self.idle_pending = False
        self.closed = False
        # DTU-client mode (Simulator.dial)
        self.heartbeat = b""
        self.heartbeat_before_reply = False  # put a heartbeat in front of every reply
        self.wrapped = False  # wrapped-report framing: FF AA addr RTU 0D
        self.heartbeats_sent = 0

    @property
    def is_tcp(self) -> bool:
        return self.sock is not None

    def fileno(self) -> int:
        if self.sock is not None:
            return self.sock.fileno()
        assert self.fds is not None
        return self.fds[0]

    def recv(self) -> bytes:
        if self.sock is not None:
            return self.sock.recv(4096)
        assert self.fds is not None
        return os.read(self.fds[0], 4096)

    def send(self, data: bytes | bytearray) -> int:
        if self.sock is not None:
            return self.sock.send(data)
        assert self.fds is not None
        return os.write(self.fds[0], data)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.sock is not None:
            self.sock.close()
        if self.fds is not None:
            for fd in self.fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
        if self.link:
            with contextlib.suppress(OSError):
                if os.readlink(self.link) == self.path:
                    os.unlink(self.link)


class Simulator:
    """Many slaves on one simulated line, served over TCP and/or ptys.

    >>> sim = Simulator(slaves=[1, 2, 3])
    >>> sim.slave(2).faults.silent = True
    >>> port = sim.serve_tcp("127.0.0.1", 0)  # starts the loop thread
    >>> sim.stop()
    """

    def __init__(
        self, slaves: Iterable[int] = (1,), size: int = DEFAULT_SIZE, *, seed: int | None = None
    ) -> None:
        self._size = size
        self._slaves: dict[int, Slave] = {}
        for sid in slaves:
            self.add_slave(sid)
        self._rng = random.Random(seed)
        self._lock = threading.Lock()  # state, command queue, owned resources, line stats
        self._state = "new"
        self._thread: threading.Thread | None = None
        self._sel: selectors.BaseSelector | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._commands: collections.deque[Callable[[], None]] = collections.deque()
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._owned: list[socket.socket | _Line] = []  # closed by stop()
        self._lines: set[_Line] = set()  # loop thread only
        self._line_stats: collections.Counter[str] = collections.Counter()
        self.tcp_ports: list[int] = []
        self.pty_paths: list[str] = []

    # -- slaves

    def add_slave(self, slave_id: int, size: int | None = None) -> Slave:
        """Put another slave on the line (also while serving)."""
        if slave_id in self._slaves:
            raise ValueError(f"slave {slave_id} already exists")
        slave = Slave(slave_id, self._size if size is None else size)
        self._slaves[slave_id] = slave
        return slave

    def remove_slave(self, slave_id: int) -> None:
        """Take a slave off the line: its address goes silent."""
        del self._slaves[slave_id]

    def slave(self, slave_id: int) -> Slave:
        return self._slaves[slave_id]

    @property
    def slaves(self) -> list[Slave]:
        return list(self._slaves.values())

    def stats(self) -> dict[str, Any]:
        """{"line": frames, discarded_bytes, unknown_slave, broadcasts, connections,
        "slaves": {id: Slave.stats()}}."""
        with self._lock:
            line = {
                k: self._line_stats[k]
                for k in ("frames", "discarded_bytes", "unknown_slave", "broadcasts", "connections")
            }
        return {"line": line, "slaves": {s.slave_id: s.stats() for s in self.slaves}}

    # -- lifecycle

    def start(self) -> Simulator:
        """Start the loop thread (serve_tcp/serve_pty do it when needed)."""
        with self._lock:
            if self._state == "running":
                return self
            if self._state == "stopped":
                raise RuntimeError("simulator stopped; create a new one")
            sel = selectors.DefaultSelector()
            wake_r, wake_w = socket.socketpair()
            wake_r.setblocking(False)
            wake_w.setblocking(False)
            sel.register(wake_r, selectors.EVENT_READ, self._on_wake)
            self._sel, self._wake_r, self._wake_w = sel, wake_r, wake_w
            self._thread = threading.Thread(
                target=self._run, name="edgemodbus-simulator", daemon=True
            )
            self._state = "running"
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving: close every socket and fd and join the thread. Idempotent."""
        with self._lock:
            if self._state == "stopped":
                return
            was_running = self._state == "running"
            self._state = "stopped"
        thread = self._thread
        if was_running and thread is not None:
            self._wake()
            thread.join(10.0)
            if thread.is_alive():
                log.error("simulator loop did not stop within 10 s")
        with self._lock:
            owned, self._owned = self._owned, []
        for res in owned:
            res.close()
        self._lines.clear()
        if self._sel is not None:
            self._sel.close()
        for s in (self._wake_r, self._wake_w):
            if s is not None:
                s.close()

    def __enter__(self) -> Simulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- endpoints

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0, *, silence: float = 0.02,
                  wrapped: bool = False) -> int:
        """Listen for raw RTU frames over TCP; returns the bound port. Each connection is
        a line of its own; ``silence`` is the idle time that ends an unparsable frame.
        ``wrapped``: the connections use the edge MCU's wrapped frames (see :meth:`dial`)."""
        self.start()
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(16)
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        self._own(sock)
        bound = int(sock.getsockname()[1])
        self._call(lambda: self._register_listener(sock, silence, wrapped))
        self.tcp_ports.append(bound)
        return bound

    def serve_pty(
        self,
        *,
        baudrate: int = 9600,
        silence: float | None = None,
        link: str | os.PathLike[str] | None = None,
    ) -> str:
        """Create a pty in raw mode and serve its master side; returns the path of the
        slave side, for a master to open as a serial port. The frame-ending silence is
        t3.5 at ``baudrate`` (11-bit characters, at least 1.75 ms: Serial Line 2.5.1.1).
        With ``link``, a symlink of that name points to it (replacing an old one), so a
        master keeps one port name across :meth:`close_pty` and a new ``serve_pty``."""
        self.start()
        master, slave = os.openpty()
        line = _Line("pty", 0.0, fds=(master, slave))
        try:
            tty.setraw(slave)  # no echo, no line discipline: bytes pass through untouched
            os.set_blocking(master, False)
            path = os.ttyname(slave)
            line.path = path
            if link is not None:
                line.link = os.fspath(link)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(line.link)
                os.symlink(path, line.link)
        except BaseException:
            line.close()
            raise
        line.name = f"pty {path}"
        line.silence = silence if silence is not None else max(3.5 * 11 / baudrate, 0.00175)
        self._own(line)
        self._call(lambda: self._register_line(line))
        self.pty_paths.append(path)
        return path

    def close_pty(self, path: str | os.PathLike[str]) -> None:
        """The adapter disappears: close a pty served by :meth:`serve_pty` (``path`` is
        its slave side or its link), so that a master holding it open gets EIO, and
        remove the link."""
        wanted = os.fspath(path)
        found: list[_Line] = []

        def drop() -> None:
            for line in list(self._lines):
                if line.fds is not None and wanted in (line.path, line.link):
                    self._close_line(line)
                    found.append(line)

        self._call(drop)
        if not found:
            raise KeyError(f"no pty {wanted!r} is served")
        with contextlib.suppress(ValueError):
            self.pty_paths.remove(found[0].path)

    def clients(self) -> list[DtuClient]:
        """Handles of the TCP connections being served (to push wrapped reports)."""
        found: list[DtuClient] = []

        def collect() -> None:
            found.extend(DtuClient(self, line) for line in self._lines if line.is_tcp)

        self._call(collect)
        return found

    def disconnect_clients(self) -> int:
        """Close every TCP client connection (the listeners stay): a link break.
        Returns how many were closed."""
        closed: list[int] = []

        def drop() -> None:
            for line in list(self._lines):
                if line.is_tcp:
                    self._close_line(line)
                    closed.append(1)

        self._call(drop)
        return len(closed)

    def dial(
        self,
        host: str,
        port: int,
        *,
        registration: bytes = b"",
        heartbeat: bytes = b"",
        heartbeat_interval: float = 0.0,
        heartbeat_before_reply: bool = False,
        wrapped: bool = False,
        silence: float = 0.02,
        timeout: float = 5.0,
    ) -> DtuClient:
        """DTU-client mode: connect to a master listening on ``host:port`` (as a 4G/
        Ethernet DTU does), send ``registration`` first, then answer RTU requests as
        this simulator's slaves.  ``heartbeat`` is sent every ``heartbeat_interval``
        seconds (0: never) and, with ``heartbeat_before_reply``, in front of every
        reply.  ``wrapped``: requests and replies use the edge MCU's wrapped frames
        (FF AA + register address + RTU frame + 0D) and :meth:`DtuClient.push_report`
        sends unsolicited reports."""
        self.start()
        sock = socket.create_connection((host, port), timeout=timeout)
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if registration:
                sock.sendall(registration)
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        local = sock.getsockname()
        line = _Line(f"dtu {local[0]}:{local[1]}", silence, sock=sock)
        line.heartbeat = heartbeat
        line.heartbeat_before_reply = heartbeat_before_reply
        line.wrapped = wrapped
        self._own(line)

        def register() -> None:
            with self._lock:
                self._line_stats["connections"] += 1
            self._register_line(line)
            if heartbeat and heartbeat_interval > 0:
                self._at(time.monotonic() + heartbeat_interval,
                         lambda: self._heartbeat_tick(line, heartbeat_interval))

        self._call(register)
        return DtuClient(self, line)

    def _heartbeat_tick(self, line: _Line, interval: float) -> None:
        if line.closed:
            return
        line.heartbeats_sent += 1
        self._act(line, line.heartbeat)
        self._at(time.monotonic() + interval, lambda: self._heartbeat_tick(line, interval))

    # -- plumbing between threads

    def _own(self, res: socket.socket | _Line) -> None:
        with self._lock:
            if self._state == "stopped":
                res.close()
                raise RuntimeError("simulator stopped")
            self._owned.append(res)

    def _disown(self, res: socket.socket | _Line) -> None:
        with self._lock, contextlib.suppress(ValueError):
            self._owned.remove(res)

    def _wake(self) -> None:
        if self._wake_w is not None:
            # A full buffer means the loop is already due to wake; OSError: closing.
            with contextlib.suppress(OSError):
                self._wake_w.send(b"\0")

    def _call(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop thread and wait for it."""
        if threading.current_thread() is self._thread:
            fn()
            return
        done = threading.Event()
        errors: list[BaseException] = []

        def wrapped() -> None:
            try:
                fn()
            except BaseException as e:
                errors.append(e)
            finally:
                done.set()

        with self._lock:
            if self._state != "running":
                raise RuntimeError("simulator not running")
            self._commands.append(wrapped)
        self._wake()
        if not done.wait(10.0):
            raise RuntimeError("simulator loop did not respond")
        if errors:
            raise errors[0]

    # -- the loop (everything below runs on the loop thread)

    def _run(self) -> None:
        sel = self._sel
        assert sel is not None
        try:
            while True:
                with self._lock:
                    commands = list(self._commands)
                    self._commands.clear()
                    stopping = self._state != "running"
                for command in commands:
                    command()
                if stopping:
                    return
                self._run_timers()
                timeout = None
                if self._timers:
                    timeout = max(0.0, self._timers[0][0] - time.monotonic())
                for key, mask in sel.select(timeout):
                    self._guarded(key.data, mask)
        except Exception:
            log.exception("simulator loop crashed")

    @staticmethod
    def _guarded(fn: Callable[..., None], *args: Any) -> None:
        """A bug in one handler is logged; it must not take the whole line down."""
        try:
            fn(*args)
        except Exception:
            log.exception("simulator handler failed")

    def _on_wake(self, mask: int) -> None:
        assert self._wake_r is not None
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass

    def _at(self, due: float, fn: Callable[[], None]) -> None:
        heapq.heappush(self._timers, (due, next(self._seq), fn))

    def _run_timers(self) -> None:
        now = time.monotonic()
        while self._timers and self._timers[0][0] <= now:
            _, _, fn = heapq.heappop(self._timers)
            self._guarded(fn)

    def _register_listener(self, sock: socket.socket, silence: float, wrapped: bool) -> None:
        assert self._sel is not None
        self._sel.register(sock, selectors.EVENT_READ,
                           lambda mask: self._accept(sock, silence, wrapped))

    def _register_line(self, line: _Line) -> None:
        assert self._sel is not None
        self._lines.add(line)
        self._sel.register(
            line.fileno(), selectors.EVENT_READ, lambda mask: self._on_io(line, mask)
        )

    def _accept(self, listener: socket.socket, silence: float, wrapped: bool = False) -> None:
        while True:
            try:
                conn, peer = listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # e.g. EMFILE: leave it in the backlog
                log.warning("simulator accept failed: %s", e)
                return
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            line = _Line(f"tcp {peer}", silence, sock=conn)
            line.wrapped = wrapped
            try:
                self._own(line)
            except RuntimeError:
                return
            with self._lock:
                self._line_stats["connections"] += 1
            self._register_line(line)

    def _close_line(self, line: _Line) -> None:
        if line.closed:
            return
        assert self._sel is not None
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(line.fileno())
        self._lines.discard(line)
        line.close()
        self._disown(line)

    def _on_io(self, line: _Line, mask: int) -> None:
        if mask & selectors.EVENT_WRITE:
            self._flush(line)
        if mask & selectors.EVENT_READ and not line.closed:
            self._on_readable(line)

    def _on_readable(self, line: _Line) -> None:
        try:
            data = line.recv()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            log.debug("simulator %s: read failed: %s", line.name, e)
            self._close_line(line)
            return
        if not data:
            self._close_line(line)  # peer closed (a pty master never reads EOF)
            return
        line.last_rx = time.monotonic()
        line.rx += data
        if len(line.rx) > _RX_LIMIT:
            with self._lock:
                self._line_stats["discarded_bytes"] += len(line.rx) - _RX_LIMIT
            del line.rx[: len(line.rx) - _RX_LIMIT]
        self._parse(line, idle=False)
        if line.rx and not line.idle_pending and not line.closed:
            line.idle_pending = True
            self._at(line.last_rx + line.silence, lambda: self._idle_check(line))

    def _idle_check(self, line: _Line) -> None:
        line.idle_pending = False
        if line.closed or not line.rx:
            return
        due = line.last_rx + line.silence
        if time.monotonic() < due:
            line.idle_pending = True
            self._at(due, lambda: self._idle_check(line))
            return
        self._parse(line, idle=True)

    def _parse(self, line: _Line, idle: bool) -> None:
        if line.wrapped:
            self._parse_wrapped(line)
            return
        frames, consumed, discarded = rtu.split_frames(line.rx, idle)
        del line.rx[:consumed]
        if discarded:
            with self._lock:
                self._line_stats["discarded_bytes"] += discarded
        for raw in frames:
            if line.closed:
                return
            self._serve(line, raw)

    def _parse_wrapped(self, line: _Line) -> None:
        """Wrapped requests: FF AA, register address, RTU request, 0D; garbage before a
        header and frames whose tail or CRC is wrong are discarded."""
        buf = line.rx
        discarded = 0
        while buf:
            start = buf.find(_WRAP_HEADER)
            if start < 0:
                keep = 1 if buf.endswith(_WRAP_HEADER[:1]) else 0
                discarded += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            discarded += start
            del buf[:start]
            need = rtu.request_length(buf, 4)
            if need == rtu.NEED_MORE:
                break
            if need == rtu.UNKNOWN or (len(buf) >= 4 + need + 1 and (
                buf[4 + need] != 0x0D or not rtu.crc_ok(buf[4 : 4 + need])
            )):
                discarded += 2
                del buf[:2]
                continue
            if len(buf) < 4 + need + 1:
                break
            address = (buf[2] << 8) | buf[3]
            raw = bytes(buf[4 : 4 + need])
            del buf[: 4 + need + 1]
            self._serve(line, raw, wrap_address=address)
            if line.closed:
                return
        if discarded:
            with self._lock:
                self._line_stats["discarded_bytes"] += discarded

    def _serve(self, line: _Line, raw: bytes, wrap_address: int | None = None) -> None:
        with self._lock:
            self._line_stats["frames"] += 1
        address, pdu = raw[0], raw[1:-2]
        actions: list[_Action] = []
        if address == 0:
            with self._lock:
                self._line_stats["broadcasts"] += 1
            if pdu[0] in rtu.WRITE_FUNCTIONS:  # Serial Line 2.1: broadcast is for writes only
                for slave in self.slaves:  # those with answer_broadcast all answer: collision
                    actions += slave._handle_broadcast(pdu)
        else:
            target = self._slaves.get(address)
            if target is None:
                with self._lock:
                    self._line_stats["unknown_slave"] += 1
                return  # nobody on the line has this address: silence
            actions = target._handle(raw, pdu, self._rng, line.is_tcp)
        if wrap_address is not None:
            actions = [(after, _wrap(wrap_address, data) if isinstance(data, bytes) else data)
                       for after, data in actions]
        now = time.monotonic()
        for after, data in actions:
            if after <= 0:
                self._act(line, data)
                if line.closed:
                    return
            else:
                self._at(now + after, functools.partial(self._act, line, data))

    def _act(self, line: _Line, data: bytes | _Reset | None) -> None:
        if line.closed:
            return
        if data is None:
            self._close_line(line)
            return
        if isinstance(data, bytes) and line.heartbeat_before_reply and line.heartbeat and (
            data != line.heartbeat
        ):
            line.heartbeats_sent += 1
            data = line.heartbeat + data
        if isinstance(data, _Reset):
            if line.sock is not None:  # linger 0: close() sends RST, not FIN
                with contextlib.suppress(OSError):
                    line.sock.setsockopt(
                        socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0)
                    )
            self._close_line(line)
            return
        if line.out:
            line.out += data
            return
        try:
            sent = line.send(data)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as e:
            log.debug("simulator %s: write failed: %s", line.name, e)
            self._close_line(line)
            return
        if sent < len(data):
            line.out += data[sent:]
            assert self._sel is not None
            self._sel.modify(
                line.fileno(),
                selectors.EVENT_READ | selectors.EVENT_WRITE,
                lambda mask: self._on_io(line, mask),
            )

    def _flush(self, line: _Line) -> None:
        try:
            sent = line.send(line.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            log.debug("simulator %s: write failed: %s", line.name, e)
            self._close_line(line)
            return
        del line.out[:sent]
        if not line.out:
            assert self._sel is not None
            self._sel.modify(
                line.fileno(), selectors.EVENT_READ, lambda mask: self._on_io(line, mask)
            )


_WRAP_HEADER = b"\xff\xaa"


def _wrap(address: int, frame: bytes) -> bytes:
    """An edge MCU's wrapped frame: FF AA, register address (big-endian), RTU frame, 0D."""
    return _WRAP_HEADER + struct.pack(">H", address & 0xFFFF) + frame + b"\x0d"


class DtuClient:
    """One dialled-in DTU connection of a :class:`Simulator` (see :meth:`Simulator.dial`)."""

    def __init__(self, sim: Simulator, line: _Line) -> None:
        self._sim = sim
        self._line = line

    @property
    def closed(self) -> bool:
        return self._line.closed

    @property
    def heartbeats_sent(self) -> int:
        return self._line.heartbeats_sent

    def send(self, data: bytes) -> None:
        """Put raw bytes on the connection (heartbeats, garbage, hand-made frames)."""
        self._sim._call(lambda: self._sim._act(self._line, bytes(data)))

    def push_report(self, slave: int, area: Area, address: int, count: int) -> bytes:
        """Send an unsolicited wrapped report of ``count`` registers (or bits) of
        ``slave`` from ``address``, with the values the slave holds now; returns it."""
        target = self._sim.slave(slave)
        pdu = struct.pack(">BHH", area.read_function, address, count)
        out: list[bytes] = []

        def push() -> None:
            rpdu = target._execute(pdu)
            frame = _wrap(address, rtu.frame(slave, rpdu))
            out.append(frame)
            self._sim._act(self._line, frame)

        self._sim._call(push)
        return out[0]

    def close(self) -> None:
        """The DTU drops its connection."""
        self._sim._call(lambda: self._sim._close_line(self._line))


# --- command line ---------------------------------------------------------------------


def _parse_ids(text: str) -> list[int]:
    """'1,2,5-8' -> [1, 2, 5, 6, 7, 8]."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            lo, hi = (int(x) for x in part.split("-", 1))
            ids.extend(range(lo, hi + 1))
        else:
            ids.append(int(part))
    if not ids:
        raise argparse.ArgumentTypeError("no slave ids")
    return ids


def main(argv: Sequence[str] | None = None) -> int:
    """``edgemodbus simulate``: serve slaves until SIGINT/SIGTERM.

    Prints one line per endpoint (``tcp HOST:PORT``, ``pty PATH``) on stdout, flushed,
    so that a script can read where to connect.
    """
    parser = argparse.ArgumentParser(
        prog="edgemodbus simulate",
        description="Multi-slave Modbus RTU simulator (raw RTU frames over TCP, or a pty).",
    )
    parser.add_argument("--host", default="127.0.0.1", help="listen address (127.0.0.1)")
    parser.add_argument("--port", type=int, default=5020, help="TCP port, 0 = any (5020)")
    parser.add_argument("--slaves", type=_parse_ids, default=[1], help="ids, e.g. 1,2,5-8")
    parser.add_argument("--size", type=int, default=DEFAULT_SIZE, help="points per area")
    parser.add_argument("--pty", action="store_true", help="also serve a pty")
    parser.add_argument("--no-tcp", action="store_true", help="do not listen on TCP")
    parser.add_argument("--movers", action="store_true", help="add the demo's moving values")
    parser.add_argument("--seed", type=int, default=None, help="seed of random faults")
    parser.add_argument("--dial", metavar="HOST:PORT", default=None,
                        help="DTU-client mode: connect to a master listening there "
                        "(rtu-over-tcp-server) instead of listening")
    parser.add_argument("--registration", default="",
                        help="with --dial: registration packet sent first (text)")
    parser.add_argument("--heartbeat", default="", help="with --dial: heartbeat packet (text)")
    parser.add_argument("--heartbeat-interval", type=float, default=0.0,
                        help="with --dial: seconds between heartbeats (0: none)")
    parser.add_argument("--wrapped", action="store_true",
                        help="speak the edge MCU's wrapped report frames")
    args = parser.parse_args(argv)
    dial: tuple[str, int] | None = None
    if args.dial is not None:
        host, _, port_text = args.dial.rpartition(":")
        if not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            parser.error(f"--dial {args.dial!r}: use HOST:PORT with a port of 1..65535")
        dial = (host, int(port_text))

    stop = threading.Event()
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda *_: stop.set())
    try:
        with Simulator(args.slaves, args.size, seed=args.seed) as sim:
            if args.movers:
                for slave in sim.slaves:
                    add_demo_movers(slave)
            if dial is not None:
                sim.dial(dial[0], dial[1], registration=args.registration.encode(),
                         heartbeat=args.heartbeat.encode(),
                         heartbeat_interval=args.heartbeat_interval, wrapped=args.wrapped)
                print(f"dialled {dial[0]}:{dial[1]}", flush=True)
            elif not args.no_tcp:
                port = sim.serve_tcp(args.host, args.port, wrapped=args.wrapped)
                print(f"tcp {args.host}:{port}", flush=True)
            if args.pty:
                print(f"pty {sim.serve_pty()}", flush=True)
            ids = ",".join(str(s) for s in args.slaves)
            print(f"serving slaves {ids}; Ctrl-C to stop", file=sys.stderr, flush=True)
            while not stop.wait(1.0):
                pass
    except OSError as e:
        print(f"edgemodbus simulate: {e}", file=sys.stderr)
        return 1
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
