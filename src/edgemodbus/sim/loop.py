"""The simulator's loop thread: one ``selectors`` loop for every listener, connection and
pty, commands from other threads, timers, and the bytes in and out of each line.

Delayed and chunked replies are scheduled on a timer heap, never slept on, so a slow
slave does not hold up other connections, and an idle simulator blocks in ``select``.
What the bytes a line receives mean is up to the subclass (:meth:`_Loop._parse`).
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import itertools
import logging
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from .actions import _Reset
from .line import _Line

log = logging.getLogger("edgemodbus.simulator")  # one logger name for the whole package

_RX_LIMIT = 4096  # a request is at most 256 bytes (Serial Line 2.5.1); more is garbage

_L = TypeVar("_L", bound="_Loop")


class _Loop:
    """The loop thread of a simulator and the lines it serves: start and stop, running
    calls from other threads on it, timers, accepting, reading and writing.  The
    subclass parses and answers what a line received (:meth:`_parse`)."""

    def __init__(self) -> None:
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

    # -- lifecycle

    def start(self: _L) -> _L:
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

    def __enter__(self: _L) -> _L:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

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

    def _parse(self, line: _Line, idle: bool) -> None:
        """Serve the requests in ``line.rx`` (consuming them); ``idle``: the line has been
        silent for ``line.silence`` since the last byte came."""
        raise NotImplementedError
