"""Item values in the poller's store (poll/store.py), end to end: reads from another thread
are consistent, the items given to start_device are the ones polled (never copied, by
the driver or by the gateway), and an item object is polled by one running driver."""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ItemReading
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.gateway.config import load_gateway_config
from edgemodbus.gateway.service import Gateway
from edgemodbus.poll.store import ItemInUseError
from edgemodbus.sim import Mover, Simulator
from tests.waiting import wait_for

PAIRS = 40


class _Alternating(Mover):
    """hr:0, 2, 4... BCD16 registers, valid on even reads and invalid (a nibble A) on
    odd ones; hr:1, 3, 5... the read count: every read changes every item, and the
    statuses flip every read."""

    def __init__(self) -> None:
        self.area = Area.HOLDING_REGISTER
        self.address = 0
        self.reads = 0

    @property
    def count(self) -> int:
        return 2 * PAIRS

    def values(self, elapsed: float) -> list[int]:
        self.reads += 1
        n = self.reads % 100
        bcd = (n // 10) << 4 | n % 10
        return [bcd if self.reads % 2 == 0 else 0xA0 | n % 10, self.reads & 0xFFFF] * PAIRS


@pytest.fixture
def sim() -> Iterator[tuple[Simulator, int]]:
    with Simulator([1, 2]) as simulator:
        simulator.slave(1).add_mover(_Alternating())
        yield simulator, simulator.serve_tcp("127.0.0.1", 0, silence=0.0)


def _config(port: int, slave: int = 1, pairs: int = 1, **extra: Any) -> em.DeviceConfig:
    items: list[dict[str, Any]] = []
    for k in range(pairs):
        suffix = str(k) if k else ""
        items += [{"name": f"bcd{suffix}", "address": f"hr:{2 * k}", "deviceDataType": "BCD16"},
                  {"name": f"count{suffix}", "address": f"hr:{2 * k + 1}",
                   "deviceDataType": "UInt16"}]
    return em.load_device_config({
        "organization": {"deviceCode": f"dev{slave}"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": slave, "readTimeout": 500,
                          "readCycle": 1, "reconnectInterval": 300, **extra},
        "addressList": items,
    })


def _entry(reading: ItemReading) -> tuple[Any, ...]:
    """A reading as driver.snapshot() shows it."""
    stamp = reading.update_ts.isoformat() if reading.update_ts else None
    return (reading.value, reading.status.value, stamp, reading.error_reason)


def test_a_reader_thread_never_sees_a_torn_reading(sim: tuple[Simulator, int]) -> None:
    """Every reading another thread takes (item.reading, snapshot()) while the worker
    writes is one the worker wrote: value, status, time and reason of one read.  The
    worker records each state it wrote (reportMode cycle: every write is reported, and
    the callback runs on the worker right after it); the switch interval is tiny, so the
    reader interleaves with the worker's writes thousands of times."""
    _, port = sim
    cfg = _config(port, pairs=PAIRS, reportMode="cycle")
    written: dict[str, set[ItemReading]] = {it.name: {it.reading} for it in cfg.address_list}

    def on_item(item: em.DeviceAddressItem) -> None:
        written[item.name].add(item.reading)

    seen: list[tuple[str, ItemReading]] = []
    snapped: list[tuple[str, tuple[Any, ...]]] = []
    stop = threading.Event()
    drv = em.DriverModbusRtu()

    def read() -> None:
        while not stop.is_set():
            for item in cfg.address_list:
                seen.append((item.name, item.reading))
            for name, entry in drv.snapshot()["items"].items():
                snapped.append((name, (entry["value"], entry["status"], entry["updateTs"],
                                       entry["errorReason"])))

    drv.address_updated_callback = on_item
    interval = sys.getswitchinterval()
    reader = threading.Thread(target=read, name="test reader")
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        sys.setswitchinterval(1e-5)
        reader.start()
        bcd = cfg.address_list[0]
        flips: set[ItemStatus] = set()
        deadline = time.monotonic() + 60
        # enough states written and read: both statuses, and many readings
        while (len(written["bcd"]) < 1000 or len(flips) < 2 or len(seen) < 200_000) \
                and time.monotonic() < deadline:
            flips.add(bcd.status)
            time.sleep(0.01)  # poll: sampling until enough was seen (deadline above)
    finally:
        stop.set()
        if reader.is_alive():
            reader.join()
        sys.setswitchinterval(interval)
        drv.stop_device()
    assert len(written["bcd"]) >= 1000 and flips >= {ItemStatus.OK, ItemStatus.INVALID}
    torn = [(name, r) for name, r in seen if r not in written[name]]
    assert not torn, f"{len(torn)} of {len(seen)} readings were never written: {torn[:3]}"
    entries = {name: {_entry(r) for r in states} for name, states in written.items()}
    torn_snaps = [(name, e) for name, e in snapped if e not in entries[name]]
    assert not torn_snaps, f"{len(torn_snaps)} of {len(snapped)}: {torn_snaps[:3]}"
    for _, r in seen:  # and each is coherent in itself
        assert (r.status is ItemStatus.INVALID) == (r.error_reason is not None)


def test_starting_a_driver_twice_uses_the_same_items(sim: tuple[Simulator, int]) -> None:
    """No copy per start: the callbacks get the objects given to start_device, each
    start; the state an item had stays with it across the restart."""
    _, port = sim
    cfg = _config(port, slave=2, readCycle=20)
    items = cfg.address_list
    got: list[em.DeviceAddressItem] = []
    drv = em.DriverModbusRtu()
    drv.address_updated_callback = got.append
    for _ in range(2):
        got.clear()
        assert drv.start_device(cfg.organization, cfg.communication, items)
        try:
            wait_for(lambda: len(got) >= 2, what="both items reported")
            assert all(any(g is it for it in items) for g in got)
            assert all(a is b for a, b in zip(drv.address_items, items, strict=True))
        finally:
            drv.stop_device()
        assert all(it.status is not ItemStatus.UNKNOWN for it in items)  # kept
        kept = [it.reading for it in items]
        assert drv.snapshot()["items"]["count"]["value"] == kept[1].value  # after the stop


def test_one_item_object_in_two_running_drivers_is_refused(
        sim: tuple[Simulator, int]) -> None:
    _, port = sim
    first, second = _config(port, slave=2, readCycle=50), _config(port, slave=1)
    one, two = em.DriverModbusRtu(), em.DriverModbusRtu()
    assert one.start_device(first.organization, first.communication, first.address_list)
    try:
        with pytest.raises(ItemInUseError, match=r"addressList\[0\] 'bcd': this item object "
                                                  r"is polled by another running driver"):
            two.start_device(second.organization, second.communication, first.address_list)
        assert two.device_driver_status.value == "Stopped"
        copies = [it.model_copy() for it in first.address_list]  # what the error advises
        assert two.start_device(second.organization, second.communication, copies)
        two.stop_device()
    finally:
        one.stop_device()
    # once the first stopped, the items are free
    assert two.start_device(second.organization, second.communication, first.address_list)
    two.stop_device()


def test_a_host_may_set_a_polled_items_value_until_the_next_read(
        sim: tuple[Simulator, int]) -> None:
    """The compatibility path: assigning a runtime field sets it in the store (under its
    lock); the next read that changes the item overwrites it."""
    simulator, port = sim
    cfg = _config(port, slave=2, readCycle=20)
    simulator.slave(2).set_registers(Area.HOLDING_REGISTER, 1, [7])
    count = cfg.address_list[1]
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        wait_for(lambda: count.value == 7, what="count read")
        count.value = 99
        assert count.reading.value == 99 and drv.snapshot()["items"]["count"]["value"] == 99
        with pytest.raises(ValueError, match="bogus"):
            count.status = "bogus"  # type: ignore[assignment]
        simulator.slave(2).set_registers(Area.HOLDING_REGISTER, 1, [8])
        wait_for(lambda: count.value == 8, what="the next read's value")
    finally:
        drv.stop_device()


def test_the_gateway_polls_the_loaded_items_themselves(
        sim: tuple[Simulator, int], tmp_path: Path) -> None:
    """The gateway gives each driver the items of its loaded config (no deep copy per
    start), and the items of a reloaded address list."""
    _, port = sim
    device = {"organization": {"deviceCode": "meter"},
              "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                "tcpPort": port, "slaveId": 2, "readCycle": 20,
                                "readTimeout": 500},
              "addressList": [{"name": "count", "address": "hr:1",
                               "deviceDataType": "UInt16"}]}
    path = tmp_path / "meter.json"
    path.write_text(json.dumps(device))
    (tmp_path / "gateway.json").write_text(json.dumps({"gatewayId": "gw"}))
    gateway = Gateway(tmp_path, load_gateway_config(tmp_path / "gateway.json"),
                      tmp_path / "gateway.json")
    gateway.start()
    try:
        dev = next(iter(gateway.devices.values()))
        assert dev.driver.address_items[0] is dev.cfg.address_list[0]
        wait_for(lambda: dev.cfg.address_list[0].status is ItemStatus.OK, what="read")
        device["addressList"].append(  # type: ignore[attr-defined]
            {"name": "bcd", "address": "hr:0", "deviceDataType": "UInt16"})
        path.write_text(json.dumps(device))
        gateway.reload()
        dev = next(iter(gateway.devices.values()))
        assert len(dev.cfg.address_list) == 2
        assert all(a is b for a, b in zip(dev.driver.address_items, dev.cfg.address_list,
                                           strict=True))
        # the kept item's state went over to the new object (same definition)
        assert dev.cfg.address_list[0].status is ItemStatus.OK
    finally:
        gateway.stop()


def test_an_update_with_another_drivers_item_is_refused_and_changes_nothing(
        sim: tuple[Simulator, int]) -> None:
    _, port = sim
    first, second = _config(port, slave=2, readCycle=50), _config(port, slave=1, readCycle=50)
    one, two = em.DriverModbusRtu(), em.DriverModbusRtu()
    assert one.start_device(first.organization, first.communication, first.address_list)
    try:
        assert two.start_device(second.organization, second.communication,
                                second.address_list)
        try:
            mixed = [second.address_list[0], first.address_list[1]]
            with pytest.raises(ItemInUseError, match=r"addressList\[1\] 'count'"):
                two.update_addresses(mixed)
            assert all(a is b for a, b in zip(two.address_items, second.address_list,
                                               strict=True))
            wait_for(lambda: second.address_list[1].status is ItemStatus.OK,
                     what="the running plan still polled")
        finally:
            two.stop_device()
    finally:
        one.stop_device()
