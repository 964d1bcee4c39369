"""The job threads of a loop worker (line/loop_jobs.py ``JobThreads``): every task runs
once, in order of submission when one thread serves them, never more than ``cap`` at a
time; a thread starts only when no idle one is free, an idle one ends, ``stop`` runs
what was submitted and leaves no thread behind."""

from __future__ import annotations

import logging
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.line.loop_jobs import JobThreads
from tests.waiting import wait_for


class Gate:
    """Tasks that wait for the test to open them; concurrency and order recorded."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.opened = threading.Event()
        self.running = 0
        self.most = 0
        self.order: list[int] = []

    def task(self, k: int, block: bool = True) -> None:
        with self.lock:
            self.running += 1
            self.most = max(self.most, self.running)
        if block:
            assert self.opened.wait(30), "the gate never opened"
        with self.lock:
            self.running -= 1
            self.order.append(k)


@settings(max_examples=25, deadline=None)
@given(cap=st.integers(1, 4), blocks=st.lists(st.booleans(), min_size=1, max_size=12))
def test_every_task_runs_once_and_never_more_than_cap_at_once(cap: int,
                                                               blocks: list[bool]) -> None:
    gate = Gate()
    jobs = JobThreads("test", cap=cap, idle=30)
    try:
        for k, block in enumerate(blocks):
            jobs.submit(lambda k=k, block=block: gate.task(k, block))
        assert jobs.threads <= cap
        wait_for(lambda: gate.running == min(cap, sum(blocks)) or len(gate.order) == len(blocks),
                 15, "the tasks taken")
        gate.opened.set()
    finally:
        gate.opened.set()
        jobs.stop()
    assert sorted(gate.order) == list(range(len(blocks)))
    assert gate.most <= cap
    assert jobs.threads == 0
    if cap == 1:
        assert gate.order == list(range(len(blocks)))


def test_a_task_finds_the_idle_thread_instead_of_starting_one() -> None:
    jobs = JobThreads("test", cap=4, idle=30)
    try:
        done = threading.Event()
        jobs.submit(done.set)
        assert done.wait(15)
        wait_for(lambda: jobs._waiting == 1, 15, "the thread idle")
        for _ in range(5):  # one after the other: the idle thread takes each
            again = threading.Event()
            jobs.submit(again.set)
            assert again.wait(15)
            wait_for(lambda: jobs._waiting == 1, 15, "the thread idle again")
        assert jobs.threads == 1
    finally:
        jobs.stop()


def test_a_task_submitted_again_from_its_hand_back_keeps_one_thread() -> None:
    """A line's jobs go back and forth (line/loop.py: the hand-back wakes the loop,
    which submits the line's next jobs at once): the thread that ran them is idle by
    then, so no thread is added per job (the loop's dead-forward soak grew from 6 to 9-10
    threads for one master's forwards)."""
    jobs = JobThreads("test", cap=8, idle=30)
    done = threading.Event()
    left = [200]

    def task() -> None:
        left[0] -= 1

    def back() -> None:  # (on the job thread, as the loop's wake-up would hand it on)
        if left[0] > 0:
            threading.Thread(target=jobs.submit, args=(task, back)).start()
        else:
            done.set()

    try:
        jobs.submit(task, back)
        assert done.wait(30)
        assert jobs.threads == 1
    finally:
        jobs.stop()


def test_an_idle_thread_ends() -> None:
    jobs = JobThreads("test", cap=2, idle=0.2)
    ran = threading.Event()
    jobs.submit(ran.set)
    assert ran.wait(15)
    wait_for(lambda: jobs.threads == 0, 15, "the idle thread ended")
    again = threading.Event()
    jobs.submit(again.set)  # a new one starts for the next task
    assert again.wait(15)
    jobs.stop()
    assert jobs.threads == 0


def test_stop_runs_what_was_submitted_and_refuses_more() -> None:
    gate = Gate()
    jobs = JobThreads("edgemodbus-loop 9", cap=1, idle=30)
    for k in range(3):
        jobs.submit(lambda k=k: gate.task(k))
    wait_for(lambda: gate.running == 1, 15, "the first task running")
    stopper = threading.Thread(target=jobs.stop)
    stopper.start()
    gate.opened.set()
    stopper.join(30)
    assert not stopper.is_alive()
    assert gate.order == [0, 1, 2]
    with pytest.raises(RuntimeError, match="edgemodbus-loop 9: stopped"):
        jobs.submit(lambda: None)


def test_a_failing_task_is_logged_and_the_next_one_runs(
        caplog: pytest.LogCaptureFixture) -> None:
    jobs = JobThreads("test", cap=1, idle=30)
    ran = threading.Event()

    def bad() -> None:
        raise ValueError("boom")

    try:
        jobs.submit(bad)
        jobs.submit(ran.set)
        assert ran.wait(15)
    finally:
        jobs.stop()
    assert any(r.levelno == logging.ERROR and "a job task failed" in r.getMessage()
               for r in caplog.records)


def test_the_cap_is_checked() -> None:
    with pytest.raises(ValueError, match=r"job threads 0: must be 1\.\.256"):
        JobThreads("test", cap=0)
