"""One line (a serial port, a TCP endpoint, or a DTU behind a listener) served by one
worker thread, which creates, uses and frees the line's libmodbus context (contexts are
not thread-safe).  Other threads reach the line through a queue (:meth:`LineWorker.submit`
and the request helpers: ``concurrent.futures.Future`` objects); pollers (the driver's
devices) are called on the worker when they are due.  Queued requests (writes) run before
the next poll step, but while a block is due at most one job runs between two poll
transactions, so that no flood of jobs starves polling (:mod:`edgemodbus.line.jobs`).
The link (:mod:`edgemodbus.line.link`) settles the line after timeouts and drains it
after other errors.  An unexpected exception on the worker is logged, the link closed,
the devices set Offline with the reason, the jobs failed, and the line restarts with
backoff: the worker never dies of it (:meth:`LineWorker._recover`).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol, TypeVar

from .._ffi.engine import (
    EV_ERROR,
    EV_FAILED,
    EV_INPUT,
    EV_REPORTS,
    EV_SPLIT,
    EV_WAKE,
    Waker,
)
from .._ffi.outcomes import LineCounters
from ..errors import LineBusyError, ModbusConnectionError, ModbusError
from ..stats import LineStats
from .connect import open_link
from .endpoint import DtuEndpoint, Endpoint, LineTiming, MqttDtuEndpoint
from .job_runner import JobRunner
from .jobs import (
    MAX_PENDING,
    STOP,
    Job,
    LineWorkerError,
    PollLag,
    TargetBackoff,
    crash_reason,
    reconnect_delay,
)
from .link import Link
from .poller_api import Poller
from .requests import LineRequests

log = logging.getLogger("edgemodbus.line")
T = TypeVar("T")

_IDLE_SLICE = 0.05  # the pause after a failed engine wait (poll() failing) before the next
_MAX_IDLE = 3600.0  # the engine comes back at least once an hour
_LEASE_SLICE = 0.1  # while the line's lease is not held: how often it is looked at again
LEASE_ENDED = "this instance does not hold the pair's lease (it sends nothing until it does)"


class Connector(Protocol):
    """How a line worker gets its link, for endpoints it cannot open itself (a DTU that
    dials in: the listener hands its socket over)."""

    def open(self, line: LineWorker) -> Link:
        """Return an open link, or raise :class:`ModbusConnectionError` (worker thread)."""
        ...


class LineWorker(LineRequests, JobRunner):
    """A line and its worker thread.  Created by :class:`LineRegistry` (shared by every
    user of the same endpoint) or directly; ``start()`` then ``stop()``."""

    # thousands of lines on a loop: slots, no dict of 30 keys (docs/scale.md "Memory per DTU")
    __slots__ = ("__weakref__", "_backoff", "_connect_now", "_counters", "_crashes", "_failures",
                 "_lag", "_last_crash", "_link", "_next_connect", "_pending_lock", "_pollers",
                 "_pollers_lock", "_queue", "_stopping", "_thread", "_told", "_up_since",
                 "_waker", "connector", "endpoint", "last_link_error", "lease", "link_up",
                 "max_pending", "stats", "timing")

    def __init__(self, endpoint: Endpoint, timing: LineTiming | None = None,
                 connector: Connector | None = None) -> None:
        self.endpoint = endpoint
        self.timing = timing or LineTiming()
        self.connector = connector
        self._connect_now = False  # a connector has a new link ready: take it at once
        self._counters = LineCounters()  # what the engine counts, across links
        self.stats = LineStats(native=self._counters.counts)
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._pollers: list[Poller] = []
        self._told: tuple[Poller, ...] = ()  # the pollers told of the link down now
        self._pollers_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stopping = self.link_up = False  # _stopping: stop() was called (nothing waits)
        self._link: Link | None = None
        self.last_link_error: str | None = None
        self._waker = Waker()  # interrupts the engine when a job is queued
        self._changed = 0.0  # monotonic end of the last job that may have written a slave
        self.max_pending = MAX_PENDING  # jobs queued at most; more: LineBusyError
        self._pending = 0  # jobs queued, not yet taken
        self._pending_lock = threading.Lock()
        self._owed = 0  # poll transactions owed while polling is due: the last job's count
        self._polled = 0  # the engine's requests counted when _owed was last set or paid
        self._share_until = 0.0  # polling's share of the line after the last job ends
        self._backoff = TargetBackoff(self.timing.max_backoff)
        self._lag = PollLag(log, endpoint.describe())
        self._last_crash: str | None = None  # the last unexpected error, logged once
        self._crashes = self._failures = 0  # crashes: unexpected errors, no calm max_backoff
        self._up_since = self._next_connect = 0.0
        self.lease: Callable[[], float] | None = None
        """A redundant pair's lease (gateway/pair.py): the monotonic time before which a request
        may start.  At or after it the engine (its run's ``until``) and the jobs (:meth:`_gate`,
        as each request goes out) send nothing; the link is closed, none opened until renewed."""

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            return
        if not self._waker.is_open:
            self._waker = Waker()
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"edgemodbus-line {self.endpoint.describe()}")
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Fail pending requests, join the worker, close the link (idempotent)."""
        thread = self._thread
        if thread is None:
            return
        self._stopping = True
        self._post(STOP)
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
        return self._thread is not None and not self._stopping

    def on_worker(self) -> bool:
        """True on the line's worker thread, where waiting for a queued job never ends."""
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

    def lease_changed(self) -> None:
        """The line's lease was lost: the engine comes back (after the transaction in
        flight) and reads the deadline again (:attr:`lease`).  Any thread."""
        self._post(None)

    def connect_now(self) -> None:
        """A new link is ready (a DTU dialled in, maybe replacing its old connection):
        drop the current link, if any, and open the new one without waiting for the
        reconnect interval.  Any thread."""
        self._connect_now = True
        self._post(None)

    # -- requests from any thread ------------------------------------------------------
    def submit(self, fn: Callable[[Link], T], reads: bool = False,
               slave: int | None = None) -> Future[T]:
        """Run ``fn(link)`` on the worker, before the next poll step (or, while polling
        is due, after the next poll transaction).  ``reads``: the job only reads, so the
        data of blocks polled before it still holds; ``slave``: the slave it addresses,
        for the target backoff after a timeout; such a job's future fails with
        :class:`LineBusyError` when :attr:`max_pending` jobs are already waiting."""
        future: Future[T] = Future()
        if self._stopping or self._thread is None:
            future.set_exception(
                ModbusConnectionError(f"line {self.endpoint.describe()} is not running")
            )
            return future
        with self._pending_lock:  # (control jobs, with no slave, are never refused)
            busy = slave is not None and self._pending >= self.max_pending
            if not busy:
                self._pending += 1
        if busy:
            self.stats.jobs_refused += 1
            future.set_exception(LineBusyError(
                f"line {self.endpoint.describe()}: {self.max_pending} jobs already waiting "
                f"(at most {self.max_pending}); try again later"))
            return future
        self._post(Job(fn, future, reads, slave))
        return future

    def _post(self, item: Any) -> None:
        self._queue.put(item)
        self._waker.signal()

    # -- the worker ------------------------------------------------------------------
    def _run(self) -> None:
        self._next_connect = 0.0
        self._failures = 0  # failed connects in a row
        try:
            while not self._stopping:
                try:
                    self._turn()
                except Exception as exc:  # a bug or an unforeseen error: never die of it
                    self._recover(exc)
        finally:
            self._shutdown()

    def _turn(self) -> None:
        """One turn of the worker: (re)connect when due, else serve the link."""
        link = self._link
        held = self.lease is None or time.monotonic() < self.lease()
        if link is not None and link.is_open and (self._connect_now or not held):
            link.close_reason = "replaced by a new connection" if held else LEASE_ENDED
            link.close()
        if link is None or not link.is_open:
            if link is not None:
                if held and self._connect_now and self._connect():
                    return  # replaced: the pollers see one "up", no "down"
                self._link_lost(link)
                self._next_connect = time.monotonic() + self._reconnect_delay(0)
            if not held:  # no link while the lease is not held; jobs fail at once
                self._connect_now, self.last_link_error = False, LEASE_ENDED
                self._serve_queue_while_down(time.monotonic() + _LEASE_SLICE)
                return
            if self._connect_now or time.monotonic() >= self._next_connect:
                if self._connect():
                    self._failures = 0
                    return
                self._failures += 1
                self._next_connect = time.monotonic() + self._reconnect_delay(self._failures)
            self._serve_queue_while_down(self._next_connect)
            return
        if self._crashes and time.monotonic() - self._up_since > self.timing.max_backoff:
            self._crashes, self._last_crash = 0, None  # calm again: a new error is news
        self._serve(link)

    def _recover(self, exc: Exception) -> None:
        """An unexpected exception on the worker (or on its loop, line/loop.py): log it
        (once while it repeats), close the link, set the devices Offline with the reason
        until the line is back, fail the jobs waiting (LineWorkerError: a forward is
        answered 0B), and try again after the reconnect backoff."""
        reason = crash_reason(exc)
        self.stats.worker_errors += 1
        if reason != self._last_crash:
            log.error("%s: %s; the line restarts", self.endpoint.describe(), reason,
                      exc_info=exc)
        else:
            log.debug("%s: %s again", self.endpoint.describe(), reason)
        self._last_crash = reason
        link, self._link = self._link, None
        if link is not None and link.is_open:
            link.close_reason = reason
            try:
                link.close()
            except Exception:
                log.debug("%s: closing the link failed", self.endpoint.describe(),
                          exc_info=True)
        self.link_up = False
        self.last_link_error = reason
        self._notify(False, reason, offline=True)
        self._fail_queued(f"{self.endpoint.describe()}: {reason}", LineWorkerError)
        self._crashes += 1
        self._next_connect = time.monotonic() + self._reconnect_delay(self._crashes)

    def _reconnect_delay(self, failures: int) -> float:
        return reconnect_delay(self.timing, failures)

    def _serve(self, link: Link) -> None:
        """One step while the link is up: a queued request (unless polling is owed its
        share of the line: line/jobs.py job_gate), else the engine's run until it needs
        Python (EV_DEADLINE: an hour went by, polling's share ended, the link closed)."""
        pollers = self._pollers
        until = time.monotonic() + _MAX_IDLE
        if not self._queue.empty():
            late, wait = self._job_wait([p.device for p in pollers])
            if wait is None:
                self._waker.clear()
                self._handle(self._queue.get_nowait(), link, late)
                return
            if wait == float("inf"):  # due now: the engine comes back once it read it
                self._waker.signal()
            else:  # falls due before polling's share ends: the engine runs until then
                self._waker.clear()
                until = wait
        if not pollers:
            self._handle(self._queue.get(), link)
            return
        if self.lease is not None:  # the engine starts no request at or after it
            until = min(until, self.lease())
        event = link.run_engine(self._waker, self._counters, [p.device for p in pollers],
                                until, self._owed > 0)
        self._pay_owed()  # the poll transactions made pay for the last job's
        self._dispatch(link, event, pollers)

    def _dispatch(self, link: Link, event: tuple[int, int, int], pollers: list[Poller]) -> None:
        """Hand what the engine came back for to whom it concerns (EV_TRACE: nothing
        more, the link logged the frames traced when the engine came back)."""
        kind, which, err = event
        for ended in link.take_ended():  # every pass that ended, EV_CYCLE or not
            try:
                pollers[ended].engine_cycle()
            except Exception:  # a poller bug must not cost the others their pass
                log.exception("%s: poller failed", self.endpoint.describe())
        try:
            if kind == EV_SPLIT:
                pollers[which].engine_split()
            elif kind == EV_FAILED:
                pollers[which].engine_failed(link, err)
            elif kind == EV_WAKE:  # the queue is served next; a stale flag is cleared
                self._waker.clear()
                if which >= 0:  # a job may set items of the pass under way: results first
                    pollers[which].take_results()
            elif kind == EV_REPORTS:  # the reports before the reply went out already
                pollers[which].take_results()  # the reply, then the rest (below)
            elif kind == EV_INPUT:
                link.pump()
            elif kind == EV_ERROR:
                log.error("%s: engine wait failed: %s", self.endpoint.describe(),
                          os.strerror(err))
                time.sleep(_IDLE_SLICE)
        except Exception:  # a poller bug must not kill the line
            log.exception("%s: poller failed", self.endpoint.describe())
        link.flush_reports()

    def _serve_queue_while_down(self, until: float) -> None:
        """While disconnected: fail queued requests at once, sleep until the next try."""
        while not self._stopping and not self._connect_now:
            wait = until - time.monotonic()
            if wait <= 0:
                return
            try:
                item = self._queue.get(timeout=wait)
            except queue.Empty:
                return
            self._handle(item, None)
            # a poller attached meanwhile learns why the link is down now, not at the next try
            self._notify(False, self.last_link_error, late=True)

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
            self._notify(False, str(exc))  # the devices know why before anyone reads it
            # exc names the line; a connector's same failure again (a DTU that has not
            # dialled in yet) is not repeated at WARNING on every try
            log.log(logging.DEBUG if repeated else logging.WARNING, "connect failed: %s", exc)
            return False
        self._link = link
        link.gate = self._gate
        self.link_up = True
        self.last_link_error = None
        self._up_since = time.monotonic()
        if first:
            self.stats.connects += 1
        else:
            self.stats.reconnects += 1
        log.info("%s: link up", self.endpoint.describe())
        self._notify(True, None)
        return True

    def _gate(self) -> None:
        """The link's check right before each request of a job (Link.gate): past the
        line's lease, close the link and refuse (ModbusConnectionError: nothing sent)."""
        lease, link = self.lease, self._link
        if lease is not None and time.monotonic() >= lease():
            if link is not None:
                link.close_reason = LEASE_ENDED
                link.close()
            raise ModbusConnectionError(f"{self.endpoint.describe()}: not sent: {LEASE_ENDED}")

    def _open(self) -> Link:
        ep = self.endpoint
        if isinstance(ep, (DtuEndpoint, MqttDtuEndpoint)):
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

    def _notify(self, up: bool, reason: str | None, offline: bool = False,
                late: bool = False) -> None:
        pollers = [p for p in self._pollers if not (late and p in self._told)]
        self._told = () if up else (self._told if late else ()) + tuple(pollers)
        for poller in pollers:
            try:
                poller.link_changed(up, reason, offline)
            except Exception:
                log.exception("%s: poller link_changed failed", self.endpoint.describe())

    def _shutdown(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None
        self.link_up = False
        self._fail_queued(f"line {self.endpoint.describe()} stopped")

    def _fail_queued(self, reason: str,
                     error: type[ModbusConnectionError] = ModbusConnectionError) -> None:
        """Fail every job waiting on the queue with ``error(reason)`` (the line stops,
        or its worker recovers from an error)."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, Job):
                with self._pending_lock:
                    self._pending -= 1
                if item.future.set_running_or_notify_cancel():
                    item.future.set_exception(error(reason))
