"""The rule a queued job waits by (line/jobs.py ``job_gate``) keeps at least half of a
polled device's rate under any flood of jobs, short or long, few or many transactions
(issue #25).  A property over a model of the line: one device polled every ``period``
(each poll transaction ``poll`` seconds), a queue that is never empty, jobs of ``k``
transactions of ``t`` seconds each; the worker's loop as line/worker.py ``_serve`` runs
it (a job when the gate says so, else the engine: one owed read, or polling until
polling's share ends), the engine's own scheduling simplified to one block."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.line.jobs import job_gate

HORIZON = 30.0  # seconds of line time simulated, at least (and 20 of the longest jobs)


@dataclass
class Device:
    """What job_gate reads of an EngineDevice."""

    due: float
    period: float
    active: bool = True


def polled_rate(period: float, poll: float, jobs: list[tuple[int, float]]) -> float:
    """Poll transactions per second of the device over HORIZON with the jobs' flood."""
    horizon = max(HORIZON, 20 * max(k * t for k, t in jobs))
    dev = Device(0.0, period)
    now, owed, share, polls = 0.0, 0, 0.0, 0
    flood = itertools.cycle(jobs)

    def read() -> None:
        nonlocal now, owed, polls
        start = max(now, dev.due)
        now = start + poll
        polls += 1
        owed = max(0, owed - 1)
        dev.due = start + period  # the next pass: a period after this one began

    while now < horizon:
        _late, wait = job_gate([dev], now, owed, share)
        if wait is None:  # the job runs: k transactions
            k, t = next(flood)
            start = now
            now += k * t
            owed = max(owed, k)
            share = 2 * now - start
        elif math.isinf(wait):  # a block is due now: the engine reads it, then comes back
            read()
        else:  # polling's share: the engine polls what falls due until then
            while dev.due <= wait:
                read()
            now = max(now, wait)
    return polls / now


@settings(max_examples=300, deadline=None)
@given(period=st.floats(0.02, 1.0), poll=st.floats(0.001, 0.05),
       jobs=st.lists(st.tuples(st.integers(1, 30), st.floats(0.001, 0.2)), min_size=1,
                     max_size=5))
def test_polling_keeps_half_its_rate_under_any_flood_of_jobs(
        period: float, poll: float, jobs: list[tuple[int, float]]) -> None:
    quiet = 1.0 / max(period, poll)
    rate = polled_rate(period, poll, jobs)
    # (half, less what one job at the horizon's end and the rounding of cycles take)
    assert rate >= 0.45 * quiet, (rate, quiet)


def test_a_read_on_demand_of_many_blocks_is_not_one_job() -> None:
    """The case the rule was made for: 24 transactions of 12 ms against a 100 ms device
    (the old rule, one job between two poll transactions, gave it about a quarter)."""
    rate = polled_rate(0.1, 0.012, [(24, 0.012)])
    assert rate >= 5.0, rate


def test_short_jobs_alternate_with_due_reads() -> None:
    """A job of one short transaction owes one read while a block is due: a flood of
    them leaves a device that is always due half the transactions."""
    dev = Device(0.0, 0.01)
    assert job_gate([dev], 1.0, 1, 0.0) == (1.0, math.inf)  # due, owed: wait for a read
    assert job_gate([dev], 1.0, 0, 0.0) == (1.0, None)  # the read made: the job runs
    idle = Device(5.0, 1.0)
    assert job_gate([idle], 1.0, 3, 0.0) == (None, None)  # nothing due: the jobs go
    assert job_gate([idle], 1.0, 3, 6.0) == (None, 6.0)  # due within the share: wait
    assert job_gate([idle], 1.0, 0, 4.0) == (None, None)  # due after the share ends
