"""The process's loop workers (line/loop.py): how many, which one serves a new line, and
starting many lines at once without a round trip to a loop thread each
(:meth:`LoopPool.deferred`, used by edgemodbus.bulk).

:data:`pool` is the process's: the DTU registry and the line registry hand it their
loop lines; ``loopThreads`` sizes it (line/dtu_registry.py: the largest asked wins).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import contextmanager

from .loop import DEFAULT_CAPACITY, LoopLine, LoopWorker, held_wakeups

log = logging.getLogger("edgemodbus.line")


class LoopPool:
    """The process's loop workers: ``threads`` (default: the cores), each line on the
    least loaded with room (``capacity`` lines; when every worker is full, one more
    starts, past ``threads``); a worker starts with its first line, stops with its last."""

    def __init__(self, threads: int | None = None, capacity: int = DEFAULT_CAPACITY) -> None:
        self.threads = threads or os.cpu_count() or 1
        self.capacity = capacity
        self._deferred = threading.local()  # .pending: the adds of deferred()
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
        added = worker.add(line)
        pending: list[Future[None]] | None = getattr(self._deferred, "pending", None)
        if pending is None:
            added.result()
        else:  # the worker takes its inbox before the news of a line: it is there first
            pending.append(added)
        return worker

    @contextmanager
    def deferred(self) -> Iterator[None]:
        """Lines started inside (on this thread) are not waited for one by one (a round
        trip to their loop thread each), and their loop threads are not woken while the
        block runs (each wake-up hands them the GIL): at the end they are woken and the
        lines waited for, all at once; then the first failure is raised (the lines stay
        started).  A job (a write, a read, a new plan) or a stop inside wakes its loop
        thread as ever."""
        previous = getattr(self._deferred, "pending", None)
        pending: list[Future[None]] = []
        self._deferred.pending = pending
        outer: set[LoopWorker] | None = getattr(held_wakeups, "workers", None)
        held: set[LoopWorker] = set()
        held_wakeups.workers = held
        try:
            yield
        finally:
            self._deferred.pending = previous
            held_wakeups.workers = outer
            for worker in held:
                worker.wake_now()
            failures = [exc for f in pending if (exc := f.exception(30)) is not None]
        if failures:  # (not over an exception of the block's own)
            raise failures[0]

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

__all__ = ["LoopPool", "pool"]
