"""A loop line's jobs off its loop thread (line/loop.py): a write, a forwarded request,
an action, a read on demand or a command runs its transactions on a blocking socket, for
up to its timeout and retries; on the loop thread that would hold every link of the
thread.  So the loop worker takes the line's link out of the loop while its jobs run
(``LoopLink.pause``: not stepped, its socket not watched) and hands them to
:class:`JobThreads`, a few threads per loop worker (started on demand, at most
``cap``, an idle one ends after ``idle`` seconds; never a thread per link).  The job
thread runs the line's queued jobs one at a time, in order (:func:`run_jobs`), and
hands the link back through the loop's wake-up: the loop thread never waits for a job.

The fairness rule of the thread engine holds (csrc/emb_engine.c, line/worker.py
``_serve``): while a block of the line is due, one job between two poll transactions;
the link reads what is due (``LoopLink.owed``) before it takes the next job.
"""

from __future__ import annotations

import contextlib
import logging
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

if TYPE_CHECKING:
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


def run_jobs(line: LineWorker, link: Link, first: Job, devices: Sequence[EngineDevice],
             leave: Callable[[], bool]) -> int:
    """Run ``first``, then the line's next queued jobs while no block of ``devices``
    (the engine's, out of the loop: nothing else touches them now) is due, the link
    stays open and ``leave()`` is false.  Job thread.  Returns how many ran."""
    job: Job | None = first
    ran = 0
    _running.line = line  # (a callback of a job is on the line's worker: on_worker)
    try:
        while job is not None:
            line._handle(job, link, late_by(devices, time.monotonic()))
            ran += 1
            if leave() or not link.is_open or late_by(devices, time.monotonic()) is not None:
                break  # the loop reads what is due first (owed), or closes the line
            job = next_job(line)
    finally:
        _running.line = None
    return ran


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
    without a task, or by :meth:`stop` (after the tasks submitted before it)."""

    def __init__(self, name: str, cap: int = JOB_THREADS, idle: float = IDLE_SECONDS) -> None:
        if not 1 <= cap <= 256:
            raise ValueError(f"job threads {cap!r}: must be 1..256")
        self.name = name
        self.cap = cap
        self.idle = idle
        self._tasks: deque[Callable[[], None]] = deque()
        self._cond = threading.Condition()
        self._threads: set[threading.Thread] = set()
        self._waiting = 0  # threads waiting for a task
        self._made = 0
        self._stopping = False

    def submit(self, task: Callable[[], None]) -> None:
        """Run ``task()`` on a job thread (never blocks; an exception is logged)."""
        with self._cond:
            if self._stopping:
                raise RuntimeError(f"{self.name}: stopped")
            self._tasks.append(task)
            if len(self._tasks) > self._waiting and len(self._threads) < self.cap:
                self._made += 1
                thread = threading.Thread(target=self._run, daemon=True,
                                          name=f"{self.name} job {self._made}")
                self._threads.add(thread)
                try:
                    thread.start()
                except RuntimeError:  # no thread to be had: the others take it, if any
                    self._threads.discard(thread)
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
            with self._cond:
                deadline = time.monotonic() + self.idle
                self._waiting += 1
                while not self._tasks and not self._stopping:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
                self._waiting -= 1
                if not self._tasks:
                    self._threads.discard(me)
                    return
                task = self._tasks.popleft()
            try:
                task()
            except Exception:  # a bug must not end the thread with tasks waiting
                log.exception("%s: a job task failed", me.name)


__all__ = ["IDLE_SECONDS", "JOB_THREADS", "JobThreads", "cut_off", "hold_of", "let_go", "next_job",
           "run_jobs", "running_jobs_of"]
