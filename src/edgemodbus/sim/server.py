"""The simulator: many slaves on one simulated line, served over TCP, over ptys, or
dialled out to a master as a DTU does; requests are cut out of each line and answered by
the slave they address."""

from __future__ import annotations

import contextlib
import functools
import os
import random
import socket
import time
import tty
from collections.abc import Callable, Iterable
from typing import Any

from ..protocol import rtu
from .dtu_client import _WRAP_HEADER, DtuClient, _wrap
from .line import _Line
from .loop import _Loop
from .slave import DEFAULT_SIZE, Slave, answer


class Simulator(_Loop):
    """Many slaves on one simulated line, served over TCP and/or ptys.

    >>> sim = Simulator(slaves=[1, 2, 3])
    >>> sim.slave(2).faults.silent = True
    >>> port = sim.serve_tcp("127.0.0.1", 0)  # starts the loop thread
    >>> sim.stop()
    """

    def __init__(
        self, slaves: Iterable[int] = (1,), size: int = DEFAULT_SIZE, *, seed: int | None = None
    ) -> None:
        super().__init__()
        self._size = size
        self._slaves: dict[int, Slave] = {}
        for sid in slaves:
            self.add_slave(sid)
        self._rng = random.Random(seed)
        self.tcp_ports: list[int] = []
        self.pty_paths: list[str] = []
        self.on_request: Callable[[float, bytes], None] | None = None
        """Called on the loop thread with (``time.monotonic()`` when the last bytes of a
        request frame arrived, the frame) for every frame cut out of a line, before it
        is served, whoever it addresses (a benchmark times requests at the slave side
        with it).  It must be quick: the loop waits for it.  Assign from any thread."""

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

    # -- requests (on the loop thread)

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
        hook = self.on_request
        if hook is not None:
            hook(line.last_rx, raw)
        with self._lock:
            self._line_stats["frames"] += 1
            if raw[0] == 0:
                self._line_stats["broadcasts"] += 1
        actions = answer(self._slaves, raw, self._rng, line.is_tcp)
        if actions is None:
            with self._lock:
                self._line_stats["unknown_slave"] += 1
            return  # nobody on the line has this address: silence
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
