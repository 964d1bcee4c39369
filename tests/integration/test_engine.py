"""The line engine end to end (csrc/emb_engine.c): a quiet line runs in C, a write
interrupts a pass after the transaction in flight.  DriverModbusRtu against our
simulator over RTU over TCP."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import Any

import pytest

from edgemodbus.datatypes import ItemStatus
from edgemodbus.sim import Simulator
from tests.integration.test_driver import Running, all_ok, device
from tests.waiting import wait_for


@pytest.fixture
def sim() -> Iterator[Simulator]:
    with Simulator([1]) as simulator:
        yield simulator


def _uint16s(n: int, step: int = 2) -> list[dict[str, Any]]:
    return [{"name": f"t{k}", "address": f"hr:{step * k}", "deviceDataType": "UInt16"}
            for k in range(n)]


class MasterCalls:
    """Counts the calls of edgemodbus's own Python functions (the simulator's aside) in
    the threads started while it is installed: here, the line worker."""

    def __init__(self) -> None:
        self.calls = 0
        self.counting = False

    def __enter__(self) -> MasterCalls:
        threading.setprofile(self._hook)
        return self

    def __exit__(self, *exc: object) -> None:
        threading.setprofile(None)  # type: ignore[arg-type]

    def _hook(self, frame: FrameType, event: str, _arg: object) -> None:
        if event == "call" and self.counting:
            name = frame.f_code.co_filename
            if "/edgemodbus/" in name and "/edgemodbus/sim/" not in name:
                self.calls += 1


def test_a_line_whose_values_do_not_change_stays_in_c(sim: Simulator) -> None:
    """20 blocks a cycle, nothing changing: the worker runs no Python per block, and
    (with no snapshot due) none per cycle either."""
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, _uint16s(200, step=3), readCycle=5, maxBlockReadRegisterCount=30,
                 maxMergeAddressGap=2)
    with MasterCalls() as watch, Running(cfg) as drv:
        wait_for(all_ok(cfg))
        before = drv.stats()["cycles"]
        watch.counting = True
        # 20 cycles however slow the machine is (about 0.2 s when it is quiet)
        wait_for(lambda: drv.stats()["cycles"] - before >= 20, timeout=60, what="20 cycles")
        watch.counting = False
        cycles = drv.stats()["cycles"] - before
    assert drv.stats()["requests"] >= 20 * cycles
    assert watch.calls < cycles, (watch.calls, cycles)  # stepping in Python: > 20 a cycle


def test_a_write_waits_only_for_the_transaction_in_flight(sim: Simulator) -> None:
    """A slow slave (20 ms a reply) and 40 blocks a cycle: a write starts after the
    read in flight, not after the rest of the cycle (800 ms)."""
    sim.slave(1).faults.delay = 0.02
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, _uint16s(40, step=10), readCycle=10, maxMergeAddressGap=0,
                 readTimeout=1000)
    with Running(cfg) as drv:
        wait_for(all_ok(cfg), timeout=10)
        took = []
        for k in range(8):
            time.sleep(0.037 * (k + 1))  # pacing: somewhere in the cycle
            start = time.monotonic()
            ok, err = drv.write_address("t5", k)
            took.append(time.monotonic() - start)
            assert ok, err
        assert cfg.address_list[5].value == 7 and cfg.address_list[5].status is ItemStatus.OK
    # the read in flight (<= 20 ms), then the write itself (20 ms), with slack
    assert max(took) < 0.02 + 0.02 + 0.05, took


def test_the_frame_trace_does_not_change_the_path(sim: Simulator,
                                                  caplog: pytest.LogCaptureFixture,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """DEBUG on edgemodbus.line (``-vv``): the engine still reads the line (no block is
    stepped or read in Python), and every frame it sent and received is logged, in
    order, from the trace ring."""
    from edgemodbus.line.link import ContextLink

    python_reads: list[str] = []
    monkeypatch.setattr(ContextLink, "_read", lambda *a: python_reads.append("_read"))
    caplog.set_level("DEBUG", logger="edgemodbus.line")
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, _uint16s(60, step=3), readCycle=5, maxBlockReadRegisterCount=30,
                 maxMergeAddressGap=2)
    with Running(cfg) as drv:
        wait_for(all_ok(cfg))
        before = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= before + 20, what="20 more cycles")
        blocks = drv.stats()["requests"] // max(1, drv.stats()["cycles"])
    assert not python_reads
    assert blocks >= 6
    lines = [r.getMessage() for r in caplog.records if r.name == "edgemodbus.line"]
    tx = [line for line in lines if " TX 01 03 " in line]
    rx = [line for line in lines if " RX 01 03 " in line]
    assert len(tx) >= 20 * blocks and len(rx) >= 20 * blocks
    first = lines.index(tx[0])
    assert " RX 01 03 " in lines[first + 1]  # a request, then its reply


def test_a_traced_frame_is_logged_while_the_engine_idles(sim: Simulator,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    """A slow line whose values do not change (a pass every 4 s, nothing for Python): the
    second pass's frames reach the log within about a second (EMB_TRACE_FLUSH_NS) while
    the engine idles, not with the third pass or at the end."""
    caplog.set_level("DEBUG", logger="edgemodbus.line")
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, _uint16s(3), readCycle=4000)

    def traced() -> int:
        return sum(1 for r in list(caplog.records)
                   if r.name == "edgemodbus.line" and " RX 01 03 " in r.getMessage())

    with Running(cfg) as drv:
        wait_for(all_ok(cfg))
        wait_for(lambda: traced() >= 1, what="the first pass's reply logged")
        wait_for(lambda: drv.stats()["cycles"] >= 2, timeout=15, what="the second pass")
        wait_for(lambda: traced() >= 2, timeout=15, what="the second pass's reply logged")
        assert drv.stats()["cycles"] == 2  # logged before the third pass, not with it
