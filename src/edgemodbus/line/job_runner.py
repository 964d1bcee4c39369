"""How a line worker runs one queued job (mixed into
:class:`~edgemodbus.line.worker.LineWorker`, kept apart for size): the job's future
set once whatever happens (a failure of the worker itself with the job taken fails the
job too: :class:`~edgemodbus.line.jobs.LineWorkerError`), the target backoff, and what
the job owes polling afterwards (line/jobs.py ``job_gate``: as many poll transactions as
it made, and as much line time as it took, while polling is due), and the one place both
engines ask whether the next job may run (:meth:`JobRunner._job_wait`: the thread
engine's worker, line/worker.py, and the loop engine, line/loop_jobs.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

from .._ffi.engine import EngineDevice
from .._ffi.outcomes import LineCounters
from ..errors import ModbusConnectionError
from ..stats import LineStats
from .endpoint import Endpoint
from .jobs import (
    STOP,
    Job,
    LineWorkerError,
    PollLag,
    TargetBackoff,
    answers_of,
    crash_reason,
    job_gate,
    period_of,
)
from .link import Link
from .poller_api import Poller


class JobRunner:
    """The job-running half of a line worker (worker thread only)."""

    __slots__ = ("_changed", "_owed", "_pending", "_polled", "_share_until")  # (LineWorker
    # sets them)

    endpoint: Endpoint
    stats: LineStats
    last_link_error: str | None
    _pollers: list[Poller]
    _pending: int  # jobs queued, not yet taken (under _pending_lock)
    _pending_lock: threading.Lock
    _lag: PollLag
    _backoff: TargetBackoff
    _counters: LineCounters  # what the engine counts (its poll transactions pay _owed)
    _owed: int  # poll transactions owed while polling is due
    _polled: int  # the engine's requests counted when _owed was last set or paid
    _share_until: float  # polling's share of the line after the last job (monotonic)
    _changed: float  # monotonic end of the last job that may have written a slave

    def _job_wait(self, devices: Sequence[EngineDevice]) -> tuple[float | None, float | None]:
        """May the next queued job run now?  The poll transactions the engine made since
        the last job ended pay what it owes, then line/jobs.py ``job_gate`` says: how
        long polling of ``devices`` has been due (None: not due), and until when the
        job waits (None: run it now; inf: until a due read was made)."""
        self._pay_owed()
        return job_gate(devices, time.monotonic(), self._owed, self._share_until)

    def _pay_owed(self) -> None:
        """The engine's poll transactions since the last look pay for the last job's."""
        if self._owed:
            polled = self._counters.counts().requests
            self._owed = max(0, self._owed - (polled - self._polled))
            self._polled = polled

    def _handle(self, item: Any, link: Link | None, late: float | None = None) -> None:
        """Run a queued job (``late``: how long polling has been due meanwhile)."""
        if item is None or item is STOP:
            return
        job: Job = item
        with self._pending_lock:
            self._pending -= 1
        if job.future.set_running_or_notify_cancel():
            try:
                self._run_job(job, link, late)
            except Exception as exc:  # the worker fails with the job taken: so does the job
                if not job.future.done():
                    job.future.set_exception(LineWorkerError(
                        f"{self.endpoint.describe()}: {crash_reason(exc)}"))
                raise

    def _run_job(self, job: Job, link: Link | None, late: float | None) -> None:
        if link is None or not link.is_open:
            job.future.set_exception(ModbusConnectionError(
                f"{self.endpoint.describe()}: link is down ({self.last_link_error})"
            ))
            return
        self.stats.jobs += 1
        devices = [p.device for p in self._pollers]
        self._lag.job_ran(self.stats, late, period_of(devices))
        start, timeouts, sent = time.monotonic(), link.stats.timeouts, link.stats.requests
        slave = job.slave
        try:
            if slave is not None:
                self._backoff.check(slave, start, answers_of(devices, slave))
            self._owed = 1
            result = job.fn(link)
        except BaseException as exc:
            self._backoff.ended(self.stats, slave, exc, start, link.stats.timeouts > timeouts,
                                devices, self.endpoint.describe())
            job.future.set_exception(exc)
        else:
            self._backoff.ended(self.stats, slave, None, start, link.stats.timeouts > timeouts,
                                devices, self.endpoint.describe())
            job.future.set_result(result)
        finally:  # a job of k transactions owes polling k, and as much line time after it
            self._owed = max(self._owed, link.stats.requests - sent)  # (unless it timed out)
            self._polled = self._counters.counts().requests  # (polling pays from here)
            end = time.monotonic()
            self._share_until = 2 * end - start if link.stats.timeouts == timeouts else end
            if not job.reads:
                self._changed = time.monotonic()
        self._lag.job_ended(self.stats, devices, time.monotonic())
        link.flush_reports()

