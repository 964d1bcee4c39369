"""Loop-engine lines started in bulk (line/loop_pool.py ``LoopPool.deferred``, used by
edgemodbus/bulk.py): a start does not wait for its loop thread, yet every line is
served, a job queued right after its start included (the worker takes its inbox before
the news of its lines), and the block ends once every line is on its worker."""

from __future__ import annotations

import gc
import threading

import pytest

from edgemodbus.bulk import starting_in_bulk
from edgemodbus.errors import ModbusConnectionError
from edgemodbus.line.endpoint import DtuEndpoint
from edgemodbus.line.link import Link
from edgemodbus.line.loop import LoopLine
from edgemodbus.line.loop_pool import LoopPool
from edgemodbus.line.worker import LineWorker


class Absent:
    """A connector whose DTU never dials in; counts the tries."""

    def __init__(self) -> None:
        self.tries = 0

    def open(self, line: LineWorker) -> Link:
        self.tries += 1
        raise ModbusConnectionError("DTU not connected (test)")


def test_lines_started_in_bulk_are_all_served_and_their_first_jobs_run() -> None:
    pool = LoopPool(2)
    connectors = [Absent() for _ in range(200)]
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, f"B{k}"), None, c, pool)
             for k, c in enumerate(connectors)]
    futures = []
    try:
        with pool.deferred():
            for line in lines:
                line.start()
                futures.append(line.write_register(1, 0, 5))  # news right after the add
        # the block's end waited for every add: each line tried its connection
        assert all(c.tries >= 1 for c in connectors)
        for future in futures:
            with pytest.raises(ModbusConnectionError, match="link is down"):
                future.result(30)
    finally:
        for line in lines:
            line.stop()
    assert pool.workers == 0


def test_starting_in_bulk_pauses_the_collector_and_puts_it_back() -> None:
    assert gc.isenabled()
    with starting_in_bulk():
        assert not gc.isenabled()
    assert gc.isenabled()
    gc.disable()
    try:
        with starting_in_bulk():
            pass
        assert not gc.isenabled()  # as it was
    finally:
        gc.enable()


def test_a_start_outside_a_bulk_block_still_waits_for_its_loop_thread() -> None:
    pool = LoopPool(1)
    connector = Absent()
    line = LoopLine(DtuEndpoint("127.0.0.1", 1, "W"), None, connector, pool)
    try:
        line.start()
        assert connector.tries >= 1
        assert threading.current_thread() is threading.main_thread()
    finally:
        line.stop()


def test_a_line_past_the_loop_threads_capacity_gets_a_worker_of_its_own_in_bulk() -> None:
    """Inside a bulk block too, a line past every worker's capacity starts one more
    worker (before, the loop thread failed the add: IndexError 'pop from empty list',
    raised at the block's end)."""
    pool = LoopPool(1, capacity=2)
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, f"C{k}"), None, Absent(), pool)
             for k in range(3)]
    try:
        with pool.deferred():
            for line in lines:
                line.start()
        assert pool.workers == 2
    finally:
        for line in lines:
            line.stop()
    assert pool.workers == 0


def test_a_job_or_a_stop_inside_a_bulk_block_is_not_held_to_its_end() -> None:
    """Only the adds and attaches wait for the block's end: a job someone waits for
    (here a write) and a stop wake the loop thread at once."""
    pool = LoopPool(1)
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, f"J{k}"), None, Absent(), pool)
             for k in range(3)]
    try:
        with pool.deferred():
            for line in lines:
                line.start()
            with pytest.raises(ModbusConnectionError, match="link is down"):
                lines[0].write_register(1, 0, 5).result(30)
            lines[1].stop()  # waits for its loop thread: woken, not held
    finally:
        for line in lines:
            line.stop()
    assert pool.workers == 0
