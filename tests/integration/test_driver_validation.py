"""start_device and update_addresses check everything before a line is touched: a
configuration the codec, the planner or the address parser cannot take is a clear
error (field, value, what is allowed) and leaves no thread, fd or line behind."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError, DeviceAddressItem
from edgemodbus.datatypes import ItemStatus
from edgemodbus.sim import Simulator
from tests.peers import free_port
from tests.waiting import wait_for


def _fds() -> set[str]:
    fds = set()
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            fds.add(f"{name}->{os.readlink(f'/proc/self/fd/{name}')}")
    return fds


def _line(transport: str) -> dict[str, Any]:
    """A line nothing answers on: a refused TCP port, a listen port, a missing tty."""
    if transport == "rtu":
        return {"transport": "rtu", "comPort": "/dev/edgemodbus-no-such-tty"}
    if transport == "rtu-over-tcp-server":
        return {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                "listenPort": free_port()}
    return {"transport": transport, "tcpHost": "127.0.0.1", "tcpPort": free_port()}


def _item(name: str = "x", **fields: Any) -> DeviceAddressItem:
    fields.setdefault("address", "hr:1")
    fields.setdefault("device_data_type", "Int16")
    return DeviceAddressItem(name=name, **fields)


def _changed(item: DeviceAddressItem, **fields: Any) -> DeviceAddressItem:
    """An item loaded valid and changed afterwards (models do not validate assignment)."""
    for key, value in fields.items():
        setattr(item, key, value)
    return item


# (items, communication changes, organisation changes, the error line expected)
BAD: dict[str, tuple[Callable[[], list[DeviceAddressItem]], dict[str, Any], dict[str, Any],
                     str]] = {
    "quantity above one read": (
        lambda: [_changed(_item(device_data_type="String", quantity=4), quantity=200)], {}, {},
        "addressList[0].quantity 200: must be 1..125"),
    "quantity 0": (
        lambda: [_changed(_item(device_data_type="String", quantity=4), quantity=0)], {}, {},
        "addressList[0].quantity 0: must be 1..125"),
    "multiplier on a String": (
        lambda: [_item(device_data_type="String", quantity=2, data_multiplier=2)], {}, {},
        "addressList[0].dataMultiplier 2.0: not allowed: String values take no multiplier, "
        "use 1"),
    "DateTime as a conversion target": (
        lambda: [_item(converted_data_type="DateTime")], {}, {},
        "addressList[0].convertedDataType 'DateTime': not allowed: a numeric type, Boolean or "
        "String"),
    "bytes codec as encoding": (
        lambda: [_changed(_item(device_data_type="String", quantity=2), encoding="base64")],
        {}, {},
        "addressList[0].encoding 'base64': not allowed: a text encoding: utf-8, gbk, ascii..."),
    "negative deadband": (
        lambda: [_changed(_item(deadband=1), deadband=-1)], {}, {},
        "addressList[0].deadband -1: must be 0 or more"),
    "bit index 16": (
        lambda: [_changed(_item(device_data_type="Boolean"), address="hr:1.16")], {}, {},
        "addressList[0].address 'hr:1.16': bit 16 out of range 0..15"),
    "registers past 65535": (
        lambda: [_item(address="hr:65530", device_data_type="String", quantity=10)], {}, {},
        "addressList[0].address 'hr:65530': 10 registers from here run past the last "
        "address 65535"),
    "block of 126 registers": (
        lambda: [_item()], {"max_block_read_register_count": 126}, {},
        "communication.maxBlockReadRegisterCount 126: must be 1..125"),
    "block of 2001 bits": (
        lambda: [_item()], {"max_block_read_bit_count": 2001}, {},
        "communication.maxBlockReadBitCount 2001: must be 1..2000"),
    "organisation read cycle": (
        lambda: [_item()], {}, {"read_cycle": -1},
        "organization.readCycle -1: must be 0..86400000"),
}


@pytest.mark.parametrize("transport", ["rtu-over-tcp", "tcp", "rtu", "rtu-over-tcp-server"])
@pytest.mark.parametrize("case", list(BAD))
def test_failed_start_names_the_problem_and_leaves_nothing_behind(
    case: str, transport: str
) -> None:
    make_items, comm_changes, org_changes, expected = BAD[case]
    comm = em.DriverModbusRtuParameter.model_validate(
        {**_line(transport), "readTimeout": 100, "reconnectInterval": 100})
    org = em.DeviceOrganizationParameter(device_code="bad")
    for key, value in comm_changes.items():
        setattr(comm, key, value)
    for key, value in org_changes.items():
        setattr(org, key, value)
    items = make_items()
    threads, fds = set(threading.enumerate()), _fds()
    lines = em.DriverModbusRtu.registry.lines()
    drv = em.DriverModbusRtu()
    with pytest.raises(ConfigError) as info:
        drv.start_device(org, comm, items)
    assert [str(p) for p in info.value.problems] == [expected]
    assert set(threading.enumerate()) == threads
    assert _fds() == fds
    assert em.DriverModbusRtu.registry.lines() == lines
    assert drv.device_driver_status is em.DeviceDriverStatus.STOPPED
    assert drv.stop_device() is False


@pytest.fixture
def simulator() -> Iterator[tuple[Simulator, int]]:
    with Simulator([1]) as sim:
        yield sim, sim.serve_tcp("127.0.0.1", 0)


def test_driver_starts_after_a_failed_start(simulator: tuple[Simulator, int]) -> None:
    _, port = simulator
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
                          "readCycle": 100, "readTimeout": 300},
        "addressList": [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}],
    })
    drv = em.DriverModbusRtu()
    bad = [_item(device_data_type="String", quantity=2, data_multiplier=2)]
    with pytest.raises(ConfigError):
        drv.start_device(cfg.organization, cfg.communication, bad)
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list) is True
    try:
        wait_for(lambda: cfg.address_list[0].status is ItemStatus.OK)
    finally:
        drv.stop_device()


@pytest.mark.parametrize("bad", [
    lambda: [_item("b", device_data_type="String", quantity=2, data_multiplier=2)],
    lambda: [_changed(_item("b", device_data_type="String", quantity=4), quantity=200)],
    lambda: [_item("b", converted_data_type="DateTime")],
])
def test_refused_update_changes_nothing(
    simulator: tuple[Simulator, int], bad: Callable[[], list[DeviceAddressItem]]
) -> None:
    sim, port = simulator
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
                          "readCycle": 50, "readTimeout": 300},
        "addressList": [{"name": "a", "address": "hr:1", "deviceDataType": "UInt16"}],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        wait_for(lambda: cfg.address_list[0].status is ItemStatus.OK)
        plan = drv.read_plan()
        with pytest.raises(ConfigError, match=r"^addressList\[0\]\.(dataMultiplier|quantity|"
                           r"convertedDataType) "):
            drv.update_addresses(bad())
        assert drv.read_plan() == plan
        assert list(drv.snapshot()["items"]) == ["a"] and drv.data_item_count == 1
        sim.slave(1).set_registers(em.Area.HOLDING_REGISTER, 1, [4321])
        wait_for(lambda: cfg.address_list[0].value == 4321, what="polling goes on")
    finally:
        drv.stop_device()
