"""Wrapped and echoing DTUs on the loop engine, end to end (listen mode, ``engine:
"loop"``): the line is a LoopLine on a loop thread (no line thread of its own), polled
values are exact, and wrapped reports reach the items as on a line worker (the same
hand-over: line/loop_events.py hand_reports).  The DTUs are our simulator in DTU-client
mode; the blocking engine's behaviour for the same cases is in test_wrapped_link.py and
test_faults.py."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.protocol.wrapped import wrap
from edgemodbus.sim import Simulator, default_register
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.integration.test_wrapped_link import running as running_one
from tests.integration.test_wrapped_link import value_of, wrapped_device
from tests.waiting import wait_for


def _line_threads(dtu_id: str) -> list[str]:
    return [t.name for t in threading.enumerate() if dtu_id in t.name]


def test_a_wrapped_mcu_is_polled_and_its_reports_applied_on_a_loop_thread() -> None:
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU7", "registration": "text",
                          "readCycle": 100, "engine": "loop", "loopThreads": 1})
    seen: list[tuple[str, Any]] = []
    with Simulator(slaves=[1]) as sim, running_one(
        cfg, address_updated_callback=lambda it: seen.append((it.name, it.value))
    ) as drv:
        assert not _line_threads("MCU7")  # served by a loop thread
        client = sim.dial("127.0.0.1", port, registration=b"MCU7", wrapped=True)
        wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                 what="polled values on the loop engine")
        assert [it.value for it in cfg.address_list] == [default_register(1, a)
                                                         for a in (1, 2, 30, 80)]
        # a report of registers the poll reads: its values reach the items
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 80, [4711])
        client.push_report(1, Area.HOLDING_REGISTER, 80, 1)
        wait_for(lambda: ("r80", 4711) in seen, what="the report applied")
        wait_for(lambda: drv.stats()["reports"] >= 1, what="the report counted")
        stats = drv.stats()
        assert stats["timeouts"] == 0 and stats["protocolErrors"] == 0
        assert not _line_threads("MCU7")


def test_an_echoing_dtu_is_read_with_the_echo_option_on_a_loop_thread() -> None:
    port = free_port()
    # timeouts far above a loaded machine's stall of the simulator between the echo and
    # the reply (the default 300/50 ms are not: the test failed in a run beside two busy
    # processes, and it asserts no timeout)
    cfg = dtu_device(port, "ECHO1", 1, echo=True, engine="loop", loopThreads=1,
                     readTimeout=3000, byteTimeout=1000)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        sim.slave(1).set_faults(echo_request=True)
        sim.dial("127.0.0.1", port, registration=b"ECHO1")
        wait_for(ok(cfg), what="values through the echo on the loop engine")
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
        wait_for(lambda: drv.stats()["cycles"] >= 5, what="five passes")
        stats = drv.stats()
        assert stats["timeouts"] == 0 and stats["protocolErrors"] == 0
        assert stats["line"]["discardedBytes"] >= 8 * 5  # the echoes, skipped
        assert not _line_threads("ECHO1")


def test_the_frames_of_a_loop_line_are_logged_at_debug(
        caplog: pytest.LogCaptureFixture) -> None:
    """DEBUG on edgemodbus.line: the loop link writes every frame to the line's trace
    ring and the loop worker logs them (ContextLink.collect), a request then its reply,
    as a line worker does."""
    caplog.set_level("DEBUG", logger="edgemodbus.line")
    port = free_port()
    cfg = dtu_device(port, "TRACE1", 1, engine="loop", loopThreads=1)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        sim.dial("127.0.0.1", port, registration=b"TRACE1")
        wait_for(ok(cfg), what="values on the loop engine")
        wait_for(lambda: drv.stats()["cycles"] >= 3, what="three passes")
        wait_for(lambda: len(_frames(caplog, " TX 01 03 ")) >= 3, what="three requests logged")
    tx, rx = _frames(caplog, " TX 01 03 "), _frames(caplog, " RX 01 03 ")
    assert all(line.endswith("TX 01 03 00 00 00 08 44 0C") for line in tx), tx
    assert len(rx) >= len(tx) - 1
    lines = _frames(caplog, "")
    assert " RX 01 03 10 " in lines[lines.index(tx[0]) + 1]  # the reply right after it


def _frames(caplog: pytest.LogCaptureFixture, part: str) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "edgemodbus.line" and (" TX " in r.getMessage()
                                                or " RX " in r.getMessage())
            and part in r.getMessage()]


def test_a_report_only_mcu_on_a_loop_thread_takes_its_reports_while_idle() -> None:
    """readCycle 0: nothing is polled, the link idles on the loop; a report in the
    registration's segment (fed to the link) and one pushed later both reach the items
    (EV_REPORTS with no device: the worker dispatches them), and a write goes out
    wrapped through the idle link."""
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU2", "registration": "text",
                          "readCycle": 0, "engine": "loop", "loopThreads": 1})
    report = wrap(80, 1, bytes.fromhex("03021234"))
    with Simulator(slaves=[1]) as sim, running_one(cfg) as drv:
        client = sim.dial("127.0.0.1", port, registration=b"MCU2" + report, wrapped=True)
        wait_for(lambda: value_of(cfg, "r80") == 0x1234, what="the first report applied")
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 30, [31337])
        client.push_report(1, Area.HOLDING_REGISTER, 30, 1)
        wait_for(lambda: value_of(cfg, "r30") == 31337, what="the pushed report applied")
        ok_, err = drv.write_address("r2", 4242)
        assert ok_, err
        assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 2) == [4242]
        stats = drv.stats()
        assert stats["reports"] == 2 and stats["line"]["droppedFrames"] == 0
        assert not _line_threads("MCU2")
