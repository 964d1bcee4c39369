"""A loop line's jobs off its loop thread (line/loop.py): a write, a forwarded request,
an action, a read on demand or a command runs its transactions on a blocking socket, for
up to its timeout and retries; on the loop thread that would hold every link of the
thread.  So the loop worker takes the line's link out of the loop while its jobs run
(``LoopLink.pause``: not stepped, its socket not watched) and hands them to
:class:`JobThreads`, a few threads per loop worker (started on demand, at most
``cap``, an idle one ends after ``idle`` seconds; never a thread per link).  The job
thread runs the line's queued jobs one at a time, in order (:func:`run_jobs`), and
hands the link back through the loop's wake-up: the loop thread never waits for a job.

The thread engine's rule holds, through the same function (line/job_runner.py
``_job_wait``, line/jobs.py ``job_gate``): a job of k transactions owes due polling k
poll transactions, and one that took t seconds (and got its answers) the next t seconds
while a block falls due in them.  :func:`job_or_wait` applies it at an idle link: the
next job goes to a job thread, or the link reads one due block first (``LoopLink.owed``:
it comes back ``EV_WAKE`` after it, and the reads made pay), or it polls until the share
ends (:class:`Shares`: the loop's turn ends then).  The job thread stops taking jobs by
the same rule (:func:`run_jobs`).  Neither thread waits or spins for it.
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import math
import os
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from .._ffi.engine import EngineDevice
from .jobs import Job, late_by
from .poller_api import Poller

if TYPE_CHECKING:
    from .._ffi.loop import LoopLink
    from .link import Link
    from .worker import LineWorker

log = logging.getLogger("edgemodbus.line")

#: Job threads a loop worker runs at most: a line whose jobs wait for one has its link
#: out of the loop meanwhile (docs/scale.md "The loop engine").
JOB_THREADS = 8
#: A job thread with nothing to do for this long ends.
IDLE_SECONDS = 5.0


_running = threading.local()  # .line: the line whose jobs this job thread runs now


def running_jobs_of() -> object | None:
    """The line whose jobs this thread runs now (None: none; see :func:`run_jobs`)."""
    return getattr(_running, "line", None)


def hold_of(fd: int) -> int:
    """A dup of socket ``fd`` for :func:`cut_off`, -1 without an fd to spare (then a
    stop waits for the job in flight)."""
    try:
        return os.dup(fd)
    except OSError:
        return -1


def let_go(hold: int) -> int:
    """Close a :func:`hold_of` dup (-1: none); -1, for the holder to keep."""
    if hold >= 0:
        os.close(hold)
    return -1


def next_job(line: LineWorker) -> Job | None:
    """The line's next queued job, past the reschedules (None items: a poller attached,
    a new connection) that need no link; None when none is queued."""
    while True:
        try:
            item = line._queue.get_nowait()
        except queue.Empty:
            return None
        if isinstance(item, Job):
            return item


def job_or_wait(line: LineWorker, ll: LoopLink, pollers: Sequence[Poller]
                ) -> Job | float | None:
    """At ``ll``, idle (loop thread): the line's next job to hand to a job thread; or
    the time polling's share of the line ends (the link polls until then, its jobs
    flag off: the caller sets a :class:`Shares` deadline); or None: no job queued, or
    one due read first (``ll.owed`` and ``ll.jobs`` set: the link comes back
    ``EV_WAKE`` once it sent it, or at once when nothing is due)."""
    ll.owed = ll.jobs = False
    if line._queue.empty():
        return None
    _late, wait = line._job_wait([p.device for p in pollers])
    if wait is None:
        return next_job(line)
    if math.isinf(wait):
        ll.owed = ll.jobs = True
        return None
    return wait


def run_jobs(line: LineWorker, link: Link, first: Job, devices: Sequence[EngineDevice],
             leave: Callable[[], bool]) -> int:
    """Run ``first``, then the line's next queued jobs while the rule lets them go
    before polling (line/job_runner.py ``_job_wait``: ``devices`` are the engine's,
    out of the loop, nothing else touches them now), the link stays open and
    ``leave()`` is false.  Job thread.  Returns how many ran."""
    job: Job | None = first
    late = late_by(devices, time.monotonic())
    ran = 0
    _running.line = line  # (a callback of a job is on the line's worker: on_worker)
    try:
        while job is not None:
            line._handle(job, link, late)
            ran += 1
            if leave() or not link.is_open:
                break
            late, wait = line._job_wait(devices)
            if wait is not None:  # polling's turn: the loop reads what is owed first
                break
            job = next_job(line)
    finally:
        _running.line = None
    return ran


class Shares:
    """The loop worker's lines whose next job waits for polling's share of the line to
    end (by slot): the loop's turn ends at the earliest, and then their queues are
    looked at again.  Loop thread only."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int]] = []
        self._at: dict[int, float] = {}

    def hold(self, slot: int, until: float) -> None:
        """Slot ``slot``'s jobs wait until ``until`` (monotonic seconds)."""
        if self._at.get(slot) != until:
            self._at[slot] = until
            heapq.heappush(self._heap, (until, slot))

    def drop(self, slot: int) -> None:
        self._at.pop(slot, None)

    def next_end(self, default: float) -> float:
        """The earliest share's end, ``default`` if none is earlier."""
        heap = self._heap
        while heap and self._at.get(heap[0][1]) != heap[0][0]:
            heapq.heappop(heap)  # moved or dropped
        return min(heap[0][0], default) if heap else default

    def ended(self, now: float) -> list[int]:
        """The slots whose share ended by ``now`` (each told once)."""
        out: list[int] = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            until, slot = heapq.heappop(heap)
            if self._at.get(slot) == until:
                del self._at[slot]
                out.append(slot)
        return out


def cut_off(fd: int) -> None:
    """Shut the socket ``fd`` down both ways (a dup the loop holds while a job has the
    link): the job's transaction fails at once instead of after its timeout (the line
    stops)."""
    if fd < 0:
        return
    with contextlib.suppress(OSError):
        sock = socket.socket(fileno=os.dup(fd))
        try:
            sock.shutdown(socket.SHUT_RDWR)
        finally:
            sock.close()


class JobThreads:
    """At most ``cap`` threads named ``name`` running the tasks submitted, in order of
    submission; started when a task finds no idle thread, ended after ``idle`` seconds
    without a task, or by :meth:`stop` (after the tasks submitted before it).  A thread
    counts as idle from its start and again before a task's ``then`` runs: a task that
    ``then`` hands back (a line's jobs) and is submitted again at once finds it idle,
    not a reason for one more thread."""

    def __init__(self, name: str, cap: int = JOB_THREADS, idle: float = IDLE_SECONDS) -> None:
        if not 1 <= cap <= 256:
            raise ValueError(f"job threads {cap!r}: must be 1..256")
        self.name = name
        self.cap = cap
        self.idle = idle
        self._tasks: deque[tuple[Callable[[], None], Callable[[], None] | None]] = deque()
        self._cond = threading.Condition()
        self._threads: set[threading.Thread] = set()
        self._waiting = 0  # threads idle: waiting for a task, starting, or done with one
        self._made = 0
        self._stopping = False

    def submit(self, task: Callable[[], None], then: Callable[[], None] | None = None
               ) -> None:
        """Run ``task()`` on a job thread, then ``then()`` once the thread counts as idle
        (never blocks; an exception of either is logged)."""
        with self._cond:
            if self._stopping:
                raise RuntimeError(f"{self.name}: stopped")
            self._tasks.append((task, then))
            if len(self._tasks) > self._waiting and len(self._threads) < self.cap:
                self._made += 1
                thread = threading.Thread(target=self._run, daemon=True,
                                          name=f"{self.name} job {self._made}")
                self._threads.add(thread)
                self._waiting += 1  # (idle from its start: it takes this task)
                try:
                    thread.start()
                except RuntimeError:  # no thread to be had: the others take it, if any
                    self._threads.discard(thread)
                    self._waiting -= 1
                    if not self._threads:
                        self._tasks.pop()
                        raise
            else:
                self._cond.notify()

    @property
    def threads(self) -> int:
        with self._cond:
            return len(self._threads)

    def stop(self, timeout: float = 60.0) -> None:
        """Run the tasks submitted, end the threads and wait for them (idempotent)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
            threads = list(self._threads)
        for thread in threads:
            if thread is not threading.current_thread():
                thread.join(timeout)
                if thread.is_alive():
                    raise RuntimeError(f"{thread.name}: did not stop")

    def _run(self) -> None:
        me = threading.current_thread()
        while True:
            with self._cond:  # (counted idle already: by submit, or after its last task)
                deadline = time.monotonic() + self.idle
                while not self._tasks and not self._stopping:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                self._waiting -= 1
                if not self._tasks:
                    self._threads.discard(me)
                    return
                task, then = self._tasks.popleft()
            try:
                task()
            except Exception:  # a bug must not end the thread with tasks waiting
                log.exception("%s: a job task failed", me.name)
            with self._cond:
                self._waiting += 1
            if then is not None:
                try:
                    then()
                except Exception:
                    log.exception("%s: a job task's hand-back failed", me.name)


__all__ = ["IDLE_SECONDS", "JOB_THREADS", "JobThreads", "Shares", "cut_off", "hold_of",
           "job_or_wait", "let_go", "next_job", "run_jobs", "running_jobs_of"]
