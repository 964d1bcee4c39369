"""One line (a serial port, a TCP endpoint, or a DTU behind a listener) served by one
worker thread.

The worker thread creates, uses and frees the line's libmodbus context: libmodbus
contexts are not thread-safe.  Other threads reach the line through a queue
(:meth:`LineWorker.submit` and the request helpers, which return
``concurrent.futures.Future`` objects), and pollers (the driver's devices) are called on
the worker when they are due.  Queued requests (writes) run before the next poll step, so
they jump ahead of reads.  The link itself (:mod:`edgemodbus.line.link`) settles the line
after timeouts and drains it after other errors.
"""

from __future__ import annotations

import logging
import operator
import os
import queue
import random
import select
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from .._ffi.engine import (
    EV_CYCLE,
    EV_ERROR,
    EV_FAILED,
    EV_INPUT,
    EV_WAKE,
    EngineDevice,
    LineCounters,
    Waker,
)
from ..datatypes import Area
from ..errors import (
    ModbusConnectionError,
    ModbusError,
)
from ..stats import LineStats
from .connect import open_link
from .endpoint import DtuEndpoint, Endpoint, LineTiming
from .forward import forward_future
from .link import Link

log = logging.getLogger("edgemodbus.line")
T = TypeVar("T")

_IDLE_SLICE = 0.05  # links with unsolicited frames: longest wait before checking the queue
_MAX_IDLE = 3600.0  # a poller due "never" (report-only) still gets an idle step per hour
_DUE = operator.attrgetter("due")


class Poller(Protocol):
    """What the line worker runs: the driver's device polling.  On a link with an
    engine the engine runs the passes over :attr:`device` and calls the poller only
    for what needs Python; otherwise the worker calls :meth:`poll_step` when due."""

    device: EngineDevice
    """The poller's plan and schedule as the engine runs them."""

    @property
    def due(self) -> float:
        """``time.monotonic()`` of the next step (read by the worker on every step)."""
        ...

    def poll_step(self, link: Link) -> None:
        """Do one request (one block read) on the worker thread."""
        ...

    def engine_cycle(self) -> None:
        """The engine ended a pass of this poller that Python must see."""
        ...

    def engine_failed(self, link: Link, err: int) -> None:
        """A read of the engine's pass failed with errno ``err``."""
        ...

    def take_results(self) -> None:
        """Store the results of the blocks the engine read so far in this pass."""
        ...


    def link_changed(self, up: bool, reason: str | None) -> None:
        """The line went up or down (called on the worker thread)."""
        ...


class Connector(Protocol):
    """How a line worker gets its link, for endpoints it cannot open itself (a DTU that
    dials in: the listener hands its socket over)."""

    def open(self, line: LineWorker) -> Link:
        """Return an open link, or raise :class:`ModbusConnectionError` (worker thread)."""
        ...


@dataclass
class _Job:
    fn: Callable[[Link], Any]
    future: Future[Any]
    reads: bool = False  # changes nothing on a slave (read coalescing keeps its data)


_STOP = object()


class LineWorker:
    """A line and its worker thread.  Created by :class:`LineRegistry` (shared by every
    user of the same endpoint) or directly; ``start()`` then ``stop()``."""

    def __init__(self, endpoint: Endpoint, timing: LineTiming | None = None,
                 connector: Connector | None = None) -> None:
        self.endpoint = endpoint
        self.timing = timing or LineTiming()
        self.connector = connector
        self._connect_now = False  # a connector has a new link ready: take it at once
        self.stats = LineStats()
        self._counters = LineCounters()  # what the engine counts, across links
        self.stats.native = self._counters.counts
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._pollers: list[Poller] = []
        self._pollers_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._link: Link | None = None
        self.link_up = False
        self.last_link_error: str | None = None
        self._waker = Waker()  # interrupts the engine when a job is queued
        self._changed = 0.0  # monotonic end of the last job that may have written a slave

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            return
        if not self._waker.is_open:
            self._waker = Waker()
        self._thread = threading.Thread(
            target=self._run, name=f"edgemodbus-line {self.endpoint.describe()}", daemon=True
        )
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Fail pending requests, join the worker, close the link (idempotent)."""
        thread = self._thread
        if thread is None:
            return
        self._stopping.set()
        self._post(_STOP)
        if thread is not threading.current_thread():
            wait = timeout if timeout is not None else (
                self.timing.response_timeout + self.timing.settle + self.timing.connect_timeout
                + 5.0
            )
            thread.join(wait)
            if thread.is_alive():
                raise RuntimeError(f"line {self.endpoint.describe()}: worker did not stop")
            self._waker.close()
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stopping.is_set()

    def on_worker(self) -> bool:
        """True on this line's worker thread (in a callback), where waiting for a queued
        job would wait forever."""
        return threading.current_thread() is self._thread

    # -- pollers ---------------------------------------------------------------------
    def attach(self, poller: Poller) -> None:
        with self._pollers_lock:
            if poller not in self._pollers:
                self._pollers = [*self._pollers, poller]
        self._post(None)  # wake the worker to reschedule

    def detach(self, poller: Poller) -> None:
        with self._pollers_lock:
            self._pollers = [p for p in self._pollers if p is not poller]
        self._post(None)  # the engine lets go of its device at once

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
        self._post(None)

    # -- requests from any thread ------------------------------------------------------
    def submit(self, fn: Callable[[Link], T], reads: bool = False) -> Future[T]:
        """Run ``fn(link)`` on the worker, before the next poll step.  ``reads``: the
        job only reads, so the data of blocks polled before it still holds."""
        future: Future[T] = Future()
        if self._stopping.is_set() or self._thread is None:
            future.set_exception(
                ModbusConnectionError(f"line {self.endpoint.describe()} is not running")
            )
            return future
        self._post(_Job(fn, future, reads))
        return future

    def _post(self, item: Any) -> None:
        self._queue.put(item)
        self._waker.signal()

    def read(self, slave: int, area: Area, address: int, count: int) -> Future[list[int]]:
        """Read registers (ints) or bits (0/1 ints) from one slave."""
        return self.submit(lambda link: link.read(slave, area, address, count).to_list(),
                           reads=True)

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

    def forward(self, slave: int, pdu: bytes, timeout: float | None = None) -> Future[bytes]:
        """Forward a request PDU to ``slave`` like a write; the future's result is the
        reply PDU, its failure comes before the line's settle (see
        :mod:`edgemodbus.line.forward`, which raises here for a PDU that is not
        forwarded).  ``timeout``: default the line's response timeout."""
        wait = self.timing.response_timeout if timeout is None else timeout
        return forward_future(self.submit, slave, pdu, wait, self._cached)

    def _cached(self, slave: int, function: int, address: int, count: int) -> list[int] | None:
        """Read coalescing (worker thread): the values a block of a device polling
        ``slave`` read since the last job that may have written, within that device's
        ``forwardCoalesce`` age; None if no such block covers the span."""
        for poller in self._pollers:
            device = poller.device
            if device.slave == slave:
                values = device.cached(function, address, count, self._changed)
                if values is not None:
                    return values
        return None

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
        """One step while the link is up: a queued request, else the engine's run until
        it needs Python, else (a link without one) the most overdue poller's step."""
        if not self._queue.empty():
            self._waker.clear()
            self._handle(self._queue.get_nowait(), link)
            return
        pollers = self._pollers
        if not pollers:
            self._handle(self._queue.get(), link)
            return
        until = time.monotonic() + _MAX_IDLE
        event = link.run_engine(self._waker, self._counters, [p.device for p in pollers],
                                until)
        if event is not None:
            self._dispatch(link, event, pollers)
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
        link.flush_reports()

    def _dispatch(self, link: Link, event: tuple[int, int, int], pollers: list[Poller]) -> None:
        """Hand what the engine came back for to whom it concerns."""
        kind, which, err = event
        try:
            if kind == EV_CYCLE:
                pollers[which].engine_cycle()
            elif kind == EV_FAILED:
                pollers[which].engine_failed(link, err)
            elif kind == EV_WAKE:  # the queue is served next; a stale flag is cleared
                self._waker.clear()
                if which >= 0:  # a job may set items of the pass under way: results first
                    pollers[which].take_results()
            elif kind == EV_INPUT:
                link.pump()
            elif kind == EV_ERROR:
                log.error("%s: engine wait failed: %s", self.endpoint.describe(),
                          os.strerror(err))
                time.sleep(_IDLE_SLICE)
        except Exception:  # a poller bug must not kill the line
            log.exception("%s: poller failed", self.endpoint.describe())
        link.flush_reports()

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
        finally:
            if not job.reads:
                self._changed = time.monotonic()
        link.flush_reports()

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
        if isinstance(ep, DtuEndpoint):
            raise ModbusConnectionError(f"{ep.describe()}: a DTU link needs a connector")
        return open_link(ep, self.timing, self.stats, on_report=self.dispatch_report)

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
                    ModbusConnectionError(f"line {self.endpoint.describe()} stopped")
                )
