"""Report by change, by period or both (reportMode, reportEvery), reads on demand
(``driver.read_now``, demand-only items) and ``publish_snapshot``, end to end against
pymodbus (docs/reporting.md)."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from tests.integration.test_driver import Running, device
from tests.peers import PymodbusSlave
from tests.waiting import wait_for


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2), size=200, fill="zero") as peer:
        yield peer


def uint16(name: str, address: str, **extra: Any) -> dict[str, Any]:
    return {"name": name, "address": address, "deviceDataType": "UInt16", **extra}


class Reports:
    """Per-item callback log: (monotonic time, value, status) per item name."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.seen: dict[str, list[tuple[float, Any, ItemStatus]]] = {}
        self.batches: list[list[str]] = []

    def item(self, item: em.DeviceAddressItem) -> None:
        with self.lock:
            self.seen.setdefault(item.name, []).append((time.monotonic(), item.value,
                                                        item.status))

    def batch(self, items: list[em.DeviceAddressItem]) -> None:
        with self.lock:
            self.batches.append([i.name for i in items])

    def of(self, name: str) -> list[tuple[float, Any, ItemStatus]]:
        with self.lock:
            return list(self.seen.get(name, []))


def test_an_unchanged_item_is_reported_again_every_report_every(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 0, [7, 8])
    log = Reports()
    cfg = device(slave.port, [uint16("periodic", "hr:0", reportEvery=300),
                              uint16("quiet", "hr:1")], readCycle=100)
    with Running(cfg, address_updated_callback=log.item,
                 addresses_updated_callback=log.batch) as drv:
        wait_for(lambda: len(log.of("periodic")) >= 5, timeout=15, what="5 reports")
        stats = drv.stats()
    reports = log.of("periodic")
    assert all(value == 7 and status is ItemStatus.OK for _, value, status in reports)
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(reports)]
    # never before reportEvery less a tenth of the scan rate (docs/reporting.md), and
    # on time within a few scan rates on a loaded machine
    assert min(gaps) >= 0.3 - 0.01 - 0.005, gaps
    assert sum(gaps) / len(gaps) < 0.6, gaps
    # the item without a period: reported once (its first read), never again
    assert len(log.of("quiet")) == 1
    # period reports go through the batch too
    assert sum("periodic" in b for b in log.batches) >= 5
    assert stats["callbackErrors"] == 0


def test_a_change_is_reported_at_once_and_restarts_the_period(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 0, [1])
    log = Reports()
    cfg = device(slave.port, [uint16("v", "hr:0", reportEvery=2000)], readCycle=100)
    with Running(cfg, address_updated_callback=log.item):
        wait_for(lambda: log.of("v"), what="the first report")
        slave.set_registers(1, "hr", 0, [2])
        wait_for(lambda: any(v == 2 for _, v, _ in log.of("v")), what="the change")
        changed_at = next(t for t, v, _ in log.of("v") if v == 2)
        wait_for(lambda: len(log.of("v")) >= 3, timeout=15, what="a period report")
    again = log.of("v")[2]
    assert again[1] == 2
    assert again[0] - changed_at >= 2.0 - 0.01 - 0.005  # the change restarted the period


def test_report_mode_cycle_per_item_on_a_change_device(slave: PymodbusSlave) -> None:
    log = Reports()
    cfg = device(slave.port, [uint16("every", "hr:0", reportMode="cycle"),
                              uint16("changes", "hr:1")], readCycle=100)
    with Running(cfg, address_updated_callback=log.item) as drv:
        wait_for(lambda: len(log.of("every")) >= 6, timeout=15, what="6 reports")
        cycles = drv.stats()["cycles"]
    assert len(log.of("changes")) == 1
    # one report per read (the first read reports it as news, then one per pass)
    assert len(log.of("every")) <= cycles + 1


def test_report_mode_change_per_item_on_a_cycle_device(slave: PymodbusSlave) -> None:
    log = Reports()
    cfg = device(slave.port, [uint16("every", "hr:0"), uint16("changes", "hr:1",
                                                               reportMode="change")],
                 readCycle=100, reportMode="cycle")
    with Running(cfg, address_updated_callback=log.item):
        wait_for(lambda: len(log.of("every")) >= 6, timeout=15, what="6 reports")
    assert len(log.of("changes")) == 1


def test_demand_items_are_never_polled_and_read_when_asked(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 0, [11])
    slave.set_registers(2, "hr", 40, [1234, 5678])
    log = Reports()
    polled = device(slave.port, [uint16("p", "hr:0")], slave=1, readCycle=50)
    demand = device(slave.port, [uint16("d", "hr:40", readCycle="demand"),
                                 uint16("d2", "hr:41", readCycle=-1)], slave=2)
    with Running(polled) as drv1, Running(demand, address_updated_callback=log.item) as drv2:
        assert drv2.read_plan() == []
        # only demand items: Running once the link is up, items Unknown until asked
        wait_for(lambda: drv2.device_driver_status is em.DeviceDriverStatus.RUNNING,
                 what="Running")
        assert drv2.snapshot()["items"]["d"]["status"] == "Unknown"
        wait_for(lambda: drv1.stats()["cycles"] >= 10, what="10 cycles on the line")
        assert slave.request_count(2) == 0
        assert log.of("d") == []
        answer = drv2.read_now(["d"]).result(timeout=10)
        assert answer["d"]["value"] == 1234 and answer["d"]["status"] == "Ok"
        assert slave.request_count(2) == 1
        assert [v for _, v, _ in log.of("d")] == [1234]
        # the same value again: still reported (it answers a request)
        slave.set_registers(2, "hr", 41, [99])
        answer = drv2.read_now().result(timeout=10)
        assert answer == {"d": answer["d"], "d2": answer["d2"]}
        assert answer["d2"]["value"] == 99
        assert [v for _, v, _ in log.of("d")] == [1234, 1234]
        assert slave.request_count(2) == 2  # d and d2 share one block
        wait_for(lambda: drv1.stats()["cycles"] >= 20, what="10 more cycles")
        assert slave.request_count(2) == 2
        with pytest.raises(KeyError, match="'nope'"):
            drv2.read_now(["nope"])


def test_read_now_of_a_polled_item_reports_it_unchanged(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 0, [5])
    log = Reports()
    cfg = device(slave.port, [uint16("v", "hr:0")], readCycle=60_000)
    with Running(cfg, address_updated_callback=log.item) as drv:
        wait_for(lambda: log.of("v"), what="the first read")
        before = slave.request_count(1)
        answer = drv.read_now(["v"]).result(timeout=10)
        assert answer["v"]["value"] == 5
        assert slave.request_count(1) == before + 1
        assert [v for _, v, _ in log.of("v")] == [5, 5]


def test_a_read_on_demand_does_not_hide_a_drift_past_the_deadband(
        slave: PymodbusSlave) -> None:
    """A read of ``other`` decodes its neighbour ``v`` too: ``v`` moved within its
    deadband (not news, not reported).  The next polls must still compare with what
    ``v`` holds: its drift past the deadband is reported."""
    slave.set_registers(1, "hr", 0, [10, 0])
    log = Reports()
    cfg = device(slave.port, [uint16("v", "hr:0", deadband=5), uint16("other", "hr:1")],
                 readCycle=100)
    with Running(cfg, address_updated_callback=log.item) as drv:
        wait_for(lambda: log.of("v"), what="the first read")
        slave.set_registers(1, "hr", 0, [14])
        drv.read_now(["other"]).result(timeout=10)
        slave.set_registers(1, "hr", 0, [18])  # 8 from 10 (reported), 4 from 14 (read)
        wait_for(lambda: [v for _, v, _ in log.of("v")] == [10, 18], what="the drift")


def test_read_now_of_a_silent_slave_answers_invalid(slave: PymodbusSlave) -> None:
    cfg = device(slave.port, [uint16("d", "hr:0", readCycle="demand")], slave=3,
                 readTimeout=200)
    with Running(cfg) as drv:
        answer = drv.read_now().result(timeout=10)
    assert answer["d"]["status"] == "Invalid"
    assert answer["d"]["errorReason"]


def test_publish_snapshot_goes_through_the_periodic_path(slave: PymodbusSlave) -> None:
    got: list[tuple[str, dict[str, Any]]] = []
    cfg = device(slave.port, [uint16("v", "hr:0")])
    drv = em.DriverModbusRtu()
    drv.snapshot_publisher = lambda topic, snap: got.append((topic, snap))
    with pytest.raises(em.ModbusConnectionError):
        drv.publish_snapshot()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        wait_for(lambda: drv.snapshot()["items"]["v"]["status"] == "Ok", what="a read")
        drv.publish_snapshot().result(timeout=10)
    finally:
        drv.stop_device()
    assert [topic for topic, _ in got] == ["/real/dev1"]
    assert got[0][1]["items"]["v"]["status"] == "Ok"


def test_a_hot_update_switches_a_cycle_device_to_per_item_modes(slave: PymodbusSlave) -> None:
    log = Reports()
    cfg = device(slave.port, [uint16("a", "hr:0")], readCycle=100, reportMode="cycle")
    with Running(cfg, address_updated_callback=log.item) as drv:
        wait_for(lambda: len(log.of("a")) >= 3, what="a at every read")
        drv.update_addresses([em.DeviceAddressItem.model_validate(uint16("a", "hr:0")),
                              em.DeviceAddressItem.model_validate(
                                  uint16("b", "hr:1", reportMode="change"))])
        seen = len(log.of("a"))
        wait_for(lambda: len(log.of("a")) >= seen + 4, what="a still at every read")
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 3, what="3 more cycles")
    assert len(log.of("b")) == 1  # its first read only
