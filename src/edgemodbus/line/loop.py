"""The loop engine's workers: a few threads, each running one
:class:`~edgemodbus._ffi.loop.Loop`, serve many lines instead of a thread per line.

A :class:`LoopLine` is a :class:`~edgemodbus.line.worker.LineWorker` without a thread of
its own (its pollers, jobs, link reports and stats are the line worker's); its link is a
:class:`~edgemodbus._ffi.loop.LoopLink` (a state machine in C, csrc/emb_loop_link.c) on
a :class:`LoopWorker`'s epoll set.  Jobs go on the line's queue and the worker's one
eventfd wakes the loop.  One turn is one C call (``Loop.turn``, csrc/emb_loop_turn.c):
it runs every ready or expired link and comes back only with the links Python must see
(passes with news, a split, reports, a failure, jobs flagged for an idle link).  A
link's jobs run while it is idle, on a job thread, the link out of the loop meanwhile
(line/loop_jobs.py), by the thread engine's rule while polling is due (line/jobs.py
``job_gate``: a job owes polling as many reads as it made, and its time).  A failed
link closes that link only; a DTU line waits for the DTU to dial in again, a
connect-mode line (RTU over TCP or Modbus TCP) connects again after the reconnect
backoff through a non-blocking :class:`~edgemodbus.line.loop_connect.Dialer` on the
same slot.

:data:`~edgemodbus.line.loop_pool.pool` (line/loop_pool.py) spreads the lines over
``loopThreads`` workers (least loaded first); a worker starts with its first line and
stops with its last.
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
from typing import Any, Protocol

from .._ffi.engine import Engine, Waker
from .._ffi.loop import (
    EV_COLLECT,
    EV_CYCLE,
    EV_FAILED,
    EV_REPORTS,
    EV_SPLIT,
    EV_WAITS,
    EV_WAKE,
    LS_IDLE,
    SLOT_DUE,
    SLOT_READY,
    Loop,
    LoopLink,
)
from . import loop_jobs
from .endpoint import DtuEndpoint, LineTiming, TcpEndpoint
from .jobs import Job
from .link import ContextLink
from .loop_connect import Dialer, abort_dial, dialing
from .loop_events import hand_ended, hand_failure, hand_reports, hand_split
from .loop_scope import loop_serves, why_not
from .poller_api import Poller
from .worker import Connector, LineWorker

log = logging.getLogger("edgemodbus.line")

_MAX_IDLE = 3600.0  # the loop comes back at least once an hour
DEFAULT_CAPACITY = 32768  # lines one worker serves at most (50,000 DTUs on two: docs/scale.md)


class Workers(Protocol):
    """What a loop line needs of its pool (line/loop_pool.py ``LoopPool``)."""

    def assign(self, line: LoopLine) -> LoopWorker: ...
    def release(self, line: LoopLine, worker: LoopWorker, timeout: float | None) -> None: ...


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
    busy: bool = False  # its jobs run on a job thread, its link out of the loop
    hold: int = -1  # meanwhile a dup of its socket (cut_off: the line stops)
    leaving: Future[None] | None = None  # removed while busy: done once it is back
    crash: Exception | None = None  # its job thread's unexpected error (_returned)


class LoopLine(LineWorker):
    """A DTU line, or a connect-mode line, RTU over TCP or Modbus TCP (its connector a
    :class:`~edgemodbus.line.loop_connect.Dialer`), served by a :class:`LoopWorker`
    (see the module)."""

    __slots__ = ("_worker", "_workers")

    def __init__(self, endpoint: DtuEndpoint | TcpEndpoint, timing: LineTiming | None,
                 connector: Connector, workers: Workers) -> None:
        if not loop_serves(endpoint):
            raise ValueError(f"{endpoint.describe()}: {why_not(endpoint)}; use engine "
                             "'thread'")
        super().__init__(endpoint, timing, connector)
        self._workers = workers
        self._worker: LoopWorker | None = None

    def on_worker(self) -> bool:
        """On its loop thread or the job thread running its jobs: no waiting for a job."""
        return threading.current_thread() is self._thread or loop_jobs.running_jobs_of() is self

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
        if worker is not None:  # None: a reschedule (attach, detach), not a job
            worker.news(self, job=item is not None)


class LoopWorker:
    """One thread and one loop serving up to ``capacity`` lines."""

    def __init__(self, name: str, capacity: int = DEFAULT_CAPACITY) -> None:
        self.loop = Loop(capacity)
        self.capacity = capacity
        self.waker = Waker()  # the engines' (the loop link never waits on it)
        self._free: list[int] = []  # slots given back; then the never used, from _unused
        self._unused = 0  # (no list of every slot: 32,768 ints are 1.2 MB a worker)
        self._slots: dict[int, _Served] = {}
        self._by_line: dict[LoopLine, _Served] = {}
        self._inbox: queue.SimpleQueue[tuple[bool, LoopLine, Future[None]]] = \
            queue.SimpleQueue()
        self._news: set[LoopLine] = set()
        self._back: list[_Served] = []  # lines whose jobs ended on a job thread
        self.jobs = loop_jobs.JobThreads(name)
        self.shares = loop_jobs.Shares()  # lines whose jobs wait for polling's share
        self._lock = threading.Lock()
        self._woken = False  # a wake-up is on its way (_wake_once)
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
        self._wake_once() if add else self.wake_now()  # (a stop waits for a removal)
        return future

    def news(self, line: LoopLine, job: bool = True) -> None:
        """``line`` has something queued: a ``job`` (someone may wait for it), or new
        pollers, a connection."""
        with self._lock:
            self._news.add(line)
        self.wake_now() if job else self._wake_once()

    def _wake_once(self) -> None:
        """:meth:`wake_now`, or inside ``LoopPool.deferred`` on this thread, at the
        block's end (lines added and pollers attached: nothing waits for them)."""
        held: set[LoopWorker] | None = getattr(held_wakeups, "workers", None)
        if held is not None:
            held.add(self)
        else:
            self.wake_now()

    def wake_now(self) -> None:
        """Wake the loop, once until its next turn takes the inbox and the news (after
        what was put there: a start of 5,000 lines is not 10,000 wake-ups, each a
        hand-over of the GIL to the loop thread)."""
        with self._lock:
            if self._woken:
                return
            self._woken = True
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
        with contextlib.suppress(OSError):  # its loop closed since is_alive() (another stop)
            self.loop.wake()
        if self.thread is not threading.current_thread():
            self.thread.join(30)
            if self.thread.is_alive():
                raise RuntimeError(f"{self.thread.name}: did not stop")

    # -- the loop thread -----------------------------------------------------------
    def _run(self) -> None:
        while not self._stopping:
            try:
                turn = self.loop.turn(self.shares.next_end(time.monotonic() + _MAX_IDLE))
                for slot, ev in turn.events:  # before the news: a held link's event
                    served = self._slots.get(slot)
                    if served is None:
                        continue
                    if served.ll is not None:
                        if ev not in (SLOT_READY, SLOT_DUE):
                            self._guarded(self._step, served, ev)
                    elif ev == SLOT_DUE or dialing(served.line.connector):  # down: the reconnect
                        self._guarded(self._connect, served)  # delay ran out, or a connect
                with self._lock:  # before the inbox: a line told of is in it by now
                    news, self._news = self._news, set()
                    back, self._back = self._back, []
                    self._woken = False  # what comes after this wakes the loop again
                self._take_inbox()
                for served in back:
                    self._guarded(self._returned, served)
                for line in news:
                    served = self._by_line.get(line)
                    if served is not None:
                        self._guarded(self._serve_queue, served)
                for slot in self.shares.ended(time.monotonic()):  # their jobs' turn
                    if (served := self._slots.get(slot)) is not None:
                        self._guarded(self._serve_queue, served)
            except Exception:  # a bug must not stop the other lines
                log.exception("%s: loop turn failed", self.thread.name)
        self.jobs.stop()  # (a line's link is its own again once its jobs ended)
        for served in list(self._by_line.values()):
            self._drop(served)
            if served.leaving is not None:
                served.leaving.set_result(None)
        self.loop.close()
        self.waker.close()

    def _guarded(self, step: Callable[..., object], served: _Served, *args: int) -> None:
        """Run ``step`` for one line; an unexpected error costs that line only, as on a
        line worker (LineWorker._recover: logged, link closed, devices told, jobs
        failed) and it tries again after the reconnect backoff."""
        try:
            step(served, *args)
        except Exception as exc:
            if served.busy:  # a job thread has the link: this waits until it is back
                log.exception("%s: loop step failed", served.line.endpoint.describe())
                return
            self._detach(served)
            abort_dial(served.line.connector)
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
                    gone = self._by_line.get(line)
                    if gone is not None and gone.busy:  # done once its job is back,
                        gone.leaving = future  # at once: the job fails on its socket
                        loop_jobs.cut_off(gone.hold)
                        continue
                    if gone is not None:
                        self._drop(gone)
                future.set_result(None)
            except Exception as exc:
                future.set_exception(exc)

    def _drop(self, served: _Served) -> None:
        """Take a line off this worker: its link closed, its jobs failed."""
        self._detach(served)
        abort_dial(served.line.connector)
        served.hold = loop_jobs.let_go(served.hold)
        self.loop.clear_timer(served.slot)  # a reconnect delay
        self.shares.drop(served.slot)
        del self._slots[served.slot], self._by_line[served.line]
        self._free.append(served.slot)
        served.line._shutdown()

    def _detach(self, served: _Served) -> None:
        """The loop lets go of the line's link (before the link closes)."""
        if served.ll is not None:
            with contextlib.suppress(OSError):  # (a socket closed already is unwatched)
                served.ll.detach()
                if served.link is not None and served.link.is_open:
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
        if served.busy:  # a job thread has the link: all this once it is back
            return
        if line._connect_now:
            link = served.link
            if link is not None and link.is_open:
                self._detach(served)
                link.close_reason = "replaced by a new connection"
                link.close()
            served.link = None
            if not self._connect(served) and link is not None:
                line._link_lost(link)  # replaced by nothing (e.g. the id is contested)
        if served.ll is None and dialing(served.line.connector):
            self._connect(served)  # (the resolver has the host's addresses)
        ll = served.ll
        if ll is None:  # down: the jobs fail at once
            with contextlib.suppress(queue.Empty):
                while True:
                    line._handle(line._queue.get_nowait(), None)
            if line.last_link_error is not None:  # a poller attached meanwhile learns why
                line._notify(False, line.last_link_error, late=True)
            return
        if ll.state == LS_IDLE:
            self._step(served)
        else:  # it comes back EV_WAKE once idle (Loop.turn), and _step runs them
            ll.jobs = True

    def _hand_off(self, served: _Served, job: Job) -> None:
        """Run ``job`` and the next ones on a job thread, the link out of the loop."""
        line, link, ll = served.line, served.link, served.ll
        assert link is not None and ll is not None
        ll.pause()
        os.set_blocking(ll.ctx.fd, True)

        def task() -> None:  # (the engine's devices: none changes while the line is busy)
            try:
                loop_jobs.run_jobs(line, link, job, [p.device for p in served.pollers],
                         lambda: line._stopping or served.leaving is not None)
            except Exception as exc:  # the line recovers on the loop thread (_returned)
                served.crash = exc

        def back() -> None:  # (its job thread counts as idle: the next jobs may take it)
            with self._lock:
                self._back.append(served)
            self.wake_now()

        served.busy, served.hold = True, loop_jobs.hold_of(ll.ctx.fd)
        try:
            self.jobs.submit(task, back)
        except Exception:  # no thread to be had: the recovery fails it with the rest
            served.busy = False
            served.hold = loop_jobs.let_go(served.hold)
            line._queue.put(job)
            raise

    def _returned(self, served: _Served) -> None:
        """Its jobs ended: the link back in the loop (owing a read), lost, or dropped."""
        served.busy = False
        served.hold = loop_jobs.let_go(served.hold)
        link, ll = served.link, served.ll
        if served.leaving is not None:
            future, served.leaving = served.leaving, None
            self._drop(served)
            future.set_result(None)
            return
        if served.crash is not None:  # as a line worker's error: _guarded's recovery
            crash, served.crash = served.crash, None
            raise crash
        if link is None or ll is None or not link.is_open:
            self._lost(served)
            return
        os.set_blocking(ll.ctx.fd, False)
        ll.resume()  # (idle: _step applies the rule, loop_jobs.job_or_wait)
        self._serve_queue(served)

    def _step(self, served: _Served, ev: int | None = None) -> None:
        """Run the line's link as far as it goes now, beginning with the event ``ev``
        it came back with in the turn (None: run it first); hand the ended passes to
        the pollers, a split or a failure to the poller concerned, its jobs run while
        it is idle."""
        ll, engine, line = served.ll, served.engine, served.line
        assert ll is not None and engine is not None
        while True:
            if ev is None:
                if ll.state == LS_IDLE:  # a job, a due read first, or polling's share
                    if served.pollers != line._pollers:
                        served.pollers = list(line._pollers)
                        engine.set_devices([p.device for p in served.pollers])
                    job = loop_jobs.job_or_wait(line, ll, served.pollers)
                    if isinstance(job, Job):
                        return self._hand_off(served, job)
                    if job is not None:
                        self.shares.hold(served.slot, job)
                ev = ll.run()
            pollers, where, link = served.pollers, line.endpoint.describe(), served.link
            hand_ended(engine, pollers, where)
            if ev == EV_WAITS:
                break
            assert link is not None
            if ev == EV_SPLIT:
                hand_split(pollers, engine.event_device, where)
            elif ev == EV_REPORTS:
                hand_reports(link, pollers, engine.event_device, where)
            elif ev == EV_FAILED:
                self._detach(served)
                hand_failure(link, pollers, engine.event_device, engine.event_errno, where)
                self._lost(served)
                return
            elif ev not in (EV_CYCLE, EV_WAKE, EV_COLLECT):
                raise RuntimeError(f"loop link: unexpected event {ev}")
            ev = None
        if link is not None:
            link.collect()  # the stream's counters (heartbeats, drops) into the stats


# this thread's LoopPool.deferred block (line/loop_pool.py): .workers, to wake at its end
held_wakeups = threading.local()


__all__ = ["DEFAULT_CAPACITY", "LoopLine", "LoopWorker", "held_wakeups", "loop_serves"]
