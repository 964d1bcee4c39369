"""An item that stays Invalid while the slave's bad value changes, end to end: in
reportMode "change" its errorReason names the value the slave holds now, and the
callbacks fire for the new reason."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from tests.peers import ExceptionRange, PymodbusSlave
from tests.waiting import wait_for


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=100, fill="zero") as peer:
        yield peer


def test_bcd16_reason_follows_the_slave_in_change_mode(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 7, [0x12AB])
    cfg = em.load_device_config({
        "organization": {"deviceCode": "bcd"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readTimeout": 300, "readCycle": 50, "reconnectInterval": 300,
            "reportMode": "change",
        },
        "addressList": [
            {"name": "bcd", "address": "hr:7", "deviceDataType": "BCD16"},
            {"name": "plain", "address": "hr:8", "deviceDataType": "UInt16"},
        ],
    })
    lock = threading.Lock()
    seen: list[tuple[str, ItemStatus, str | None]] = []
    batches: list[list[str]] = []

    def on_item(item: em.DeviceAddressItem) -> None:
        with lock:
            seen.append((item.name, item.status, item.error_reason))

    def on_batch(items: list[em.DeviceAddressItem]) -> None:
        with lock:
            batches.append([item.name for item in items])

    def reasons() -> list[str | None]:
        with lock:
            return [reason for name, _, reason in seen if name == "bcd"]

    drv = em.DriverModbusRtu()
    drv.address_updated_callback = on_item
    drv.addresses_updated_callback = on_batch
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        item = cfg.address_list[0]
        wait_for(lambda: item.status is ItemStatus.INVALID, what="the BCD item Invalid")
        assert item.error_reason is not None and "0x12AB" in item.error_reason
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 3, what="a few more cycles")
        assert reasons() == [item.error_reason]  # the same bad value is reported once
        with lock:
            batches_before = len(batches)

        slave.set_registers(1, "hr", 7, [0x34CD])
        wait_for(lambda: len(reasons()) == 2, what="a report of the new reason")
        assert item.status is ItemStatus.INVALID
        assert item.error_reason == "invalid BCD value 0x34CD (a digit above 9)"
        assert reasons()[1] == item.error_reason
        with lock:
            assert ["bcd"] in batches[batches_before:]  # the batch callback fired too
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 3, what="a few more cycles")
        assert len(reasons()) == 2  # and once only

        slave.set_registers(1, "hr", 7, [0x1234])
        wait_for(lambda: item.status is ItemStatus.OK, what="the BCD item Ok again")
        assert item.value == 1234 and item.error_reason is None
    finally:
        drv.stop_device()


def test_a_new_read_failure_reason_is_reported(slave: PymodbusSlave) -> None:
    """An item already Invalid (bad BCD) whose read then fails (exception 03) is reported
    with the new reason: a reason describes what happens now, in every mode."""
    slave.set_registers(1, "hr", 7, [0x12AB])
    cfg = em.load_device_config({
        "organization": {"deviceCode": "bcd"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readTimeout": 300, "readCycle": 50, "reconnectInterval": 300,
            "reportMode": "change",
        },
        "addressList": [{"name": "bcd", "address": "hr:7", "deviceDataType": "BCD16"}],
    })
    lock = threading.Lock()
    reasons: list[str | None] = []

    def on_item(item: em.DeviceAddressItem) -> None:
        with lock:
            reasons.append(item.error_reason)

    drv = em.DriverModbusRtu()
    drv.address_updated_callback = on_item
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        item = cfg.address_list[0]
        wait_for(lambda: item.status is ItemStatus.INVALID, what="the BCD item Invalid")
        slave.set_exception_ranges([ExceptionRange(7, 8, code=3)])
        wait_for(lambda: "exception 0x03" in (item.error_reason or ""), what="exception 03")
        wait_for(lambda: len(reasons) == 2, what="the new reason reported")
        with lock:
            assert "0x12AB" in (reasons[0] or "") and reasons[1] == item.error_reason
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 3, what="a few more cycles")
        assert len(reasons) == 2  # the same failure is reported once
    finally:
        drv.stop_device()
