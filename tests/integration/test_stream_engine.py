"""DTU streams in the line engine (csrc/emb_engine.c over csrc/emb_stream.c): a DTU with
heartbeats is read by the engine like a plain RTU-over-TCP line (its heartbeats counted
live, no Python per block or per heartbeat), and a wrapped-report link's reports reach
the items around the reply in the order they came on the wire, without the Python step
path."""

from __future__ import annotations

import functools
import itertools
import operator
import select
import socket
import struct
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.line.link import ContextLink
from edgemodbus.poll.poller import Poller
from edgemodbus.protocol.wrapped import wrap
from edgemodbus.sim import Simulator, default_register
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.integration.test_engine import MasterCalls
from tests.integration.test_wrapped_link import EagerMcu, wrapped_device
from tests.integration.test_wrapped_link import running as running_one
from tests.waiting import wait_for


@pytest.fixture
def python_reads(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """The reads made in Python instead of the engine (the old step path), recorded."""
    calls: list[str] = []
    monkeypatch.setattr(ContextLink, "_read", lambda *a: calls.append("_read"))
    yield calls


def test_a_dtu_with_heartbeats_runs_in_the_engine(python_reads: list[str]) -> None:
    """Heartbeats between and before the replies, values that do not change: the worker
    runs less Python than one call per pass, and the heartbeats are counted live."""
    port = free_port()
    cfg = dtu_device(port, "DTU8", heartbeat="HB", readCycle=20, addresses=(0, 1, 7, 40, 90),
                     maxMergeAddressGap=0)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        client = sim.dial("127.0.0.1", port, registration=b"HBDTU8", heartbeat=b"HB",
                          heartbeat_interval=0.01, heartbeat_before_reply=True)
        wait_for(ok(cfg))
        with MasterCalls() as watch:
            before = drv.stats()
            watch.counting = True
            wait_for(lambda: drv.stats()["cycles"] >= before["cycles"] + 20
                     and drv.stats()["line"]["heartbeats"] >= before["line"]["heartbeats"] + 5,
                     what="20 passes and 5 heartbeats")
            watch.counting = False
            stats = drv.stats()
        cycles = stats["cycles"] - before["cycles"]
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7, 40, 90)]
    assert not python_reads
    assert stats["timeouts"] == 0 and stats["protocolErrors"] == 0
    assert stats["requests"] - before["requests"] >= 4 * cycles - 4  # [0, 1] 7 40 90
    assert watch.calls < cycles, (watch.calls, cycles)
    assert client.heartbeats_sent >= stats["line"]["heartbeats"] - 1


def _eager_config(port: int, **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {"framing": "wrapped-report", "transport": "rtu-over-tcp",
                            "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
                            "readTimeout": 500, "byteTimeout": 50, "reportMode": "cycle"}
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": "eager"},
        "communication": comm,
        "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in (1, 2, 3)],
    })


@pytest.mark.parametrize("report_after", [False, True])
def test_wrapped_reports_around_the_reply_in_the_engine(python_reads: list[str],
                                                        report_after: bool) -> None:
    """Every read of [1, 2] brings a report of 1..4 before its reply (or right behind it,
    in the same segment): each item sees the frames in the order they came, the engine
    made every read."""
    mcu = EagerMcu(report_after=report_after)
    seen: list[tuple[str, Any, ItemStatus]] = []
    try:
        cfg = _eager_config(mcu.port, readCycle=30, maxBlockReadRegisterCount=2)
        with running_one(cfg, address_updated_callback=lambda it: seen.append(
                (it.name, it.value, it.status))) as drv:
            wait_for(lambda: mcu.reports >= 6, what="six reads answered with a report")
            stats = drv.stats()
    finally:
        mcu.close()
    assert not python_reads
    assert stats["reports"] >= 5 and stats["timeouts"] == stats["protocolErrors"] == 0
    assert all(status is ItemStatus.OK for _, _, status in seen)
    r1 = [v for n, v, _ in seen if n == "r1"]
    polled, reported = EagerMcu.polled(1), [v for v in r1 if v >= 9000]
    assert len(reported) >= 5 and polled in r1
    for before, after in itertools.pairwise(r1):
        if report_after:  # the reply, then its report: a report never follows a report
            assert before != polled or after >= 9000, r1
        else:  # the report, then the reply
            assert before < 9000 or after == polled, r1


def test_wrapped_reports_inside_a_block_are_applied_in_c(
        python_reads: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """An edge MCU (our simulator) polled every 50 ms as one block pushes one-register
    reports: the engine applies them in C (csrc/emb_report.c).  Those that bring no news
    cost no Python at all; those that do reach the item with the pass's changes, never
    through the Python path (Poller.on_report)."""
    python_path: list[int] = []
    monkeypatch.setattr(Poller, "on_report", lambda self, report: python_path.append(
        report.address))
    hr = Area.HOLDING_REGISTER
    seen: list[tuple[str, Any]] = []
    with Simulator(slaves=[1]) as sim, MasterCalls() as watch:
        port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
        cfg = wrapped_device({"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": port, "readCycle": 50, "maxMergeAddressGap": 100})
        with running_one(cfg, address_updated_callback=lambda it: seen.append(
                (it.name, it.value))) as drv:
            wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                     what="the first poll")
            (client,) = sim.clients()
            before = drv.stats()
            watch.counting = True
            for k in range(20):  # the values the slave holds: no news
                client.push_report(1, hr, (1, 2, 30)[k % 3], 1)
            wait_for(lambda: drv.stats()["reports"] >= before["reports"] + 20,
                     what="20 reports applied")
            watch.counting = False
            calls = watch.calls
            for value in (4242, 4243):  # news, while the slave holds the polled value
                sim.slave(1).set_registers(hr, 30, [value])
                client.push_report(1, hr, 30, 1)
                sim.slave(1).set_registers(hr, 30, [default_register(1, 30)])
                wait_for(functools.partial(operator.contains, seen, ("r30", value)),
                         what=f"the report of {value}")
            stats = drv.stats()
    assert not python_reads and not python_path
    assert calls < 20, calls  # the Python path: dozens of calls a report
    assert stats["line"]["reports"] == stats["reports"] >= before["reports"] + 22
    assert stats["timeouts"] == stats["protocolErrors"] == 0


class CrossMcu(EagerMcu):
    """An edge MCU that, on each read of holding register 1, first pushes a report of
    register 3 (another block of the same pass, read next) with a new value each time,
    then answers the read."""

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        while not self._stop.is_set():
            if not select.select([conn], [], [], 0.05)[0]:
                continue
            data = conn.recv(4096)
            if not data:
                return
            buf += data
            while len(buf) >= 13:
                request, buf = buf[:13], buf[13:]
                slave, fc, start, count = struct.unpack_from(">BBHH", request, 4)
                assert fc == 3, request.hex()
                regs = [self.polled(start + i) for i in range(count)]
                if start == 1:
                    self.reports += 1
                    conn.sendall(wrap(3, slave, struct.pack(
                        ">BBH", 3, 2, self.reported(self.reports, 3))))
                conn.sendall(wrap(start, slave,
                                  struct.pack(f">BB{count}H", 3, 2 * count, *regs)))
                self.replies += 1


def test_a_report_for_a_block_read_later_in_the_pass_goes_before_its_reply(
        python_reads: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks [1] and [3], change mode: the read of [1] brings a report of 3 before its
    reply.  The engine applies it in C to [3]'s plan; before it reads [3] it hands the
    report to Python, so r3 sees the report, then the poll, every pass, and never
    through the Python path."""
    python_path: list[int] = []
    monkeypatch.setattr(Poller, "on_report", lambda self, report: python_path.append(
        report.address))
    mcu = CrossMcu()
    seen: list[tuple[str, Any]] = []
    try:
        cfg = _eager_config(mcu.port, readCycle=30, reportMode="change",
                            maxBlockReadRegisterCount=2)
        with running_one(cfg, address_updated_callback=lambda it: seen.append(
                (it.name, it.value))) as drv:
            assert [(b["start"], b["count"]) for b in drv.read_plan()] == [(1, 2), (3, 1)]
            wait_for(lambda: mcu.reports >= 6, what="six reports before a reply")
            stats = drv.stats()
    finally:
        mcu.close()
    assert not python_reads and not python_path
    assert stats["timeouts"] == stats["protocolErrors"] == 0
    r3 = [v for n, v in seen if n == "r3"]
    polled = EagerMcu.polled(3)
    assert len([v for v in r3 if v != polled]) >= 5, r3
    for before, after in itertools.pairwise(r3):  # report, poll, report, poll ...
        assert (before == polled) != (after == polled), r3
