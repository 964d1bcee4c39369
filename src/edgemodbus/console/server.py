"""The console's HTTP server: aiohttp on a thread of its own (``edgemodbus-console``).

aiohttp, not an ASGI framework with uvicorn: one maintained package that is both the
server and the framework, with server-sent events as a plain streamed response, and a
low-level server (``web.Server``) whose protocol factory we wrap to bound what a peer may
cost (docs/fault-checklist.md, "console"):

* connections open at once are capped (``maxConnections``): one more is closed at accept;
* a connection must send a complete request head within :data:`HEAD_SECONDS` (slow
  headers), idle keep-alive connections close after :data:`KEEPALIVE_SECONDS`;
* request heads are bounded by aiohttp's line and field limits, bodies by
  routes.py's MAX_BODY (a large device file) -> 413;
* live streams are capped (``maxStreams``, 503 past it), each writes with a deadline
  (a reader that stalls is dropped) and holds only the latest row of each tag;
* accept failing for want of fds (EMFILE) pauses accepting (asyncio's own back-off:
  the listening socket leaves the selector for a second, no busy loop), counted
  (``loopErrors``) and logged through line/log_limit.py (one line per 10 s).

The socket is bound on the caller's thread, so a port in use is an OSError from
:meth:`ConsoleServer.start`, as for the metrics exporter.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
from typing import Any

from aiohttp import web

from ..line.log_limit import LogLimiter
from .auth import Sessions
from .feed import Feeds
from .host import ConsoleHost
from .routes import MAX_BODY, Routes
from .settings import ConsoleSettings, console_key

log = logging.getLogger("edgemodbus.console")

HEAD_SECONDS = 10.0  # a connection's first request head must be in by then
KEEPALIVE_SECONDS = 15.0
MAX_LINE = 8190  # request line and each header field, bytes (aiohttp's defaults)


class _Guard:
    """Counts the open connections and remembers which have sent a request."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.open = 0
        self.refused = 0
        self.slow_heads = 0
        self.seen: set[int] = set()  # id() of the transports that sent a request head


class _Guarded(asyncio.Protocol):
    """aiohttp's request handler (the inner protocol) behind the guard's checks."""

    def __init__(self, inner: Any, guard: _Guard, loop: asyncio.AbstractEventLoop) -> None:
        self.inner = inner
        self.guard = guard
        self.loop = loop
        self.transport: asyncio.BaseTransport | None = None
        self.timer: asyncio.TimerHandle | None = None
        self.admitted = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        guard = self.guard
        if guard.open >= guard.cap:
            guard.refused += 1
            with contextlib.suppress(Exception):
                transport.abort()  # type: ignore[attr-defined]
            return
        guard.open += 1
        self.admitted = True
        self.transport = transport
        self.timer = self.loop.call_later(HEAD_SECONDS, self._head_deadline)
        self.inner.connection_made(transport)

    def _head_deadline(self) -> None:
        transport = self.transport
        if transport is not None and id(transport) not in self.guard.seen:
            self.guard.slow_heads += 1
            transport.close()

    def data_received(self, data: bytes) -> None:
        if self.admitted:
            self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.admitted else None

    def pause_writing(self) -> None:
        if self.admitted:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.admitted:
            self.inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.admitted:
            return
        self.admitted = False
        self.guard.open -= 1
        if self.timer is not None:
            self.timer.cancel()
        if self.transport is not None:
            self.guard.seen.discard(id(self.transport))
        self.inner.connection_lost(exc)


class ConsoleServer:
    """``start()`` (binds, or OSError naming the address), ``port``, ``stop()``."""

    def __init__(self, settings: ConsoleSettings, host: ConsoleHost) -> None:
        self.settings = settings
        self.host = host
        self.guard = _Guard(settings.max_connections)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self.routes: Routes | None = None
        self.port = 0
        self.key = console_key(settings)  # what it was made from, TLS file contents too
        self.loop_errors = 0
        self._logs = LogLimiter(log, interval=10.0, burst=1)

    @property
    def url(self) -> str:
        host = self.settings.host
        if ":" in host:
            host = f"[{host}]"
        return f"{self.settings.scheme}://{host}:{self.port}/"

    def start(self) -> ConsoleServer:
        settings = self.settings
        context = self._ssl_context()
        infos = socket.getaddrinfo(settings.host, settings.port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_PASSIVE)
        family, kind, proto, _, address = infos[0]
        sock = socket.socket(family, kind, proto)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(address)
            sock.listen(128)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"console: cannot listen on {settings.host}:"
                          f"{settings.port}: {exc.strerror or exc}") from None
        self._sock = sock
        self.port = sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, args=(sock, context),
                                        name="edgemodbus-console", daemon=True)
        self._thread.start()
        self._started.wait(30.0)
        if self._error is not None:
            self.stop()
            raise OSError(f"console: cannot start: {self._error}")
        log.info("console on %s", self.url)
        return self

    def _ssl_context(self) -> ssl.SSLContext | None:
        tls = self.settings.tls
        if tls is None or not tls.enabled:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        context.load_cert_chain(tls.cert_file, tls.key_file)
        return context

    def _on_loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """asyncio's errors of the loop (an accept failing for want of fds: asyncio takes
        the listening socket out for a second): counted, logged through the limiter, one
        line each (no traceback: it is the machine's state, not a bug of ours)."""
        self.loop_errors += 1
        exc = context.get("exception")
        self._logs.event(logging.WARNING, "console loop errors", "console", "console: %s%s",
                         context.get("message", "error"), f" ({exc})" if exc else "")
        self._logs.flush()

    def _run(self, sock: socket.socket, context: ssl.SSLContext | None) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        loop.set_exception_handler(self._on_loop_error)
        try:
            runner, server = loop.run_until_complete(self._serve(loop, sock, context))
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._started.set()
            loop.close()
            return
        self._started.set()
        try:
            loop.run_forever()
        finally:
            server.close()
            if self.routes is not None:
                self.routes.closing()
            loop.run_until_complete(runner.shutdown())
            loop.run_until_complete(runner.cleanup())
            tasks = asyncio.all_tasks(loop)
            for task in tasks:
                task.cancel()
            if tasks:
                loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_default_executor())  # login's scrypt
            loop.close()
            self._logs.flush(force=True)

    async def _serve(self, loop: asyncio.AbstractEventLoop, sock: socket.socket,
                     context: ssl.SSLContext | None) -> tuple[web.AppRunner, asyncio.Server]:
        routes = Routes(self.settings, self.host, Feeds(loop), Sessions(), self.guard,
                        lambda: self.port)
        self.routes = routes
        app = web.Application(client_max_size=MAX_BODY,
                              middlewares=[routes.middleware])
        routes.install(app)
        runner = web.AppRunner(app, handle_signals=False, access_log=None,
                               keepalive_timeout=KEEPALIVE_SECONDS, max_line_size=MAX_LINE,
                               max_field_size=MAX_LINE, shutdown_timeout=1.0,
                               handler_cancellation=True)  # a browser that left ends
        # its stream at once (the feed unsubscribed), not at the next keep-alive write
        await runner.setup()
        inner = runner.server
        if inner is None:
            raise RuntimeError("aiohttp's runner has no server after setup()")
        guard = self.guard
        tls: dict[str, Any] = ({} if context is None else
                               {"ssl": context, "ssl_handshake_timeout": HEAD_SECONDS})
        server = await loop.create_server(lambda: _Guarded(inner(), guard, loop), sock=sock,
                                          **tls)
        return runner, server

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
            thread.join(10.0)
        self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def stats(self) -> dict[str, int]:
        """Connections open, refused at the cap, closed for a slow head; streams and
        subscribed feeds."""
        routes = self.routes
        return {"connections": self.guard.open, "refused": self.guard.refused,
                "slowHeads": self.guard.slow_heads, "loopErrors": self.loop_errors,
                "streams": routes.feeds.streams if routes is not None else 0,
                "subscribed": routes.feeds.subscribed if routes is not None else 0}


__all__ = ["ConsoleServer"]
