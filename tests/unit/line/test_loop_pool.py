"""The loop engine's pool and its settings (line/loop.py, line/dtu_registry.py): bad
values named, DTUs the loop cannot serve refused, and a worker thread that starts with
its first line and stops with its last."""

from __future__ import annotations

import threading

import pytest

from edgemodbus.errors import ModbusConnectionError
from edgemodbus.line import DtuRegistry
from edgemodbus.line.endpoint import DtuEndpoint, LineTiming
from edgemodbus.line.link import Link
from edgemodbus.line.loop import LoopLine, loop_serves
from edgemodbus.line.loop_pool import LoopPool
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


def test_every_dtu_stream_kind_goes_to_the_loop() -> None:
    """Plain, wrapped and echoing DTUs are all served by the loop (csrc/emb_loop_link.c
    frames each); a framing it does not know is refused by name."""
    plain = DtuEndpoint("127.0.0.1", 1, "A")
    wrapped = DtuEndpoint("127.0.0.1", 1, "B", framing="wrapped-report")
    echo = DtuEndpoint("127.0.0.1", 1, "C", echo=True)
    assert loop_serves(plain) and loop_serves(wrapped) and loop_serves(echo)
    other = DtuEndpoint("127.0.0.1", 1, "D", framing="ascii")
    assert not loop_serves(other)
    with pytest.raises(ValueError, match=r"framing 'ascii': engine 'loop' serves framing rtu "
                                         r"and wrapped-report; use engine 'thread'"):
        LoopLine(other, None, Absent(), LoopPool(1))


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
        name = threading.current_thread().name
        if not name.startswith("edgemodbus-loop"):
            # the job failed before the callback was attached (the line is down), so
            # the callback ran here: ask again until it runs on the loop thread
            line.write_register(1, 0, 5).add_done_callback(stop_here)
            return
        stopped_on.append(name)
        line.stop()

    line.write_register(1, 0, 5).add_done_callback(stop_here)
    wait_for(lambda: loop_threads() == before, what="the loop thread gone")
    assert stopped_on == ["edgemodbus-loop 1"] and pool.workers == 0


class Buggy(Absent):
    """A connector with a bug the first time: not a connection error."""

    def open(self, line: LineWorker) -> Link:
        self.tries += 1
        if self.tries == 1:
            raise RuntimeError("bug")
        return super().open(line)


def test_an_unexpected_error_costs_its_line_only_and_the_line_tries_again() -> None:
    pool = LoopPool(1)
    buggy, calm = Buggy(), Absent()
    quick = LineTiming(reconnect_interval=0.05, max_backoff=0.1)
    lines = [LoopLine(DtuEndpoint("127.0.0.1", 1, name), quick, connector, pool)
             for name, connector in (("B", buggy), ("C", calm))]
    for line in lines:
        line.start()
    try:
        assert lines[0].stats.worker_errors == 1
        assert lines[0].last_link_error == "line worker error: RuntimeError: bug"
        wait_for(lambda: buggy.tries >= 3, what="the buggy line trying again")
        assert lines[0].last_link_error == "DTU not connected (test)"
        assert lines[1].stats.worker_errors == 0 and calm.tries >= 1
    finally:
        for line in lines:
            line.stop()


class _EndingThread:
    """A worker's thread seen alive by stop() that then ends (its loop closed by then):
    what a second stop() meets while the first one's thread finishes."""

    def __init__(self) -> None:
        self.asked = 0

    def is_alive(self) -> bool:
        self.asked += 1
        return self.asked == 1

    def join(self, timeout: float | None = None) -> None:
        return None


def test_a_stop_racing_the_thread_that_closes_the_loop_is_quiet() -> None:
    """It raised OSError (loop: cannot wake: Bad file descriptor) out of
    driver.stop_device (found by tests/integration/test_differential.py on the loop)."""
    from edgemodbus.line.loop import LoopWorker

    worker = LoopWorker("test-loop-stop")
    worker.stop()
    assert not worker.thread.is_alive()
    worker.thread = _EndingThread()  # type: ignore[assignment]
    worker.stop()
