"""The gateway's Modbus TCP server: serve mode (devices' latest values as unit ids) and
the server side of forward mode (requests passed to a device's slave on its line).

One thread (``edgemodbus-serve :PORT``) runs the C loop (csrc/emb_serve.c) with the GIL
released: it accepts masters, frames their requests and answers reads of served devices
from the register image, without Python.  It comes back to Python only for a write to a
served device or a request to a forward unit, which it hands over and goes on serving
the other masters; the answer is posted when the driver's future resolves (on the line's
worker), and that master's connection reads nothing more until then.  The images are
updated by the server's listener on each driver (``driver.subscribe``), one C call per
batch (serve/image.py).

A forwarded request is answered by its timeout counted from its arrival: when it runs
out while the line is still busy (another request's timeout and settle), this thread
answers 0B and the request is dropped from the line's queue, or, already sent, its
reply is dropped (a connection's answer is posted once).  A line with too many jobs
waiting answers exception 06 (server device busy); one connection has at most one
request in the line's queue (csrc/emb_serve.c reads nothing more from it until its
answer was posted).

Freshness (``max_age``): a served device's reads get exception 0B once ``max_age`` has
passed since the slave last answered a read while the device was Running (checked every
``tick``); an item that is Invalid or not read yet gets 0B at any age.  It bounds the
device, not each block: a block that fails is Invalid at once (its items get 0B), and a
block of a slower scan rate than the device's is as old as its own rate makes it.
"""

from __future__ import annotations

import errno
import heapq
import itertools
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from .._ffi.serve import (
    EV_ERROR,
    EV_REQUEST,
    EV_STOP,
    MODE_CACHED,
    MODE_FORWARD,
    MODE_NONE,
    POST_EXCEPTION,
    POST_PDU,
    POST_WRITTEN,
    Request,
    ServerCore,
)
from ..config import DeviceAddressItem, DeviceConfig, validate_items
from ..datatypes import Area, DeviceDriverStatus, ItemStatus
from ..driver import DriverModbusRtu
from ..errors import LineBusyError
from ..line.forward import ForwardFuture
from ..line.jobs import LineWorkerError
from ..poll.listeners import Listener
from ..protocol.forward import (
    GATEWAY_TARGET_FAILED,
    SERVER_DEVICE_BUSY,
    SERVER_DEVICE_FAILURE,
    ForwardRequestError,
    exception_code_for,
)
from .image import ILLEGAL_DATA_VALUE, UnitImage
from .settings import DEFAULT_PENDING_PER_MASTER, ipv4_masks
from .staleness import StaleWatch, stale_limiter

log = logging.getLogger("edgemodbus.serve")

_NEVER_STALE = (1 << 63) - 1
ACCEPT_LOG_INTERVAL = 10.0
"""Seconds between two log lines about accept failures (out of fds or memory): the C
loop pauses accepting 0.05 s doubling to 2 s after each (csrc/emb_serve.c), and counts
them; the server's thread logs what the count grew by at most once per interval."""
_SLAVE_EXCEPTION = re.compile(r"exception 0x([0-9a-f]{2})")


class _Hook(Listener[DriverModbusRtu]):
    """A served unit's subscription to its driver: each batch re-encoded into the unit's
    image.  Inactive once the unit is removed (a delivery under way while it is
    unsubscribed writes nothing)."""

    def __init__(self, image: UnitImage, core: ServerCore, max_age_ns: int | None,
                 watch: StaleWatch) -> None:
        self.image = image
        self.core = core
        self.max_age_ns = max_age_ns
        self.watch = watch
        self.active = True

    def on_changes(self, source: DriverModbusRtu, items: list[DeviceAddressItem]) -> None:
        if not self.active:
            return
        self.core.update(self.image.runs(items))
        if self.max_age_ns is not None and any(it.status is ItemStatus.OK for it in items):
            # the slave just answered: fresh from now (between the server's checks)
            now = self.watch.answered_ns = time.monotonic_ns()
            self.core.set_fresh(self.image.unit, now + self.max_age_ns)


@dataclass(eq=False)
class _Unit:
    unit_id: int
    driver: DriverModbusRtu
    image: UnitImage | None = None  # a served device; None: a forward unit
    hook: _Hook | None = None
    max_age: float | None = None
    timeout: float | None = None  # forward: None is the device's readTimeout
    responses: int = -1
    watch: StaleWatch | None = None  # a served device: its reads answered 0B, and why


class ModbusTcpServer:
    """A Modbus TCP server on ``host:port`` (port 0: any free one, see :attr:`port`)
    with at most ``max_connections`` masters at once (one more is closed at once) and
    an idle timeout (seconds; 0: none); one master (a source address) has at most
    ``max_pending_per_master`` requests waiting for a line across its connections
    (forwards, writes; one more is answered 06).  Add units, then :meth:`start`;
    :meth:`stop` closes every socket and unsubscribes from the drivers."""

    def __init__(self, host: str = "127.0.0.1", port: int = 502, *,
                 max_connections: int = 32, idle_timeout: float = 60.0,
                 tick: float = 0.1, allow_from: Sequence[str] = (),
                 max_pending_per_master: int = DEFAULT_PENDING_PER_MASTER) -> None:
        if max_pending_per_master < 1:
            raise ValueError(f"max_pending_per_master {max_pending_per_master}: must be at "
                             "least 1")
        self.core = ServerCore(host, port, max_connections=max_connections,
                               idle_timeout=idle_timeout)
        try:  # connections from other sources are reset at once (settings.py allowFrom)
            self.core.allow(None, ipv4_masks(allow_from))
        except BaseException:
            self.core.close()
            raise
        self.host = host
        self.port = self.core.port
        self.tick = tick
        self._units: dict[int, _Unit] = {}
        self._lock = threading.Lock()  # the units table
        self._thread: threading.Thread | None = None
        self.writes = 0
        self.write_errors = 0
        self.forwarded = 0
        self._accept_errors_logged = 0  # the C loop's accept_errors when last logged
        self._accept_log_at = 0.0  # the next accept-failure line not before (monotonic)
        self.forward_expired = 0
        self.busy = 0
        self.busy_master = 0  # answered 06: their master had max_pending_per_master waiting
        self.max_pending_per_master = max_pending_per_master
        self._pending: dict[int, int] = {}  # source address -> its requests waiting
        self._stale_log = stale_limiter()
        # forwards waiting for an answer, by deadline (time.monotonic())
        self._deadlines: list[tuple[float, int, Future[bytes]]] = []
        self._seq = itertools.count()

    # -- units -------------------------------------------------------------------------
    def serve_device(self, unit_id: int, driver: DriverModbusRtu, config: DeviceConfig, *,
                     offset: int = 0, max_age: float | None = None,
                     allow_from: Sequence[str] = ()) -> None:
        """Serve ``driver``'s items (as ``config`` defines them) as ``unit_id``, each at
        its own address plus ``offset``; reads after ``max_age`` seconds without a good
        cycle get exception 0B; requests from outside ``allow_from`` (IPv4 networks;
        empty: any) get 0A.  Raises ConfigError for an item outside 0..65535."""
        params = config.effective_parameters()
        parsed = validate_items(list(config.address_list), params)
        code = config.organization.device_code or f"slave{params.slave_id}"
        image = UnitImage(unit_id, code, parsed, offset)
        self.remove_unit(unit_id)
        core = self.core
        core.allow(unit_id, ipv4_masks(allow_from))
        core.set_unit(unit_id, MODE_CACHED, image.spans())
        core.update(image.mapping())
        core.set_fresh(unit_id, 0 if max_age is not None else _NEVER_STALE)
        watch = StaleWatch(unit_id, code, driver, max_age)
        hook = _Hook(image, core, None if max_age is None else int(max_age * 1e9), watch)
        driver.subscribe(hook)
        core.update(image.seed(driver.snapshot()["items"]))
        unit = _Unit(unit_id, driver, image, hook, max_age, watch=watch)
        with self._lock:
            self._units[unit_id] = unit
        self._refresh(unit, time.monotonic_ns())

    def forward_device(self, unit_id: int, driver: DriverModbusRtu,
                       timeout: float | None = None, *,
                       allow_from: Sequence[str] = ()) -> None:
        """Pass every request to ``unit_id`` to ``driver``'s slave (``driver.forward``)
        with ``timeout`` seconds for its reply (None: the device's readTimeout); those
        from outside ``allow_from`` (IPv4 networks; empty: any) get 0A."""
        self.remove_unit(unit_id)
        self.core.allow(unit_id, ipv4_masks(allow_from))
        self.core.set_unit(unit_id, MODE_FORWARD)
        with self._lock:
            self._units[unit_id] = _Unit(unit_id, driver, timeout=timeout)

    def remove_unit(self, unit_id: int) -> None:
        """Stop serving ``unit_id`` (exception 0A from now on)."""
        with self._lock:
            unit = self._units.pop(unit_id, None)
        if unit is None:
            return
        self.core.set_unit(unit_id, MODE_NONE)
        self.core.allow(unit_id, ())
        _unhook(unit)

    def units(self) -> dict[int, str]:
        """unit id -> what it is ("serve DEVICE" or "forward DEVICE")."""
        with self._lock:
            return {u.unit_id: (f"serve {u.image.device}" if u.image is not None
                                else "forward") for u in self._units.values()}

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> ModbusTcpServer:
        thread = threading.Thread(target=self._run, name=f"edgemodbus-serve :{self.port}",
                                  daemon=True)
        self._thread = thread
        thread.start()
        log.info("Modbus TCP server on %s:%d (%d units)", self.host, self.port,
                 len(self._units))
        return self

    def stop(self) -> None:
        """Stop the thread, close every connection and the listening socket, and take
        the units' listeners off their drivers.  Answers still pending are dropped."""
        self.core.stop()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:
            units, self._units = list(self._units.values()), {}
        for unit in units:
            _unhook(unit)
        self.core.close()

    def stats(self) -> dict[str, Any]:
        """The server's counters (camelCase keys); ``staleReplies``: per served unit id,
        its reads answered 0B by reason (serve/staleness.py)."""
        c = self.core.counters()
        with self._lock:
            units = list(self._units.values())
        return {
            "listen": f"{self.host}:{self.port}",
            "connections": self.core.open_connections(),
            "accepted": c.accepted, "refused": c.refused, "closedIdle": c.closed_idle,
            "closedBad": c.closed_bad, "closedByPeer": c.closed_peer,
            "requests": c.requests, "cachedReplies": c.cached_replies,
            "exceptions": c.exceptions, "writes": self.writes,
            "writeErrors": self.write_errors, "forwarded": self.forwarded,
            "acceptErrors": c.accept_errors,
            "refusedSource": c.refused_source, "refusedUnit": c.refused_unit,
            "forwardExpired": self.forward_expired, "busy": self.busy,
            "busyMaster": self.busy_master,
            "staleReplies": {u.unit_id: dict(u.watch.counts) for u in units
                             if u.watch is not None},
        }

    # -- the server's thread -----------------------------------------------------------
    def _run(self) -> None:
        core = self.core
        tick = int(self.tick * 1e9)
        next_check = 0
        while True:
            now = time.monotonic_ns()
            if now >= next_check:
                next_check = now + tick
                with self._lock:
                    units = list(self._units.values())
                for unit in units:
                    self._refresh(unit, now)
                    if unit.watch is not None:
                        unit.watch.look(core.stale(unit.unit_id), now, self._stale_log)
            event = core.run(min(next_check, self._expire()))
            self._log_accept_errors()
            if event == EV_STOP:
                return
            if event == EV_REQUEST:
                request = core.request()
                try:
                    self._handle(request)
                except Exception:
                    log.exception("serve: request %s failed", request.adu.hex(" "))
                    self._answer(request, SERVER_DEVICE_FAILURE)
            elif event == EV_ERROR:
                log.error("serve: poll() failed; retrying in %.1f s", self.tick)
                time.sleep(self.tick)

    def _log_accept_errors(self) -> None:
        """One line per :data:`ACCEPT_LOG_INTERVAL` while accept fails (EMFILE...)."""
        now = time.monotonic()
        if now < self._accept_log_at:
            return
        c = self.core.counters()
        failed = c.accept_errors - self._accept_errors_logged
        if failed <= 0:
            return
        self._accept_errors_logged = c.accept_errors
        self._accept_log_at = now + ACCEPT_LOG_INTERVAL
        name = errno.errorcode.get(c.accept_errno, str(c.accept_errno))
        log.warning("serve :%d: accept failed %d times (%s: %s); accepting pauses 0.05 s "
                    "doubling to 2 s, new masters wait in the backlog (next report in "
                    "%.0f s at most)", self.port, failed, name, os.strerror(c.accept_errno),
                    ACCEPT_LOG_INTERVAL)

    def _expire(self) -> int:
        """Answer 0B to the forwards whose timeout ran out (cancelling them: a queued
        one is not sent); returns the next deadline (``time.monotonic_ns``)."""
        deadlines = self._deadlines
        while True:
            with self._lock:
                if not deadlines:
                    return _NEVER_STALE
                deadline, _, future = deadlines[0]
                if future.done():
                    heapq.heappop(deadlines)
                    continue
                if deadline > time.monotonic():
                    return int(deadline * 1e9)
                heapq.heappop(deadlines)
            if future.cancel():  # its done-callback answers 0B
                self.forward_expired += 1

    def _refresh(self, unit: _Unit, now: int) -> None:
        """A unit with a max age stays fresh for max_age past each check that saw the
        slave answer (its ``responses`` grew) while the device was Running."""
        if unit.max_age is None or unit.watch is None:
            return
        driver = unit.driver
        stats = driver.stats()
        unit.watch.lag_seen(stats, now)
        answered = int(stats.get("responses", 0))
        if answered != unit.responses and driver.device_driver_status is DeviceDriverStatus.RUNNING:
            # (the first look, when the unit is added, trusts a device Running with
            # answers: its items are as fresh as its last cycle)
            unit.watch.answered_ns = now
            self.core.set_fresh(unit.unit_id, now + int(unit.max_age * 1e9))
        unit.responses = answered

    def _handle(self, request: Request) -> None:
        adu = request.adu
        with self._lock:
            unit = self._units.get(adu[6])
        if unit is None:  # removed meanwhile
            self._answer(request, 0x0A)
            return
        src = request.src
        with self._lock:
            waiting = self._pending.get(src, 0)
            if waiting < self.max_pending_per_master:
                self._pending[src] = waiting + 1
        if waiting >= self.max_pending_per_master:  # other masters keep their share
            self.busy_master += 1
            self._answer(request, SERVER_DEVICE_BUSY)
            return
        future: Future[Any] | None = None
        release: Callable[[object], None] = lambda _: self._release(src)  # noqa: E731
        try:  # (released before the answer is posted: the master's next request counts it)
            if unit.image is None:
                future = self._forward(unit, request, release)
            else:
                future = self._write(unit, unit.image, request, release)
        finally:
            if future is None:
                self._release(src)

    def _release(self, src: int) -> None:
        """A request of the master at ``src`` was answered: one less waiting."""
        with self._lock:
            left = self._pending.pop(src, 1) - 1
            if left > 0:
                self._pending[src] = left

    def _forward(self, unit: _Unit, request: Request,
                 release: Callable[[object], None]) -> Future[bytes] | None:
        """Hand a request to a forward unit's line; its future (None: answered now)."""
        pdu = request.adu[7:]
        self.forwarded += 1
        try:
            future = unit.driver.forward(pdu, unit.timeout)
        except ForwardRequestError as exc:
            self._answer(request, exc.exception_code)
            return None

        def done(f: Future[bytes]) -> None:
            if f.cancelled():
                self._answer(request, GATEWAY_TARGET_FAILED)
                return
            exc = f.exception()
            if exc is not None:
                self.busy += isinstance(exc, LineBusyError)
                # the line's worker failed with the request queued: its target did not
                # answer (0B, issue #25), not a path that is down (0A)
                self._answer(request, GATEWAY_TARGET_FAILED if isinstance(
                    exc, LineWorkerError) else exception_code_for(exc))
            else:
                self.core.post(request.conn, request.gen, POST_PDU, f.result())

        if isinstance(future, ForwardFuture) and not future.done():
            with self._lock:
                heapq.heappush(self._deadlines, (future.deadline, next(self._seq), future))
        future.add_done_callback(release)
        future.add_done_callback(done)
        return future

    def _write(self, unit: _Unit, image: UnitImage, request: Request,
               release: Callable[[object], None]) -> Future[tuple[bool, str | None]] | None:
        """A write (FC05/06/0F/10; csrc/emb_serve.c checked its form and addresses) to
        a served device: through write_addresses, answered once the slave confirmed;
        its future (None: answered now)."""
        adu = request.adu
        fc, address = adu[7], int.from_bytes(adu[8:10], "big")
        if fc == 0x05:
            area, words = Area.COIL, [1 if adu[10] else 0]
        elif fc == 0x06:
            area, words = Area.HOLDING_REGISTER, [int.from_bytes(adu[10:12], "big")]
        elif fc == 0x0F:
            qty = int.from_bytes(adu[10:12], "big")
            area, words = Area.COIL, [(adu[13 + k // 8] >> (k % 8)) & 1 for k in range(qty)]
        else:
            qty = int.from_bytes(adu[10:12], "big")
            area = Area.HOLDING_REGISTER
            words = [int.from_bytes(adu[13 + 2 * k:15 + 2 * k], "big") for k in range(qty)]
        writes = image.write_values(area, address, words)
        self.writes += 1
        if isinstance(writes, int):
            self.write_errors += 1
            self._answer(request, writes)
            return None
        try:
            future = unit.driver.submit_writes(writes)
        except ValueError:
            self.write_errors += 1
            self._answer(request, ILLEGAL_DATA_VALUE)
            return None
        except Exception as exc:
            self.write_errors += 1
            self._answer(request, exception_code_for(exc))
            return None

        def done(f: Future[tuple[bool, str | None]]) -> None:
            if f.cancelled() or f.exception() is not None:
                self.write_errors += 1
                busy = not f.cancelled() and isinstance(f.exception(), LineBusyError)
                self.busy += busy
                self._answer(request, SERVER_DEVICE_BUSY if busy else GATEWAY_TARGET_FAILED)
                return
            ok, why = f.result()
            if ok:
                self.core.post(request.conn, request.gen, POST_WRITTEN, b"")
                return
            self.write_errors += 1
            log.info("serve: unit %d: write %s refused: %s", unit.unit_id,
                     ", ".join(name for name, _ in writes), why)
            self._answer(request, write_exception_code(why or ""))

        future.add_done_callback(release)
        future.add_done_callback(done)
        return future

    def _answer(self, request: Request, code: int) -> None:
        self.core.post(request.conn, request.gen, POST_EXCEPTION, bytes((code,)))


def write_exception_code(why: str) -> int:
    """The exception code for a write the driver reports as failed with ``why``: the
    slave's own exception 01..04 as it sent it (errors.py writes them "exception 0xNN"),
    04 for another exception code, 0B for anything else (no reply, a bad reply, the
    link down: the gateway's target did not answer)."""
    found = _SLAVE_EXCEPTION.search(why)
    if found is None:
        return GATEWAY_TARGET_FAILED
    code = int(found.group(1), 16)
    return code if 1 <= code <= 4 else SERVER_DEVICE_FAILURE


def _unhook(unit: _Unit) -> None:
    hook = unit.hook
    if hook is None:
        return
    hook.active = False
    unit.driver.unsubscribe(hook)
