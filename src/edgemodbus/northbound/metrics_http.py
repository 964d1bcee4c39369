"""The ``/metrics`` HTTP server: one thread, one selector, bounded.

The standard library's servers give every connection a thread and wait for a request's
headers as long as the peer likes: 1,024 connections that never finish their headers
held 1,019 threads and every fd of the process (then the Modbus TCP server's accept
failed too).  This one serves every connection from one thread with a selector:

* a request's headers must arrive within :data:`HEADER_DEADLINE` seconds of the accept
  and fit in :data:`MAX_REQUEST_BYTES` (else 431, or the connection is closed);
* at most :data:`MAX_CONNECTIONS` connections at once; one more evicts the oldest that
  is still sending its request (a scraper sends its request at once: the oldest waiting
  one is the likeliest a slow peer), or is closed when every one is being answered;
* the answer is written without blocking, within :data:`WRITE_DEADLINE` seconds, then
  the connection is closed (``Connection: close``: one request per connection);
* accept errors for want of fds or memory (EMFILE, ENFILE, ENOBUFS, ENOMEM) are a cap
  too: the oldest connection still sending its request is closed to make room; when
  there is none, accepting pauses, 50 ms doubling to 2 s as the DTU listener does
  (line/dtu_listener.py); logged through line/log_limit.py (one line per kind and
  10 s, then a summary).

The request is handed to a WSGI application (prometheus_client's ``make_wsgi_app``, so
the exposition, its content negotiation, gzip and ``name[]`` filtering are the
library's) on the server's thread: a scrape reads counters only.  Only GET and HEAD.
"""

from __future__ import annotations

import contextlib
import io
import logging
import selectors
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import unquote

from ..line.accept_pause import ACCEPT_ERRORS, AcceptPause
from ..line.log_limit import LogLimiter

log = logging.getLogger("edgemodbus.metrics")

HEADER_DEADLINE = 5.0
"""Seconds from the accept until a request's headers are complete; then it is closed."""
WRITE_DEADLINE = 10.0
"""Seconds to write the answer to a peer that reads slowly; then it is closed."""
MAX_CONNECTIONS = 64
"""Connections at once (each is one fd and a buffer of at most MAX_REQUEST_BYTES)."""
MAX_REQUEST_BYTES = 8192
"""The request line and headers, at most (a body is never read)."""
ACCEPT_BATCH = 64
"""Connections accepted per turn of the loop."""

_REASONS = {400: "Bad Request", 405: "Method Not Allowed",
            431: "Request Header Fields Too Large", 500: "Internal Server Error"}

WsgiApp = Callable[[dict[str, Any], Callable[..., Any]], Iterable[bytes]]


@dataclass(eq=False)
class _Conn:
    sock: socket.socket
    source: str
    deadline: float  # monotonic: headers (reading) or the answer (writing) by then
    buf: bytearray = field(default_factory=bytearray)
    out: memoryview | None = None  # the answer still to send (None: reading)


class MetricsHttpServer:
    """Serve ``app`` on ``host:port`` (0: a free port, see :attr:`server_port`) from the
    thread that calls :meth:`serve_forever`; :meth:`shutdown` (any thread) ends it,
    :meth:`server_close` closes every socket."""

    def __init__(self, host: str, port: int, app: WsgiApp, *,
                 header_deadline: float = HEADER_DEADLINE,
                 write_deadline: float = WRITE_DEADLINE,
                 max_connections: int = MAX_CONNECTIONS,
                 max_request_bytes: int = MAX_REQUEST_BYTES) -> None:
        if max_connections < 1:
            raise ValueError(f"max_connections {max_connections}: must be >= 1")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(128)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self.server_port: int = sock.getsockname()[1]
        self._app = app
        self.header_deadline = header_deadline
        self.write_deadline = write_deadline
        self.max_connections = max_connections
        self.max_request_bytes = max_request_bytes
        self._conns: dict[socket.socket, _Conn] = {}  # in accept order, oldest first
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(sock, selectors.EVENT_READ)
        self._sel.register(self._wake_r, selectors.EVENT_READ)
        self._stop = threading.Event()
        self._done = threading.Event()
        self._done.set()
        self._logs = LogLimiter(log, interval=10.0, burst=1)
        self._paused = AcceptPause()  # accepting after an accept error (EMFILE...)
        self.counts = {"accepted": 0, "answered": 0, "evicted": 0, "refused": 0,
                       "timedOut": 0, "tooLarge": 0, "badRequests": 0, "acceptErrors": 0}

    # -- lifecycle ---------------------------------------------------------------------
    def serve_forever(self) -> None:
        """Serve until :meth:`shutdown`."""
        self._done.clear()
        try:
            while not self._stop.is_set():
                try:
                    self._turn()
                except Exception:  # a bug must not end the exporter: log it and go on
                    log.exception("metrics: unexpected error in the HTTP server")
                    self._stop.wait(0.1)
        finally:
            self._logs.flush(force=True)
            self._done.set()

    def shutdown(self) -> None:
        """Make :meth:`serve_forever` return, and wait for it (at most 5 s)."""
        self._stop.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._done.wait(5.0)

    def server_close(self) -> None:
        """Close the listening socket and every connection."""
        for conn in list(self._conns.values()):
            self._close(conn)
        self._sel.close()
        for sock in (self._sock, self._wake_r, self._wake_w):
            sock.close()

    def connections(self) -> int:
        return len(self._conns)

    # -- the loop --------------------------------------------------------------------
    def _turn(self) -> None:
        now = time.monotonic()
        if self._paused.over(now):
            self._sel.register(self._sock, selectors.EVENT_READ)
        first = min((c.deadline for c in self._conns.values()), default=now + 60.0)
        first = min(first, self._logs.next_due(), self._paused.until)
        accept = False
        for key, events in self._sel.select(max(0.0, first - now)):
            if key.fileobj is self._sock:
                accept = True
            elif key.fileobj is self._wake_r:
                with contextlib.suppress(OSError):
                    self._wake_r.recv(64)
            else:
                conn = self._conns.get(key.fileobj)  # type: ignore[call-overload]
                if conn is None:
                    continue
                if events & selectors.EVENT_WRITE:
                    self._send(conn)
                elif events & selectors.EVENT_READ:
                    self._read(conn)
        if accept:
            self._accept()
        now = time.monotonic()
        for conn in [c for c in self._conns.values() if c.deadline <= now]:
            self.counts["timedOut"] += 1
            self._close(conn)
        self._logs.flush()

    def _accept(self) -> None:
        for _ in range(ACCEPT_BATCH):
            try:
                sock, addr = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in ACCEPT_ERRORS:
                    if self._evict(exc.strerror or str(exc)):  # the fd limit is a cap too
                        continue
                    self._pause_accepting(exc)
                else:
                    self._logs.event(logging.WARNING, "accept errors", "accept",
                                     "metrics: accept failed: %s", exc)
                return
            self._paused.accepted()
            self.counts["accepted"] += 1
            source = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
            if (len(self._conns) >= self.max_connections
                    and not self._evict(f"{len(self._conns)} connections open")):
                self.counts["refused"] += 1
                sock.close()
                continue
            sock.setblocking(False)
            conn = _Conn(sock, source, time.monotonic() + self.header_deadline)
            self._conns[sock] = conn
            self._sel.register(sock, selectors.EVENT_READ)

    def _evict(self, why: str) -> bool:
        """Close the oldest connection still sending its request; False if none is."""
        for conn in self._conns.values():
            if conn.out is None:
                self.counts["evicted"] += 1
                self._logs.event(logging.WARNING, "evicted", conn.source.rsplit(":", 1)[0],
                                 "metrics: no room for a connection (%s): the oldest still "
                                 "sending its request (%s) closed", why, conn.source)
                self._close(conn)
                return True
        return False

    def _pause_accepting(self, exc: OSError) -> None:
        """Out of fds or memory: the pending connections wait in the backlog a while."""
        self.counts["acceptErrors"] += 1
        pause = self._paused.failed(time.monotonic())
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(self._sock)
        self._logs.event(logging.WARNING, "accept pauses", "accept",
                         "metrics: accept failed (%s); pausing accepting for %.2g s",
                         exc.strerror or exc, pause)

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._close(conn)
            return
        conn.buf += data
        end = conn.buf.find(b"\r\n\r\n")
        if end < 0:
            if len(conn.buf) > self.max_request_bytes:
                self.counts["tooLarge"] += 1
                self._answer(conn, _error(431))
            return
        if end + 4 > self.max_request_bytes:
            self.counts["tooLarge"] += 1
            self._answer(conn, _error(431))
            return
        self._answer(conn, self._respond(bytes(conn.buf[:end])))

    def _respond(self, head: bytes) -> bytes:
        """The whole answer to a request whose line and headers are ``head``."""
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            self.counts["badRequests"] += 1
            return _error(400)
        method, target, version = parts
        if method not in ("GET", "HEAD"):
            self.counts["badRequests"] += 1
            return _error(405, [("Allow", "GET, HEAD")])
        path, _, query = target.partition("?")
        environ: dict[str, Any] = {
            "REQUEST_METHOD": method, "SCRIPT_NAME": "", "PATH_INFO": unquote(path),
            "QUERY_STRING": query, "SERVER_NAME": "edgemodbus",
            "SERVER_PORT": str(self.server_port), "SERVER_PROTOCOL": version,
            "CONTENT_LENGTH": "", "wsgi.version": (1, 0), "wsgi.url_scheme": "http",
            "wsgi.input": io.BytesIO(b""), "wsgi.errors": sys.stderr,
            "wsgi.multithread": False, "wsgi.multiprocess": False, "wsgi.run_once": False,
        }
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if not sep or not name or name != name.strip():
                self.counts["badRequests"] += 1
                return _error(400)
            key = name.upper().replace("-", "_")
            if key not in ("CONTENT_TYPE", "CONTENT_LENGTH"):
                key = "HTTP_" + key
            environ[key] = value.strip()
        status: list[str] = []
        headers: list[tuple[str, str]] = []

        def start_response(st: str, hdrs: list[tuple[str, str]], exc_info: Any = None) -> Any:
            status[:] = [st]
            headers[:] = hdrs
            return lambda _data: None

        try:
            result = self._app(environ, start_response)
            try:
                body = b"".join(result)
            finally:
                close = getattr(result, "close", None)
                if close is not None:
                    close()
        except Exception:
            log.exception("metrics: the scrape failed")
            return _error(500)
        self.counts["answered"] += 1
        return _response(status[0] if status else "500 Internal Server Error", headers,
                         body, send_body=method != "HEAD")

    def _answer(self, conn: _Conn, data: bytes) -> None:
        """Send ``data``, then close; what does not fit now is sent as the peer reads."""
        conn.out = memoryview(data)
        conn.buf = bytearray()
        conn.deadline = time.monotonic() + self.write_deadline
        self._sel.modify(conn.sock, selectors.EVENT_WRITE)
        self._send(conn)

    def _send(self, conn: _Conn) -> None:
        out = conn.out
        if out is None:
            return
        try:
            sent = conn.sock.send(out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(conn)
            return
        conn.out = out[sent:]
        if not conn.out:
            self._close(conn)

    def _close(self, conn: _Conn) -> None:
        if self._conns.pop(conn.sock, None) is None:
            return
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(conn.sock)
        conn.sock.close()


def _response(status: str, headers: list[tuple[str, str]], body: bytes, *,
              send_body: bool = True) -> bytes:
    lines = [f"HTTP/1.1 {status}"]
    lines += [f"{k}: {v}" for k, v in headers if k.lower() not in ("content-length",
                                                                   "connection")]
    lines += [f"Content-Length: {len(body)}", "Connection: close", "", ""]
    return "\r\n".join(lines).encode("latin-1") + (body if send_body else b"")


def _error(code: int, headers: list[tuple[str, str]] | None = None) -> bytes:
    reason = _REASONS[code]
    return _response(f"{code} {reason}", [("Content-Type", "text/plain; charset=utf-8"),
                                          *(headers or [])], f"{reason}\n".encode())


__all__ = ["HEADER_DEADLINE", "MAX_CONNECTIONS", "MAX_REQUEST_BYTES", "MetricsHttpServer"]
