"""Jobs on a line's queue, and what bounds the line time they take from polling.

* :class:`Job`: a function the worker runs on the link (a write, a forwarded request, a
  re-plan), its future, and the slave it addresses (forwarded requests, writes);
* :class:`TargetBackoff`: a slave that did not answer a forwarded request or a write is
  treated like a dead slave: later forwards and writes to it fail at once
  (``TargetBackoffError``, a gateway answers 0B) for a backoff interval instead of
  costing the line a timeout and a settle each; the interval is four times what the
  failure cost the line (so a dead target takes at most a fifth of the line), doubling
  per failure in a row up to the line's maxBackoff, and ends early when the slave
  answers anything (a poll of a device on that slave counts);
* :class:`LineWorkerError`, :func:`crash_reason`, :func:`reconnect_delay`: what a line
  worker that recovers from an unexpected error tells and when it tries again;
* :class:`PollLag`: the counters and the rate-limited WARNING of jobs that run while
  polling is due (the fairness rule itself is in the worker and csrc/emb_engine.c: while
  a block is due, at most one job between two poll transactions).
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from .._ffi.engine import EngineDevice
from ..errors import ModbusConnectionError, TargetBackoffError
from .endpoint import LineTiming
from .forward import QueuedTooLongError
from .log_limit import LogLimiter

#: Jobs to a slave (writes, forwards) a line holds at most, queued and not yet taken;
#: one more fails with LineBusyError.
MAX_PENDING = 64
#: A failed target's backoff is this many times what the failure cost the line.
BACKOFF_FACTOR = 4.0
#: Characters of an unexpected error's message in the reason the devices show.
MAX_REASON = 200

log = logging.getLogger("edgemodbus.line")

STOP = object()
"""Queued to end the worker."""


@dataclass
class Job:
    fn: Callable[[Any], Any]  # fn(link)
    future: Future[Any]
    reads: bool = False  # changes nothing on a slave (read coalescing keeps its data)
    slave: int | None = None  # the slave it addresses: target backoff applies


@dataclass
class _Dead:
    until: float
    backoff: float
    marker: int  # the slave's polled responses when it failed


class TargetBackoff:
    """Slaves of one line whose last forwarded request timed out (worker thread only)."""

    def __init__(self, max_backoff: float) -> None:
        self.max_backoff = max_backoff
        self._dead: dict[int, _Dead] = {}

    def check(self, slave: int, now: float, marker: int) -> None:
        """Raise :class:`TargetBackoffError` while ``slave`` is backing off and has not
        answered a poll since (``marker``: its devices' responses, summed)."""
        dead = self._dead.get(slave)
        if dead is None:
            return
        if marker != dead.marker:  # a poll of it got an answer: alive again
            del self._dead[slave]
            return
        if now < dead.until:
            raise TargetBackoffError(
                f"slave {slave} did not answer a forwarded request; requests to it are "
                f"not sent for {dead.until - now:.1f} s more (backoff {dead.backoff:.1f} s)")

    def failed(self, slave: int, now: float, cost: float, marker: int) -> float:
        """A request to ``slave`` timed out after costing the line ``cost`` seconds:
        back off (doubling while it stays dead); returns the interval."""
        dead = self._dead.get(slave)
        base = BACKOFF_FACTOR * max(cost, 0.05)
        backoff = base if dead is None else max(base, 2 * dead.backoff)
        backoff = min(backoff, max(self.max_backoff, base))
        self._dead[slave] = _Dead(now + backoff, backoff, marker)
        return backoff

    def settled(self, slave: int, exc: BaseException | None, timed_out: bool, now: float,
                cost: float, marker: int) -> float | None:
        """A job to ``slave`` ended with ``exc`` (None: it succeeded) after ``cost``
        seconds of line time; ``timed_out``: a request of it got no answer (the link
        counted a timeout).  A timeout backs off (the interval is returned); any other
        end (a reply, a bad one, the link lost) ends the backoff; a forward that never
        went out (its time ran out in the queue) changes nothing."""
        if timed_out:
            return self.failed(slave, now, cost, marker)
        if not isinstance(exc, QueuedTooLongError | TargetBackoffError):
            self._dead.pop(slave, None)
        return None

    def ended(self, stats: Any, slave: int | None, exc: BaseException | None, start: float,
              timed_out: bool, devices: Sequence[EngineDevice], line: str) -> None:
        """A job to ``slave`` on ``line`` ended (``timed_out``: a request of it got no
        answer): count a backoff (``stats``), or start or end one."""
        if isinstance(exc, TargetBackoffError):
            stats.target_backoffs += 1
        elif slave is not None:
            now = time.monotonic()
            backoff = self.settled(slave, exc, timed_out, now, now - start,
                                   answers_of(devices, slave))
            if backoff is not None:
                log.info("%s: slave %d did not answer: requests to it fail at once for "
                         "%.1f s", line, slave, backoff)

    def backing_off(self) -> list[int]:
        return sorted(self._dead)


class PollLag:
    """Jobs and polling: a job that starts while polling is due counts in the line's
    ``jobsAheadOfPolls``; one that leaves polling late by more than its own scan rate
    when it ends (the time it took included: one 200 ms forward between two polls of a
    100 ms device delays it past its cycle) counts in ``pollsDelayed`` and logs a
    WARNING (a few per 10 s, then a summary)."""

    def __init__(self, logger: logging.Logger, line: str) -> None:
        self._limiter = LogLimiter(logger)
        self._line = line

    def job_ran(self, stats: Any, late: float | None, period: float) -> None:
        """A job starts; ``late``: how long polling had been due then (None: not due)."""
        if late is not None:
            stats.jobs_ahead_of_polls += 1

    def job_ended(self, stats: Any, devices: Sequence[EngineDevice], now: float) -> None:
        """A job ended at ``now``: is polling (of ``devices``) late past its cycle?"""
        late, period = late_by(devices, now), period_of(devices)
        if late is not None and late > period > 0:
            stats.polls_delayed += 1
            self._limiter.event(logging.WARNING, "polls delayed by queued jobs", self._line,
                                "%s: queued jobs delay polling: %.2f s late (scan rate "
                                "%.2f s); jobs waiting on the line", self._line, late, period)
        self._limiter.flush()


class LineWorkerError(ModbusConnectionError):
    """A job failed because its line's worker failed (an unexpected error: the line
    restarts); a gateway answers a forwarded request 0B (serve/server.py), as issue #25
    asks, not 0A (a path that is down)."""


def crash_reason(exc: BaseException) -> str:
    """The one-line reason of a worker's unexpected error: the devices' status and the
    jobs' failure say it (the log line has the traceback)."""
    text = str(exc).strip().splitlines()
    first = text[0] if text else ""
    if len(first) > MAX_REASON:
        first = first[:MAX_REASON - 3] + "..."
    return f"line worker error: {type(exc).__name__}" + (f": {first}" if first else "")


def reconnect_delay(timing: LineTiming, failures: int) -> float:
    """Wait before the next connect: reconnectInterval, doubled per failed connect in
    a row up to maxBackoff, with +-20 % jitter so that lines do not reconnect in step."""
    base = timing.reconnect_interval * 2.0 ** max(0, min(failures - 1, 30))
    base = max(timing.reconnect_interval, min(base, timing.max_backoff))
    return base * random.uniform(0.8, 1.2)


def job_gate(devices: Sequence[EngineDevice], now: float, owed: int,
             share_until: float) -> tuple[float | None, float | None]:
    """May a queued job run at ``now``?  Returns how long polling has been due (None:
    not due) and, when the job must wait, until when at most (None: run it now):

    * ``share_until`` (polling's share: the last job got its answers and ended as long
      before it as it took) while a block falls due before then: a 300 ms job costs a
      100 ms device three cycles, and its next three polls go before the next job;
    * inf, while a block is due now and ``owed`` poll transactions are owed (the last
      job made that many): the engine comes back once it read one.

    So a flood of short jobs gets one job between two poll transactions, and a flood of
    long ones (reads on demand of many blocks, a slow slave's forwards) about half the
    line while polling is due.  A job that timed out gives no share (its slave's
    backoff, :class:`TargetBackoff`, bounds what it costs): the answers 0B of the
    backoff go at once."""
    late = late_by(devices, now)
    if now < share_until and late_by(devices, share_until) is not None:
        return late, share_until
    if owed and late is not None:
        return late, float("inf")
    return late, None


def late_by(devices: Sequence[EngineDevice], now: float) -> float | None:
    """How long polling of ``devices`` has been due at ``now`` (None: nothing due)."""
    due = min((d.due for d in devices if d.active), default=float("inf"))
    return now - due if now >= due else None


def period_of(devices: Sequence[EngineDevice]) -> float:
    """The scan rate of the device due first (0: none polled)."""
    active = [d for d in devices if d.active]
    return min(active, key=lambda d: d.due).period if active else 0.0


def answers_of(devices: Sequence[EngineDevice], slave: int) -> int:
    """Responses of the devices polling ``slave``, summed: they grow while it answers."""
    return sum(d.counts().responses for d in devices if d.slave == slave)
