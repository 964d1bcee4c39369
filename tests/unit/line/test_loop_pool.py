"""The loop engine's pool and its settings (line/loop.py, line/dtu_registry.py): bad
values named, DTUs the loop cannot serve refused, and a worker thread that starts with
its first line and stops with its last."""

from __future__ import annotations

import threading

import pytest

from edgemodbus.errors import ModbusConnectionError
from edgemodbus.line import DtuRegistry
from edgemodbus.line.endpoint import DtuEndpoint
from edgemodbus.line.link import Link
from edgemodbus.line.loop import LoopLine, LoopPool, loop_serves
from edgemodbus.line.worker import LineWorker
from tests.waiting import wait_for


class Absent:
    """A connector whose DTU never dials in."""

    def __init__(self) -> None:
        self.tries = 0

    def open(self, line: LineWorker) -> Link:
        self.tries += 1
        raise ModbusConnectionError("DTU not connected (test)")


def loop_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("edgemodbus-loop")]


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match=r"engine 'fast': must be one of thread, loop"):
        DtuRegistry().set_engine("fast")
    with pytest.raises(ValueError, match=r"loopThreads 0: must be an integer 1\.\.1024"):
        LoopPool().configure(0)


def test_only_plain_rtu_dtus_go_to_the_loop() -> None:
    plain = DtuEndpoint("127.0.0.1", 1, "A")
    wrapped = DtuEndpoint("127.0.0.1", 1, "B", framing="wrapped-report")
    echo = DtuEndpoint("127.0.0.1", 1, "C", echo=True)
    assert loop_serves(plain) and not loop_serves(wrapped) and not loop_serves(echo)
    with pytest.raises(ValueError, match=r"wrapped: engine 'loop' serves plain RTU DTUs"):
        LoopLine(wrapped, None, Absent(), LoopPool(1))


def test_lines_share_a_worker_that_stops_with_the_last() -> None:
    pool = LoopPool(1)
    connectors = [Absent(), Absent()]
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, f"D{k}"), None, c, pool)
             for k, c in enumerate(connectors)]
    before = loop_threads()
    for line in lines:
        line.start()
    assert pool.workers == 1 and len(loop_threads()) == len(before) + 1
    assert all(c.tries >= 1 for c in connectors)  # each tried its connection at once
    assert all(line.last_link_error == "DTU not connected (test)" for line in lines)
    future = lines[0].write_register(1, 0, 5)  # a job while the link is down fails
    with pytest.raises(ModbusConnectionError, match="link is down"):
        future.result(10)
    lines[0].stop()
    assert pool.workers == 1
    lines[1].stop()
    assert pool.workers == 0 and loop_threads() == before
    lines[1].stop()  # idempotent


def test_a_line_stopped_on_its_loop_thread_goes_at_the_next_turn() -> None:
    """A callback on the loop thread (here: a failed job's) stops the worker's last
    line: nothing waits for itself, and the worker's thread ends."""
    pool = LoopPool(1)
    before = loop_threads()
    line = LoopLine(DtuEndpoint("127.0.0.1", 1, "S"), None, Absent(), pool)
    line.start()
    stopped_on: list[str] = []

    def stop_here(_future: object) -> None:
        stopped_on.append(threading.current_thread().name)
        line.stop()

    line.write_register(1, 0, 5).add_done_callback(stop_here)
    wait_for(lambda: loop_threads() == before, what="the loop thread gone")
    assert stopped_on == ["edgemodbus-loop 1"] and pool.workers == 0
