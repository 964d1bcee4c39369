"""The loop engine's workers: a few threads, each running one
:class:`~edgemodbus._ffi.loop.Loop`, serve many DTU lines instead of a thread per line.

A :class:`LoopLine` is a :class:`~edgemodbus.line.worker.LineWorker` without a thread of
its own: its pollers, jobs, link-up and link-down reports and stats are the line
worker's, but its link is a :class:`~edgemodbus._ffi.loop.LoopLink` (a non-blocking
state machine in C, csrc/emb_loop_link.c) on the epoll set of a :class:`LoopWorker`.
Other threads reach it as they reach a line worker: jobs go on the line's queue and
the worker's one eventfd wakes the loop (wake-ups coalesce).  Each turn the worker
runs every link that had news (a ready socket, a deadline, a job) and hands the passes
that ended to the pollers; a link's jobs run while that link is idle, one after the
other, blocking the loop for the job's own transaction (writes are rare and short;
the fairness rule of csrc/emb_engine.c, one job between two reads, is not kept yet).
A link failure closes that link only: its devices go down with the reason and the
line waits for the DTU to dial in again (:meth:`LineWorker.connect_now`).  A
connect-mode line (an RTU-over-TCP endpoint the gateway connects to) connects again
after the line worker's reconnect backoff, without blocking the loop: its connector is a
:class:`~edgemodbus.line.loop_connect.Dialer`, a non-blocking connect on the same slot.

:data:`pool` spreads the lines over ``loopThreads`` workers (least loaded first); a
worker starts with its first line and stops with its last.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from .._ffi.engine import Engine, Waker
from .._ffi.loop import EV_CYCLE, EV_FAILED, EV_REPORTS, EV_SPLIT, EV_WAITS, LS_IDLE, Loop, LoopLink
from ..errors import ModbusConnectionError
from .endpoint import DtuEndpoint, LineTiming, TcpEndpoint
from .link import ContextLink
from .loop_connect import Dialer
from .poller_api import Poller
from .worker import Connector, LineWorker

log = logging.getLogger("edgemodbus.line")

_MAX_IDLE = 3600.0  # the loop comes back at least once an hour
DEFAULT_CAPACITY = 32768  # lines one worker serves at most (50,000 DTUs on two: docs/scale.md)


def loop_serves(endpoint: DtuEndpoint | TcpEndpoint) -> bool:
    """Whether the loop engine serves this line: a DTU that dials in, with every stream
    framing csrc/emb_loop_link.c serves (plain RTU, with heartbeats or the echo option,
    and wrapped frames with their reports), or an RTU-over-TCP endpoint the gateway
    connects to, plain, without alternates (failover.py's watcher drives a line worker)."""
    if isinstance(endpoint, TcpEndpoint):
        return (endpoint.transport == "rtu-over-tcp" and not endpoint.alternates
                and not endpoint.echo and endpoint.framing == "rtu")
    return endpoint.framing in ("rtu", "wrapped-report")


@dataclass(eq=False, slots=True)
class _Served:
    """A line on a worker: its slot, and while up its link, engine and loop link."""

    line: LoopLine
    slot: int
    link: ContextLink | None = None
    engine: Engine | None = None
    ll: LoopLink | None = None
    failures: int = 0  # connects failed in a row (the reconnect backoff)
    pollers: list[Poller] = field(default_factory=list)


class LoopLine(LineWorker):
    """A DTU line, or a connect-mode RTU-over-TCP line (its connector a
    :class:`~edgemodbus.line.loop_connect.Dialer`), served by a :class:`LoopWorker`
    (see the module)."""

    __slots__ = ("_worker", "_workers")

    def __init__(self, endpoint: DtuEndpoint | TcpEndpoint, timing: LineTiming | None,
                 connector: Connector, workers: LoopPool) -> None:
        if not loop_serves(endpoint):
            raise ValueError(f"{endpoint.describe()}: framing {endpoint.framing!r}: engine "
                             "'loop' serves DTUs that dial in "
                             "(framing rtu or wrapped-report) and plain rtu-over-tcp "
                             "endpoints (no alternates, no echo); use engine 'thread'")
        super().__init__(endpoint, timing, connector)
        self._workers = workers
        self._worker: LoopWorker | None = None

    def start(self) -> None:
        if self._worker is not None:
            return
        worker = self._workers.assign(self)
        self._worker = worker
        self._thread = worker.thread
        self._waker.close()  # the worker's eventfd wakes the loop
        self._waker = worker.waker

    def stop(self, timeout: float | None = None) -> None:
        """Fail pending requests, leave the worker, close the link (idempotent)."""
        worker = self._worker
        if worker is None:
            return
        self._stopping = True
        self._worker = None
        self._workers.release(self, worker, timeout)
        self._thread = None

    def _post(self, item: Any) -> None:
        self._queue.put(item)
        worker = self._worker
        if worker is not None:
            worker.news(self)


class LoopWorker:
    """One thread and one loop serving up to ``capacity`` lines."""

    def __init__(self, name: str, capacity: int = DEFAULT_CAPACITY) -> None:
        self.loop = Loop(capacity)
        self.waker = Waker()  # the engines' (the loop link never waits on it)
        self._free: list[int] = []  # slots given back; then the never used, from _unused
        self._unused = 0  # (no list of every slot: 32,768 ints are 1.2 MB a worker)
        self._slots: dict[int, _Served] = {}
        self._by_line: dict[LoopLine, _Served] = {}
        self._inbox: queue.SimpleQueue[tuple[bool, LoopLine, Future[None]]] = \
            queue.SimpleQueue()
        self._news: set[LoopLine] = set()
        self._lock = threading.Lock()
        self._stopping = False
        self.load = 0  # lines assigned (the pool's count)
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    # -- any thread ----------------------------------------------------------------
    def add(self, line: LoopLine) -> Future[None]:
        return self._ask(True, line)

    def remove(self, line: LoopLine) -> Future[None]:
        return self._ask(False, line)

    def _ask(self, add: bool, line: LoopLine) -> Future[None]:
        future: Future[None] = Future()
        self._inbox.put((add, line, future))
        self.loop.wake()
        return future

    def news(self, line: LoopLine) -> None:
        """``line`` has something queued (a job, a connection, new pollers)."""
        with self._lock:
            self._news.add(line)
        try:
            self.loop.wake()
        except OSError:
            if not self._stopping:  # else the loop is closed: nothing to wake
                raise

    def stop(self) -> None:
        """End the thread, which drops the lines left and closes the loop (idempotent;
        from the loop thread itself, it ends after this turn)."""
        self._stopping = True
        if not self.thread.is_alive():
            return
        self.loop.wake()
        if self.thread is not threading.current_thread():
            self.thread.join(30)
            if self.thread.is_alive():
                raise RuntimeError(f"{self.thread.name}: did not stop")

    # -- the loop thread -----------------------------------------------------------
    def _run(self) -> None:
        while not self._stopping:
            try:
                turn = self.loop.wait(time.monotonic() + _MAX_IDLE)
                self._take_inbox()
                with self._lock:
                    news, self._news = self._news, set()
                for line in news:
                    served = self._by_line.get(line)
                    if served is not None:
                        self._guarded(self._serve_queue, served)
                expired = set(turn.expired)
                for slot in sorted({s for s, _ in turn.ready} | expired):
                    served = self._slots.get(slot)
                    if served is None:
                        continue
                    if served.ll is not None:
                        self._guarded(self._step, served)
                    elif slot in expired or _dialing(served):  # down: the reconnect
                        self._guarded(self._connect, served)  # delay ran out, or a connect
            except Exception:  # a bug must not stop the other lines
                log.exception("%s: loop turn failed", self.thread.name)
        for served in list(self._by_line.values()):
            self._drop(served)
        self.loop.close()
        self.waker.close()

    def _guarded(self, step: Callable[[_Served], object], served: _Served) -> None:
        """Run ``step`` for one line; an unexpected error costs that line only, as on a
        line worker (LineWorker._recover: logged, link closed, devices told, jobs
        failed) and it tries again after the reconnect backoff."""
        try:
            step(served)
        except Exception as exc:
            self._detach(served)
            _abort_dial(served)
            served.link = None
            line = served.line
            line._recover(exc)
            served.failures = max(1, line._crashes)
            self._retry(served)

    def _slot(self) -> int:
        """A free slot of the loop (the pool gives a worker at most its capacity)."""
        if self._free:
            return self._free.pop()
        if self._unused >= self.loop.capacity:
            raise RuntimeError(f"loop worker full: {self.loop.capacity} lines")
        self._unused += 1
        return self._unused - 1

    def _take_inbox(self) -> None:
        while True:
            try:
                add, line, future = self._inbox.get_nowait()
            except queue.Empty:
                return
            try:
                if add:
                    served = _Served(line, self._slot())
                    self._slots[served.slot] = served
                    self._by_line[line] = served
                    self._guarded(self._connect, served)
                else:
                    served_or_none = self._by_line.get(line)
                    if served_or_none is not None:
                        self._drop(served_or_none)
                future.set_result(None)
            except Exception as exc:
                future.set_exception(exc)

    def _drop(self, served: _Served) -> None:
        """Take a line off this worker: its link closed, its jobs failed."""
        self._detach(served)
        _abort_dial(served)
        self.loop.clear_timer(served.slot)  # a reconnect delay
        del self._slots[served.slot], self._by_line[served.line]
        self._free.append(served.slot)
        served.line._shutdown()

    def _detach(self, served: _Served) -> None:
        """The loop lets go of the line's link (before the link closes)."""
        if served.ll is not None:
            with contextlib.suppress(OSError):  # (a socket closed already is unwatched)
                served.ll.detach()
                os.set_blocking(served.ll.ctx.fd, True)
        served.ll = served.engine = None

    def _connect(self, served: _Served) -> bool:
        """Take the line's new connection, if any (its devices hear up, or why not);
        without one, try again after the line's reconnect delay (the slot's deadline,
        free while the line is down), as the line worker does."""
        line = served.line
        self.loop.clear_timer(served.slot)
        dialer = line.connector
        if isinstance(dialer, Dialer) and not dialer.step(
                self.loop, served.slot, line.timing.connect_timeout, lambda: self.news(line)):
            return False  # connecting: the slot wakes when the socket or deadline says
        if not line._connect():
            served.failures += 1
            self._retry(served)
            return False
        served.failures = 0
        link = line._link
        assert isinstance(link, ContextLink)
        engine = link.new_engine(self.waker, line._counters)
        try:
            ll = LoopLink(self.loop, served.slot, engine, link.context,
                          line.timing.byte_timeout)
        except (ValueError, OSError) as exc:
            link.close_reason = f"the loop engine cannot serve it: {exc}"
            link.close()
            line._link_lost(link)
            self._retry(served)
            return False
        served.link, served.engine, served.ll = link, engine, ll
        served.pollers = []  # the new engine has no devices yet: _step gives them
        self._step(served)
        return True

    def _retry(self, served: _Served) -> None:
        delay = served.line._reconnect_delay(served.failures)
        self.loop.set_timer(served.slot, time.monotonic() + delay)

    def _lost(self, served: _Served) -> None:
        """The line's link failed or closed: the devices hear why, unless a new
        connection is waiting (replaced: they see one "up", no "down")."""
        link = served.link
        self._detach(served)
        served.link = None
        if link is None:
            return
        if link.is_open:
            link.close()
        if served.line._connect_now and self._connect(served):
            return
        served.line._link_lost(link)
        if served.ll is None:
            self._retry(served)

    def _serve_queue(self, served: _Served) -> None:
        """Run what the line queued, while its link is idle (or down: jobs fail)."""
        line = served.line
        if line._connect_now:
            link = served.link
            if link is not None and link.is_open:
                self._detach(served)
                link.close_reason = "replaced by a new connection"
                link.close()
            served.link = None
            if not self._connect(served) and link is not None:
                line._link_lost(link)  # replaced by nothing (e.g. the id is contested)
        if served.ll is None and _dialing(served):
            self._connect(served)  # (the resolver has the host's addresses)
        ll = served.ll
        if ll is None:  # down: the jobs fail at once
            while True:
                try:
                    item = line._queue.get_nowait()
                except queue.Empty:
                    return
                line._handle(item, None)
        if ll.state == LS_IDLE:  # else the link comes back to its jobs once idle (_step)
            self._step(served)

    def _run_jobs(self, served: _Served) -> bool:
        """Run the jobs queued for the line's idle link, on its socket made blocking for
        their transactions; False if the link was lost meanwhile."""
        line, link, ll = served.line, served.link, served.ll
        assert link is not None and ll is not None
        while True:
            try:
                item = line._queue.get_nowait()
            except queue.Empty:
                return True
            os.set_blocking(ll.ctx.fd, True)
            try:
                line._handle(item, link)
            finally:
                if link.is_open:
                    os.set_blocking(ll.ctx.fd, False)
            if not link.is_open:
                self._lost(served)
                return False

    def _step(self, served: _Served) -> None:
        """Run the line's link as far as it goes now; hand the ended passes to the
        pollers, a split or a failure to the poller concerned."""
        ll, engine, line = served.ll, served.engine, served.line
        assert ll is not None and engine is not None
        while True:
            if ll.state == LS_IDLE:  # jobs go ahead of the next read
                if not line._queue.empty() and not self._run_jobs(served):
                    return
                if served.pollers != line._pollers:
                    served.pollers = list(line._pollers)
                    engine.set_devices([p.device for p in served.pollers])
            ev = ll.run()
            pollers = served.pollers
            for ended in engine.take_ended():
                try:
                    pollers[ended].engine_cycle()
                except Exception:
                    log.exception("%s: poller failed", line.endpoint.describe())
            if ev == EV_WAITS:
                break
            if ev == EV_SPLIT:
                try:
                    pollers[engine.event_device].engine_split()
                except Exception:
                    log.exception("%s: poller failed", line.endpoint.describe())
            elif ev == EV_REPORTS:
                self._reports(served, engine.event_device)
            elif ev == EV_FAILED:
                self._failed(served, engine.event_device, engine.event_errno)
                return
            elif ev != EV_CYCLE:
                raise RuntimeError(f"loop link: unexpected event {ev}")
        link = served.link
        if link is not None:
            link.collect()  # the stream's counters (heartbeats, drops) into the stats

    def _reports(self, served: _Served, which: int) -> None:
        """A wrapped link took reports: handed over as the line worker hands them after
        the blocking engine's EV_REPORTS (line/worker.py ``_dispatch``): those that came
        before the reply, then the reply's results (device ``which``), then the rest."""
        link = served.link
        assert link is not None
        link.collect()
        if 0 <= which < len(served.pollers):
            try:
                served.pollers[which].take_results()
            except Exception:
                log.exception("%s: poller failed", served.line.endpoint.describe())
        link.flush_reports()

    def _failed(self, served: _Served, which: int, err: int) -> None:
        link = served.link
        assert link is not None
        self._detach(served)
        link.collect()
        try:
            if 0 <= which < len(served.pollers):
                served.pollers[which].engine_failed(link, err)
        except ModbusConnectionError:
            pass
        except Exception:
            log.exception("%s: poller failed", served.line.endpoint.describe())
        if link.is_open:
            link.close_reason = f"link failed: {os.strerror(err)}"
        self._lost(served)


def _dialing(served: _Served) -> bool:
    """A connect-mode line whose connect is under way."""
    connector = served.line.connector
    return isinstance(connector, Dialer) and connector.busy


def _abort_dial(served: _Served) -> None:
    connector = served.line.connector
    if isinstance(connector, Dialer):
        connector.abort()


class LoopPool:
    """The process's loop workers: ``threads`` (default: the cores), each line on the
    least loaded with room (``capacity`` lines; when every worker is full, one more
    starts, past ``threads``); a worker starts with its first line, stops with its last."""

    def __init__(self, threads: int | None = None, capacity: int = DEFAULT_CAPACITY) -> None:
        self.threads = threads or os.cpu_count() or 1
        self.capacity = capacity
        self._workers: list[LoopWorker] = []
        self._lock = threading.Lock()
        self._made = 0

    def configure(self, threads: int | None) -> None:
        """``loopThreads`` (None: the cores); for workers started from now on."""
        if threads is not None and not (isinstance(threads, int) and 1 <= threads <= 1024):
            raise ValueError(f"loopThreads {threads!r}: must be an integer 1..1024")
        self.threads = threads or os.cpu_count() or 1

    def assign(self, line: LoopLine) -> LoopWorker:
        with self._lock:
            room = [w for w in self._workers if w.load < self.capacity]
            if len(self._workers) < self.threads or not room:
                if not room and self._workers:
                    log.info("every loop thread serves %d lines: one more loop thread, "
                             "past loopThreads %d", self.capacity, self.threads)
                self._made += 1
                worker = LoopWorker(f"edgemodbus-loop {self._made}", self.capacity)
                self._workers.append(worker)
            else:
                worker = min(room, key=lambda w: w.load)
            worker.load += 1
        worker.add(line).result()
        return worker

    def release(self, line: LoopLine, worker: LoopWorker, timeout: float | None) -> None:
        """Take ``line`` off ``worker`` (waited for, except on the loop thread itself: a
        poller's callback, where the line goes at the next turn)."""
        removed = worker.remove(line)
        if worker.thread is not threading.current_thread():
            removed.result(timeout if timeout is not None else 30)
        with self._lock:
            worker.load -= 1
            last = worker.load == 0
            if last:
                self._workers.remove(worker)
        if last:
            worker.stop()

    @property
    def workers(self) -> int:
        with self._lock:
            return len(self._workers)


pool = LoopPool()

__all__ = ["LoopLine", "LoopPool", "LoopWorker", "loop_serves", "pool"]
