"""Engineering units over the wire against an independent slave (pymodbus, in its own
process): offset, range scaling (4-20 mA as 0..27648 counts) with Invalid and clamp,
SunSpec scale factors in the same block, in an earlier and in a later block of the
pass, changed between cycles and "not implemented"; writes inverted exactly."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

ITEMS: list[dict[str, Any]] = [
    # SunSpec-like: the value, then its factor, in one block
    {"name": "W", "address": "hr:0", "deviceDataType": "Int16", "scaleFactor": "W_SF"},
    {"name": "W_SF", "address": "hr:1", "deviceDataType": "Int16"},
    # the factor in an earlier block of the same pass (blocks split by the gap)
    {"name": "Hz_SF", "address": "hr:20", "deviceDataType": "Int16"},
    {"name": "Hz", "address": "hr:50", "deviceDataType": "UInt16", "scaleFactor": "Hz_SF"},
    # the factor in a later block: the value uses the one read in the pass before
    {"name": "V", "address": "hr:60", "deviceDataType": "UInt32", "scaleFactor": "V_SF"},
    {"name": "V_SF", "address": "hr:90", "deviceDataType": "Int16"},
    {"name": "Temp", "address": "hr:100", "deviceDataType": "Int16", "dataMultiplier": 0.1,
     "offset": -40},
    {"name": "Current", "address": "hr:110", "deviceDataType": "UInt16", "rawMin": 0,
     "rawMax": 27648, "engMin": 4, "engMax": 20},
    {"name": "Level", "address": "hr:111", "deviceDataType": "Int16", "rawMin": 4000,
     "rawMax": 20000, "engMin": 0, "engMax": 100, "clamp": True},
]

INITIAL = {0: 1234, 1: 0xFFFE, 20: 0xFFFF, 50: 6001, 60: 0, 61: 2305, 90: 0xFFFF,
           100: 650, 110: 13824, 111: 2000}


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200, fill="zero",
                       initial={1: {"hr": INITIAL}}) as peer:
        yield peer


@pytest.fixture
def device(slave: PymodbusSlave) -> Iterator[tuple[em.DriverModbusRtu, dict[str, Any]]]:
    comm = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readTimeout": 1000, "readCycle": 100, "reconnectInterval": 300,
            "maxMergeAddressGap": 5}
    cfg = em.load_device_config({"organization": {"deviceCode": "inverter"},
                                 "communication": comm, "addressList": ITEMS})
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        yield drv, {it.name: it for it in cfg.address_list}
    finally:
        drv.stop_device()


def _reads(items: dict[str, Any], name: str, value: object) -> bool:
    it = items[name]
    return bool(it.status is ItemStatus.OK and it.value == value)


def _invalid(items: dict[str, Any], name: str, reason: str) -> bool:
    it = items[name]
    return bool(it.status is ItemStatus.INVALID and it.error_reason == reason)


def test_values_in_engineering_units_from_pymodbus(
    slave: PymodbusSlave, device: tuple[em.DriverModbusRtu, dict[str, Any]]
) -> None:
    drv, items = device
    # the factor blocks are apart from their values' blocks
    plan = [(b["start"], b["count"]) for b in drv.read_plan()]
    assert len(plan) >= 5, plan
    expected = {"W": 12.34, "W_SF": -2, "Hz_SF": -1, "Hz": 600.1, "V": 230.5, "V_SF": -1,
                "Temp": 25.0, "Current": 12.0, "Level": 0.0}
    for name, value in expected.items():
        wait_for(lambda n=name, v=value: _reads(items, n, v), 15, f"{name} == {value}")


def test_a_changed_factor_rescales_and_bad_factors_make_items_invalid(
    slave: PymodbusSlave, device: tuple[em.DriverModbusRtu, dict[str, Any]]
) -> None:
    _, items = device
    wait_for(lambda: _reads(items, "W", 12.34), 15, "W first read")
    slave.set_registers(1, "hr", 1, [1])  # W_SF 1: the same raw value is ten times more
    wait_for(lambda: _reads(items, "W", 12340.0), 15, "W with sf 1")
    slave.set_registers(1, "hr", 1, [0x8000])
    wait_for(lambda: _invalid(items, "W", "scale factor item 'W_SF' is 0x8000 (SunSpec: "
                              "not implemented)"), 15, "W invalid for 0x8000")
    slave.set_registers(1, "hr", 1, [11])
    wait_for(lambda: _invalid(items, "W", "scale factor item 'W_SF' holds 11, outside "
                              "-10..10"), 15, "W invalid for sf 11")
    slave.set_registers(1, "hr", 20, [0])  # in an earlier block of the pass
    wait_for(lambda: _reads(items, "Hz", 6001.0), 15, "Hz with sf 0")
    slave.set_registers(1, "hr", 90, [2])  # in a later block: seen one pass after
    wait_for(lambda: _reads(items, "V", 230500.0), 15, "V with sf 2")


def test_a_raw_value_outside_its_range_is_invalid_or_clamped(
    slave: PymodbusSlave, device: tuple[em.DriverModbusRtu, dict[str, Any]]
) -> None:
    _, items = device
    wait_for(lambda: _reads(items, "Current", 12.0), 15, "Current first read")
    slave.set_registers(1, "hr", 110, [30000])
    wait_for(lambda: _invalid(items, "Current", "raw value 30000 outside rawMin..rawMax "
                              "(0..27648)"), 15, "Current invalid")
    slave.set_registers(1, "hr", 111, [25000])  # clamped to engMax
    wait_for(lambda: _reads(items, "Level", 100.0), 15, "Level clamped")
    slave.set_registers(1, "hr", 111, [12000])
    wait_for(lambda: _reads(items, "Level", 50.0), 15, "Level inside")


def test_writes_invert_the_scaling_exactly(
    slave: PymodbusSlave, device: tuple[em.DriverModbusRtu, dict[str, Any]]
) -> None:
    drv, items = device
    wait_for(lambda: _reads(items, "W", 12.34), 15, "W first read (its factor known)")
    assert drv.write_address("W", 3.21) == (True, None)
    assert slave.registers(1, "hr", 0) == [321]
    assert drv.write_address("Temp", 25.5) == (True, None)
    assert slave.registers(1, "hr", 100) == [655]
    assert items["Temp"].value == 25.5
    assert drv.write_address("Current", 8) == (True, None)
    assert slave.registers(1, "hr", 110) == [6912]
    ok, err = drv.write_address("Current", 20.5)
    assert not ok and err is not None and "allowed 4..20 (engMin..engMax)" in err, err
    ok, err = drv.write_address("W", 400)
    assert not ok and err is not None and "allowed -327.68..327.67 (Int16 on the device)" in err
    assert slave.registers(1, "hr", 110) == [6912]
