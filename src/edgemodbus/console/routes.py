"""The console's pages and API (aiohttp handlers), behind one middleware that checks
the Host header, the login and CSRF (auth.py) before any handler runs.

API (JSON; every change is a POST with ``Content-Type: application/json``, the
``X-CSRF-Token`` of the session, and an Origin, when the browser sends one, of this
server):
  GET  /api/session                  whether a login is needed, who, the CSRF token
  POST /api/login {user, password} | {token};  POST /api/logout
  GET  /api/overview                 devices (status, last error, cycles, counters), DTU ports
  GET  /api/devices/{code}/tags      every tag of a device (the tag page's table)
  GET  /api/devices/{code}/events    server-sent events: changed tags, status (feed.py)
  POST /api/devices/{code}/write     {name, value} -> {ok, error}: confirmed by the slave
  POST /api/devices/{code}/action    {name, params} -> {ok, error}
  GET  /api/descriptor               driver_descriptor() (the device form is made from it)
  POST /api/commission/check         {document} -> {ok, problems, plan}
  POST /api/commission/save          {fileName, document, overwrite} -> saved, reload asked
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
import time
from collections.abc import Awaitable, Callable
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import web

from ..codec import json_bytes
from ..config import DeviceConfig
from ..descriptor import driver_descriptor
from ..driver import DriverModbusRtu
from .auth import (
    CSRF_HEADER,
    SESSION_COOKIE,
    PasswordHash,
    Sessions,
    hash_password,
    host_allowed,
    origin_allowed,
    token_matches,
)
from .feed import MIN_INTERVAL, Feeds, Stream
from .host import ConsoleHost, HostDevice
from .settings import ConsoleSettings
from .views import (
    check_device,
    check_file_name,
    device_row,
    plan_preview,
    save_device,
    tag_rows,
    writable_names,
)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
STATIC = {"index.html": "text/html", "console.css": "text/css",
          "console.js": "text/javascript"}
KEEPALIVE = 15.0  # seconds between two comments on an idle stream (proxies, dead peers)
WRITE_SECONDS = 10.0  # a stream's write must go out by then, else the reader is dropped
LOGIN_FAILURE_DELAY = 1.0  # seconds a failed login waits before it is answered
OPEN = frozenset({"/api/session", "/api/login"})
MAX_BODY = 4 << 20  # bytes of a request body: a device file of 10,000 tags is ~1.5 MB


def _json(data: Any, status: int = 200) -> web.Response:
    return web.Response(body=json_bytes(data), status=status, content_type="application/json")


def _error(status: int, message: str, **extra: Any) -> web.Response:
    return _json({"ok": False, "error": message, **extra}, status)


class Routes:
    """The handlers and what they share (the host, the feeds, the sessions)."""

    def __init__(self, settings: ConsoleSettings, host: ConsoleHost, feeds: Feeds,
                 sessions: Sessions, guard: Any, port: Callable[[], int]) -> None:
        self.settings = settings
        self.host = host
        self.feeds = feeds
        self.sessions = sessions
        self.guard = guard
        self.port = port
        self.csrf = Sessions().create("")[1].csrf  # no credentials: one token per server
        self.users = {u.name: PasswordHash.parse(u.password_hash) for u in settings.users}
        self.decoy = PasswordHash.parse(hash_password(secrets.token_urlsafe(16)))
        self.login_lock = asyncio.Lock()
        self.token = (settings.token.get_secret_value()
                      if settings.token is not None else None)
        self.rates: dict[str, tuple[float, int, float]] = {}  # code -> time, cycles, rate
        self.writable: dict[int, tuple[DeviceConfig, frozenset[str]]] = {}
        self.stopping = asyncio.Event()

    def install(self, app: web.Application) -> None:
        app.router.add_get("/", self.index)
        app.router.add_get("/static/{name}", self.static)
        app.router.add_get("/api/session", self.session)
        app.router.add_post("/api/login", self.login)
        app.router.add_post("/api/logout", self.logout)
        app.router.add_get("/api/overview", self.overview)
        app.router.add_get("/api/devices/{code}/tags", self.tags)
        app.router.add_get("/api/devices/{code}/events", self.events)
        app.router.add_post("/api/devices/{code}/write", self.write)
        app.router.add_post("/api/devices/{code}/action", self.action)
        app.router.add_get("/api/descriptor", self.descriptor)
        app.router.add_post("/api/commission/check", self.check)
        app.router.add_post("/api/commission/save", self.save)

    def closing(self) -> None:
        """The server stops: end the streams (their handlers return)."""
        self.stopping.set()

    # -- the checks before every handler ------------------------------------------------
    def who(self, request: web.Request) -> tuple[str, str | None] | None:
        """(user, the CSRF token to expect or None for a bearer token), or None."""
        auth = request.headers.get("Authorization", "")
        if auth.startswith("Bearer ") and self.token is not None:
            return ("token", None) if token_matches(auth[7:], self.token) else None
        session = self.sessions.get(request.cookies.get(SESSION_COOKIE))
        if session is not None:
            return session.user, session.csrf
        if not self.settings.has_credentials:
            return "", self.csrf
        return None

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.transport is not None:
            self.guard.seen.add(id(request.transport))
        if not host_allowed(request.host, self.settings.host, self.port()):
            return _error(421, f"Host {request.host!r}: this console answers to "
                          "127.0.0.1 or localhost only (it listens on loopback)")
        path = request.path
        if path.startswith("/api/"):
            who = self.who(request)
            if who is None and path not in OPEN:
                return _error(401, "log in first (console.token or console.users)")
            if request.method != "GET":
                if not origin_allowed(request.headers.get("Origin"), request.host):
                    return _error(403, f"Origin {request.headers.get('Origin')!r} is not "
                                  "this console: refused (CSRF)")
                if request.content_type != "application/json":
                    return _error(415, f"Content-Type {request.content_type!r}: "
                                  "application/json only")
                if path != "/api/login" and who is not None and who[1] is not None and \
                        request.headers.get(CSRF_HEADER) != who[1]:
                    return _error(403, f"missing or wrong {CSRF_HEADER} header (CSRF)")
        try:
            response = await handler(request)
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"request body over {MAX_BODY:,} bytes")
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("X-Frame-Options", "DENY")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        response.headers.setdefault("Content-Security-Policy",
                                    "default-src 'self'; frame-ancestors 'none'")
        if path.startswith("/api/"):
            response.headers.setdefault("Cache-Control", "no-store")
        return response

    async def body(self, request: web.Request) -> dict[str, Any]:
        """The request's JSON object; HTTPBadRequest (as JSON) says what is wrong."""
        try:
            data = await request.json(loads=json.loads)
        except (ValueError, UnicodeDecodeError) as exc:
            raise web.HTTPBadRequest(text=json.dumps({"ok": False, "error":
                                     f"body is not JSON: {exc}"}),
                                     content_type="application/json") from None
        if not isinstance(data, dict):
            raise web.HTTPBadRequest(text=json.dumps({"ok": False, "error":
                                     "body must be a JSON object"}),
                                     content_type="application/json")
        return data

    def device(self, request: web.Request) -> HostDevice:
        code = request.match_info["code"]
        for dev in tuple(self.host.devices.values()):
            if dev.code == code:
                return dev
        raise web.HTTPNotFound(text=json.dumps({"ok": False, "error":
                               f"device {code!r}: no such device in the gateway"}),
                               content_type="application/json")

    # -- pages --------------------------------------------------------------------------
    async def index(self, request: web.Request) -> web.StreamResponse:
        return self._file("index.html")

    async def static(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if name not in STATIC:
            raise web.HTTPNotFound()
        return self._file(name)

    def _file(self, name: str) -> web.Response:
        data = resources.files(__package__).joinpath("static").joinpath(name).read_bytes()
        return web.Response(body=data, content_type=STATIC[name], charset="utf-8",
                            headers={"Cache-Control": "no-cache"})

    # -- session ------------------------------------------------------------------------
    async def session(self, request: web.Request) -> web.StreamResponse:
        who = self.who(request)
        return _json({"required": self.settings.has_credentials,
                      "user": who[0] if who is not None else None,
                      "csrf": who[1] if who is not None else None,
                      "gatewayId": self.host.gateway_id})

    async def login(self, request: web.Request) -> web.StreamResponse:
        data = await self.body(request)
        user = data.get("user")
        password, token = data.get("password"), data.get("token")
        ok = False
        # one login at a time, a failed one held for a second: guessing is paced, and a
        # flood of logins costs at most one scrypt (~50 ms of a core) per second
        async with self.login_lock:
            if isinstance(token, str) and self.token is not None:
                ok, user = token_matches(token, self.token), "token"
            elif isinstance(user, str) and isinstance(password, str):
                # an unknown user costs the same scrypt (no timing tells who exists)
                known = self.users.get(user, self.decoy)
                ok = await asyncio.get_running_loop().run_in_executor(
                    None, known.matches, password) and user in self.users
            if not ok:
                await asyncio.sleep(LOGIN_FAILURE_DELAY)
        if not ok:
            return _error(401, "wrong user name, password or token")
        sid, session = self.sessions.create(str(user))
        response = _json({"ok": True, "user": user, "csrf": session.csrf})
        response.set_cookie(SESSION_COOKIE, sid, httponly=True, samesite="Strict",
                            secure=self.settings.scheme == "https", path="/")
        return response

    async def logout(self, request: web.Request) -> web.StreamResponse:
        self.sessions.drop(request.cookies.get(SESSION_COOKIE))
        response = _json({"ok": True})
        response.del_cookie(SESSION_COOKIE, path="/")
        return response

    # -- overview -----------------------------------------------------------------------
    async def overview(self, request: web.Request) -> web.StreamResponse:
        now = time.monotonic()
        rows = []
        for dev in sorted(tuple(self.host.devices.values()), key=lambda d: d.code):
            row = device_row(dev)
            then, cycles, rate = self.rates.get(dev.code, (now, row["cycles"], 0.0))
            if now - then >= 0.5:  # cycles per second since the last sample
                rate = max(0, row["cycles"] - cycles) / (now - then)
                then, cycles = now, row["cycles"]
            self.rates[dev.code] = (then, cycles, rate)
            row["cycleRate"] = rate
            rows.append(row)
        registry = DriverModbusRtu.dtu_registry
        return _json({"gatewayId": self.host.gateway_id, "devices": rows,
                      "listeners": registry.stats(), "dtus": registry.held()})

    # -- a device's tags ----------------------------------------------------------------
    def _writable(self, dev: HostDevice) -> frozenset[str]:
        known = self.writable.get(id(dev.driver))
        if known is None or known[0] is not dev.cfg:
            known = (dev.cfg, writable_names(dev.cfg))
            self.writable[id(dev.driver)] = known
        return known[1]

    async def tags(self, request: web.Request) -> web.StreamResponse:
        dev = self.device(request)
        return _json({"code": dev.code, "status": dev.driver.device_driver_status.value,
                      "serverTime": time.time(),
                      "actions": [a.name for a in dev.driver.actions],
                      "tags": tag_rows(dev.driver, self._writable(dev))})

    async def events(self, request: web.Request) -> web.StreamResponse:
        dev = self.device(request)
        if self.feeds.streams >= self.settings.max_streams:
            return _error(503, f"{self.settings.max_streams} live streams are open "
                          "(console.maxStreams): close a tag page, or raise it")
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                               "Cache-Control": "no-store",
                                               "X-Accel-Buffering": "no"})
        await response.prepare(request)
        stream = self.feeds.open(dev.driver)
        try:
            # subscribed: the page loads its table now, so nothing falls between the two
            await self._send(response, b"retry: 2000\n\nevent: ready\ndata: {}\n\n")
            await self._pump(dev, stream, response)
        except (ConnectionError, asyncio.TimeoutError):
            pass  # the reader went away or stalled: drop it
        finally:
            self.feeds.close(stream)
        return response

    async def _pump(self, dev: HostDevice, stream: Stream, response: web.StreamResponse
                    ) -> None:
        """Send the stream's events until the reader leaves, the device is replaced
        (a reload: the page reloads its table), or the console stops."""
        stopping = asyncio.ensure_future(self.stopping.wait())
        try:
            while not self.stopping.is_set():
                ready = asyncio.ensure_future(stream.ready.wait())
                done, _ = await asyncio.wait({ready, stopping}, timeout=KEEPALIVE,
                                             return_when=asyncio.FIRST_COMPLETED)
                if not ready.done():
                    ready.cancel()
                if stopping in done:
                    return
                if ready not in done:  # idle: is the device still the one we watch?
                    if not any(d.driver is dev.driver for d in self.host.devices.values()):
                        await self._send(response, b"event: reload\ndata: {}\n\n")
                        return
                    await self._send(response, b": keep-alive\n\n")
                    continue
                event = stream.take()
                await self._send(response, b"data: " + json_bytes(event) + b"\n\n")
                await asyncio.sleep(MIN_INTERVAL)  # what comes meanwhile goes in one event
        finally:
            stopping.cancel()

    async def _send(self, response: web.StreamResponse, data: bytes) -> None:
        await asyncio.wait_for(response.write(data), WRITE_SECONDS)

    # -- writes and actions -------------------------------------------------------------
    async def write(self, request: web.Request) -> web.StreamResponse:
        dev = self.device(request)
        data = await self.body(request)
        name, value = data.get("name"), data.get("value")
        if not isinstance(name, str):
            return _error(400, f"name {name!r}: give the tag's name (a string)")
        if name not in self._writable(dev):
            known = any(i.name == name for i in dev.driver.address_items)
            return _error(400, f"tag {name!r}: " + ("not writable (a discrete input or an "
                          "input register)" if known else "no such tag on this device"))
        ok, error = await dev.driver.write_address_async(name, value)
        return _json({"ok": ok, "error": error, "name": name, "value": value})

    async def action(self, request: web.Request) -> web.StreamResponse:
        dev = self.device(request)
        data = await self.body(request)
        name, params = data.get("name"), data.get("params") or {}
        if not isinstance(name, str) or not isinstance(params, dict):
            return _error(400, "give name (the action's, a string) and params (an object)")
        ok, error = await dev.driver.run_action_async(name, params)
        return _json({"ok": ok, "error": error, "name": name})

    # -- commissioning ------------------------------------------------------------------
    async def descriptor(self, request: web.Request) -> web.StreamResponse:
        return _json(driver_descriptor())

    async def check(self, request: web.Request) -> web.StreamResponse:
        data = await self.body(request)
        cfg, problems = check_device(data.get("document"))
        if cfg is None:
            return _json({"ok": False, "problems": problems})
        return _json({"ok": True, "problems": [], "plan": plan_preview(cfg)})

    async def save(self, request: web.Request) -> web.StreamResponse:
        data = await self.body(request)
        folder: Path = self.host.dir
        try:
            name = check_file_name(data.get("fileName"), self.host.gateway_file)
        except ValueError as exc:
            return _json({"ok": False, "problems": [{"path": "fileName", "value":
                          data.get("fileName"), "message": str(exc), "text": str(exc)}]})
        document = data.get("document")
        cfg, problems = check_device(document)
        if cfg is None or not isinstance(document, dict):
            return _json({"ok": False, "problems": problems})
        try:
            path = save_device(folder, name, document, overwrite=data.get("overwrite") is True)
        except FileExistsError as exc:
            return _json({"ok": False, "problems": [{"path": "fileName", "value": name,
                          "message": str(exc), "text": str(exc)}]})
        except OSError as exc:
            return _error(500, f"cannot write {name}: {exc.strerror or exc}")
        with contextlib.suppress(Exception):
            self.host.request_reload()
        code = cfg.organization.device_code or Path(name).stem
        return _json({"ok": True, "file": path.name, "code": code})


__all__ = ["Routes"]
