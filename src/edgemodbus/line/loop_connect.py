"""Connect-mode lines on the loop engine: the TCP connect of an RTU-over-TCP or Modbus
TCP endpoint that never blocks the loop thread.

A :class:`Dialer` is the connector of a connect-mode :class:`~edgemodbus.line.loop.LoopLine`.
The loop worker calls :meth:`Dialer.step` when the line is due to connect and again
whenever its slot wakes (the socket became writable, the connect deadline passed, a
host name was resolved): a non-blocking ``connect()`` watched for writability on the
loop's epoll set (connect(2): EINPROGRESS, then SO_ERROR), each address of the host in
turn with ``connectTimeout`` each, as :func:`socket.create_connection` tries them for
the line worker (line/connect.py :func:`~edgemodbus.line.connect.connect_tcp`).  Once it
ended, the worker calls the line's ``_connect()`` as a line worker does, which calls
:meth:`Dialer.open`: the link on the connected socket, or the connect's failure, worded as
:func:`~edgemodbus.line.connect.connect_tcp` words it, so that link-up and link-down
reports, device statuses and the reconnect backoff are the line worker's.

A numeric host (an IPv4 or IPv6 address) is connected at once; a host name is resolved
on a resolver thread (``edgemodbus-resolve``, up to :data:`MAX_RESOLVERS` while names
wait to be resolved, one lookup per name at a time), since getaddrinfo(3) blocks; the
connect deadline counts from the start of that.
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from .._ffi.context import Context
from .._ffi.loop import Loop
from ..errors import ModbusConnectionError
from .connect import context_link, open_socket_link
from .endpoint import TcpEndpoint
from .link import Link

if TYPE_CHECKING:
    from .worker import LineWorker

Address = tuple[int, Any]  # (family, sockaddr)


def _resolve(host: str, port: int) -> list[Address]:
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return [(family, addr) for family, _, _, _, addr in infos]


def _numeric(host: str, port: int) -> list[Address] | None:
    """The addresses of a numeric host, None for a host name (to resolve)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_NUMERICHOST)
    except (socket.gaierror, UnicodeError):
        return None
    return [(family, addr) for family, _, _, _, addr in infos]


MAX_RESOLVERS = 4
"""Threads that resolve host names at once.  One thread did them in turn: a name whose
DNS answer took 30 s held every other line's name behind it, and each retry of the slow
line queued one more lookup of it, so the others' connects timed out "resolving"."""


class _Resolver:
    """Host names resolved on up to :data:`MAX_RESOLVERS` threads, started when a name is
    asked for and ended once none waits (names are rare beside addresses, and resolved
    once per connect).  A name already waiting or being resolved is not queued again:
    its lookup is shared (a slow name's retries cost no thread or queue entry each)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiting: deque[tuple[str, int]] = deque()
        self._futures: dict[tuple[str, int], Future[list[Address]]] = {}
        self._threads = 0

    def submit(self, host: str, port: int) -> Future[list[Address]]:
        key = (host, port)
        with self._lock:
            future = self._futures.get(key)
            if future is None:
                future = self._futures[key] = Future()
                self._waiting.append(key)
                if self._threads < MAX_RESOLVERS:
                    self._threads += 1
                    threading.Thread(target=self._run, daemon=True,
                                     name="edgemodbus-resolve").start()
        return future

    def _run(self) -> None:
        while True:
            with self._lock:
                if not self._waiting:
                    self._threads -= 1
                    return
                key = self._waiting.popleft()
                future = self._futures[key]
            future.set_running_or_notify_cancel()
            try:
                addresses = _resolve(*key)
            except BaseException as exc:  # handed to the dialers (gaierror, UnicodeError)
                with self._lock:
                    del self._futures[key]
                future.set_exception(exc)
            else:
                with self._lock:
                    del self._futures[key]
                future.set_result(addresses)


resolver = _Resolver()


class Dialer:
    """The connect of one connect-mode loop line (see the module): its state between
    two wake-ups of the slot; loop thread only, but :meth:`open` on the same thread."""

    def __init__(self, endpoint: TcpEndpoint) -> None:
        if endpoint.transport not in ("rtu-over-tcp", "tcp"):
            raise ValueError(f"{endpoint.describe()}: transport {endpoint.transport!r}: "
                             "the loop engine connects rtu-over-tcp and tcp endpoints only")
        self.endpoint = endpoint
        self._sock: socket.socket | None = None  # a connect under way
        self._watched: tuple[Loop, int] | None = None  # (loop, fd) while watched
        self._resolving: Future[list[Address]] | None = None
        self._addresses: list[Address] = []
        self._deadline = 0.0
        self._timeout = 0.0
        self._error = ""  # the last address's failure
        self._result: socket.socket | ModbusConnectionError | None = None

    @property
    def busy(self) -> bool:
        """A connect (or the resolution of its host) is under way."""
        return self._sock is not None or self._resolving is not None

    def step(self, loop: Loop, slot: int, timeout: float, wake: Callable[[], None]) -> bool:
        """Start the connect (when none is under way) or take it further: True once it
        ended (:meth:`open` says how), False while it waits for ``slot``'s socket or
        deadline (set here) or for the resolver, which calls ``wake``."""
        now = time.monotonic()
        if not self.busy:
            self._result = None
            self._timeout = timeout
            self._deadline = now + timeout
            self._error = "no address"
            numeric = _numeric(self.endpoint.host, self.endpoint.port)
            if numeric is None:
                future = resolver.submit(self.endpoint.host, self.endpoint.port)
                self._resolving = future
                future.add_done_callback(lambda _f: wake())
            else:
                self._addresses = numeric
        if self._resolving is not None and not self._resolved(now):
            if self._result is not None:
                return True
            loop.set_timer(slot, self._deadline)
            return False
        while True:
            if self._sock is None:
                if not self._addresses:
                    self._fail(f"connect failed: {self._error}")
                    return True
                if not self._begin(loop, slot, now):
                    continue
            state = self._check(now)
            if state == "pending":
                loop.set_timer(slot, self._deadline)
                return False
            if state == "connected":
                return True

    def _resolved(self, now: float) -> bool:
        """The host name's addresses are in (True), or it failed (False, the result set),
        or it still waits (False)."""
        future = self._resolving
        assert future is not None
        if not future.done():
            if now >= self._deadline:
                self._resolving = None
                self._fail(f"connect timed out after {self._timeout:g} s "
                           f"(resolving {self.endpoint.host!r})")
            return False
        self._resolving = None
        try:
            self._addresses = future.result()
        except UnicodeError as exc:  # the IDNA codec refuses the name before any lookup
            self._fail(f"connect failed: host name {self.endpoint.host!r} is not a valid "
                       f"DNS name (labels of 1..63 characters, no empty label): {exc}")
            return False
        except OSError as exc:
            self._fail(f"connect failed: {exc.strerror or exc}")
            return False
        return True

    def _begin(self, loop: Loop, slot: int, now: float) -> bool:
        """Start the connect to the next address: True while it is under way or done
        (watched on ``slot``), False if it failed at once (the next address, if any)."""
        family, address = self._addresses.pop(0)
        try:
            sock = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:  # e.g. EMFILE: no fd left (the line worker's words)
            self._error = exc.strerror or str(exc)
            return False
        sock.setblocking(False)
        err = sock.connect_ex(address)
        if err not in (0, errno.EINPROGRESS):
            sock.close()
            self._error = os.strerror(err)
            return False
        self._sock = sock
        self._deadline = now + self._timeout
        try:
            loop.watch(sock.fileno(), slot, want_write=True)
        except OSError:
            self._close()
            raise
        self._watched = (loop, sock.fileno())
        return True

    def _check(self, now: float) -> str:
        """The connect under way: "connected", "failed" (the next address) or "pending"
        (or failed for want of time: the last address's timeout is the result)."""
        sock = self._sock
        assert sock is not None
        err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err == 0:
            try:
                sock.getpeername()
            except OSError as exc:
                if exc.errno != errno.ENOTCONN:
                    err = exc.errno or errno.EIO
                elif now < self._deadline:
                    return "pending"
                else:
                    self._error = f"timed out after {self._timeout:g} s"
                    self._close()
                    if not self._addresses:  # (worded as connect_tcp words a timeout)
                        self._fail(f"connect timed out after {self._timeout:g} s")
                        return "connected"
                    return "failed"
            else:
                self._connected(sock)
                return "connected"
        self._error = os.strerror(err)
        self._close()
        return "failed"

    def _connected(self, sock: socket.socket) -> None:
        self._unwatch()
        self._sock = None
        sock.setblocking(True)  # as connect_tcp hands it over (the loop link sets it back)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        self._result = sock

    def _fail(self, message: str) -> None:
        self._close()
        self._addresses = []
        self._result = ModbusConnectionError(f"{self.endpoint.describe()}: {message}")

    def _unwatch(self) -> None:
        watched, self._watched = self._watched, None
        if watched is not None:
            loop, fd = watched
            with contextlib.suppress(OSError):  # (the loop closed already)
                loop.unwatch(fd)

    def _close(self) -> None:
        self._unwatch()
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def abort(self) -> None:
        """Drop a connect under way and a connected socket not taken (the line stops or
        its worker recovers from an error)."""
        self._close()
        self._resolving = None
        self._addresses = []
        result, self._result = self._result, None
        if isinstance(result, socket.socket):
            result.close()

    def open(self, line: LineWorker) -> Link:
        """The link on the socket the connect ended with, or its failure (raised)."""
        result, self._result = self._result, None
        if result is None:
            raise ModbusConnectionError(f"{self.endpoint.describe()}: not connected yet")
        if isinstance(result, ModbusConnectionError):
            raise result
        try:
            if self.endpoint.transport == "tcp":  # Modbus TCP: the loop link frames MBAP
                ctx = Context.on_socket(result.fileno(), self.endpoint.describe(), mbap=True)
                try:
                    return context_link(ctx, self.endpoint, line.timing, line.stats, result)
                except BaseException:
                    ctx.close()
                    raise
            return open_socket_link(result, self.endpoint, line.timing, line.stats,
                                    on_report=line.dispatch_report)
        except BaseException:
            result.close()
            raise


def dialing(connector: object) -> bool:
    """``connector`` is a :class:`Dialer` whose connect is under way."""
    return isinstance(connector, Dialer) and connector.busy


def abort_dial(connector: object) -> None:
    """Abort ``connector``'s connect under way, if it is a :class:`Dialer`."""
    if isinstance(connector, Dialer):
        connector.abort()


__all__ = ["MAX_RESOLVERS", "Dialer", "abort_dial", "dialing"]
