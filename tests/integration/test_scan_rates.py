"""Per-item scan rates (an item's ``readCycle``) end to end: DriverModbusRtu against our
simulator, whose registers here count the reads that touch them."""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.sim import Simulator
from edgemodbus.sim.movers import Mover
from tests.integration.test_driver import Running, all_ok, device
from tests.waiting import wait_for

HR = em.Area.HOLDING_REGISTER


class ReadLog(Mover):
    """One register that holds how many reads touched it; logs when each read came."""

    def __init__(self, address: int) -> None:
        self.area = HR
        self.address = address
        self.times: list[float] = []

    @property
    def count(self) -> int:
        return 1

    def values(self, elapsed: float) -> list[int]:
        self.times.append(time.monotonic())
        return [len(self.times)]


def uint16(name: str, address: str, **extra: Any) -> dict[str, Any]:
    return {"name": name, "address": address, "deviceDataType": "UInt16", **extra}


@pytest.fixture
def sim() -> Iterator[Simulator]:
    with Simulator([1]) as simulator:
        yield simulator


def reads_between(log: ReadLog, start: float, end: float) -> list[float]:
    return [t for t in log.times if start <= t < end]


def test_a_fast_and_a_slow_item_are_read_at_their_own_rates(sim: Simulator) -> None:
    fast, slow = sim.slave(1).add_mover(ReadLog(0)), sim.slave(1).add_mover(ReadLog(12))
    assert isinstance(fast, ReadLog) and isinstance(slow, ReadLog)
    sim.slave(1).set_float32(HR, 10, 2.5)
    port = sim.serve_tcp("127.0.0.1", 0)
    # hr:12 follows the float at hr:10-11: at one rate all three would be one request
    cfg = device(port, [uint16("fast", "hr:0", readCycle=50), uint16("slow", "hr:12"),
                        {"name": "f", "address": "hr:10", "deviceDataType": "Float",
                         "readCycle": 50}],
                 readCycle=1000)
    with Running(cfg) as drv:
        # the float merges with the fast item (same rate, gap 8), never with the slow one
        assert [(b["start"], b["count"]) for b in drv.read_plan()] == [(0, 12), (12, 1)]
        wait_for(lambda: slow.times and time.monotonic() - slow.times[0] >= 1.5,
                 what="1.5 s of polling")
        t0 = slow.times[0]
        slow_reads = reads_between(slow, t0, t0 + 1.5)
        fast_reads = reads_between(fast, t0, t0 + 1.5)
        wait_for(all_ok(cfg))
    requests = drv.stats()["requests"]  # after the stop: no read since
    # the slow block: at the start and one readCycle later
    assert len(slow_reads) == 2
    assert 0.99 <= slow_reads[1] - slow_reads[0] < 1.3
    # the fast block: every 50 ms (never more often), 20 to 31 times in 1.5 s
    gaps = [b - a for a, b in zip(fast.times, fast.times[1:], strict=False)]
    assert 20 <= len(fast_reads) <= 31, len(fast_reads)
    # (a block may join a cycle that begins up to 5 ms before it is due, and its place in
    # the cycle varies: a single gap may be a little short of 50 ms)
    assert min(gaps) >= 0.035 and 0.045 <= statistics.median(gaps) < 0.08, gaps
    # values: each counter as of its last read; the float of the fast rate
    fast_item, slow_item, float_item = cfg.address_list
    assert len(fast.times) - 1 <= fast_item.value <= len(fast.times)  # one may be in flight
    assert slow_item.value == len(slow.times)
    assert float_item.value == 2.5 and float_item.status is ItemStatus.OK
    # one request per read of each block
    assert len(fast.times) + len(slow.times) - 1 <= requests <= len(fast.times) + len(slow.times)


def test_update_addresses_changing_a_rate_replans(sim: Simulator) -> None:
    a, b = sim.slave(1).add_mover(ReadLog(0)), sim.slave(1).add_mover(ReadLog(1))
    assert isinstance(a, ReadLog) and isinstance(b, ReadLog)
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, [uint16("a", "hr:0"), uint16("b", "hr:1")], readCycle=100)
    with Running(cfg) as drv:
        assert [(p["start"], p["count"]) for p in drv.read_plan()] == [(0, 2)]
        wait_for(lambda: len(a.times) >= 3)
        assert len(a.times) == len(b.times)  # one request reads both
        new = [em.DeviceAddressItem.model_validate(uint16("a", "hr:0", readCycle=50)),
               em.DeviceAddressItem.model_validate(uint16("b", "hr:1", readCycle=1000))]
        t0 = time.monotonic()
        drv.update_addresses(new)
        assert [(p["start"], p["count"]) for p in drv.read_plan()] == [(0, 1), (1, 1)]
        wait_for(lambda: time.monotonic() - t0 >= 1.3, what="1.3 s of polling")
        a_reads, b_reads = reads_between(a, t0, t0 + 1.3), reads_between(b, t0, t0 + 1.3)
        # b: perhaps one read of the old plan (every 100 ms) before the swap, then at the
        # swap and one second later; a: every 50 ms
        assert len(b_reads) in (2, 3) and 0.99 <= b_reads[-1] - b_reads[-2] < 1.2, b_reads
        assert 20 <= len(a_reads) <= 29, len(a_reads)
        wait_for(lambda: all(it.status is ItemStatus.OK for it in new))
    # each value is its counter as of one of the last reads (one may be in flight at stop)
    assert len(a.times) - 1 <= new[0].value <= len(a.times)
    assert len(b.times) - 1 <= new[1].value <= len(b.times)


def test_an_item_at_rate_0_is_only_reported(sim: Simulator) -> None:
    pushed = sim.slave(1).add_mover(ReadLog(5))
    assert isinstance(pushed, ReadLog)
    sim.slave(1).set_registers(HR, 2, [502])
    port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
    cfg = device(port, [uint16("polled", "hr:2"), uint16("pushed", "hr:5", readCycle=0)],
                 readCycle=100, framing="wrapped-report")
    polled, item = cfg.address_list
    with Running(cfg) as drv:
        assert [(p["start"], p["count"]) for p in drv.read_plan()] == [(2, 1)]
        wait_for(lambda: polled.status is ItemStatus.OK and drv.stats()["cycles"] >= 3)
        assert pushed.times == [] and item.status is ItemStatus.UNKNOWN
        (client,) = sim.clients()
        client.push_report(1, HR, 5, 1)
        wait_for(lambda: item.status is ItemStatus.OK, what="the report")
        assert item.value == len(pushed.times) == 1  # read once: by the report


def test_rate_0_is_refused_without_wrapped_reports() -> None:
    with pytest.raises(em.ConfigError) as caught:
        device(5020, [uint16("x", "hr:0", readCycle=0)])
    assert str(caught.value).startswith("addressList[0].readCycle 0: 0 means not polled")
    assert "framing 'wrapped-report' (framing is 'rtu')" in str(caught.value)
    # -1 is "demand" (docs/reporting.md); below it, refused with what is allowed
    with pytest.raises(em.ConfigError, match=r"addressList\[0\]\.readCycle -2: .*-1 .*"
                       r"0 .*1\.\.86400000 ms"):
        device(5020, [uint16("x", "hr:0", readCycle=-2)])


def test_a_silent_slave_goes_offline_and_back_with_every_rate(sim: Simulator) -> None:
    port = sim.serve_tcp("127.0.0.1", 0)
    cfg = device(port, [uint16("fast", "hr:0", readCycle=50), uint16("slow", "hr:1")],
                 readCycle=2000, readTimeout=100, retries=0, offlineAfterFailedCycles=2)
    with Running(cfg) as drv:
        wait_for(all_ok(cfg))
        sim.slave(1).faults.silent = True
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.OFFLINE)
        # the slow item was not due (2 s), but an offline slave holds no fresh value
        assert all(it.status is ItemStatus.INVALID for it in cfg.address_list)
        assert all("not responding" in (it.error_reason or "") for it in cfg.address_list)
        stats = drv.stats()
        assert stats["failedCycles"] >= 2
        sim.slave(1).faults.silent = False
        wait_for(all_ok(cfg))
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
