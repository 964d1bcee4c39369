"""A device that joins a line whose link is down learns why at once (line/worker.py
``_notify(late=True)``, line/loop.py's down branch): before, it stayed Connecting with
items Unknown and no reason until the line's next try, up to maxBackoff later, and
`edgemodbus run` said "never answered" without the reason (a flake under load, where
the first connect could fail before the device's poller was attached)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from tests.peers import free_port
from tests.waiting import wait_for


def _config(port: int, slave: int, engine: str) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"d{slave}"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": slave, "readCycle": 100,
                          "reconnectInterval": 120_000, "maxBackoff": 120_000,
                          "engine": engine},
        "addressList": [{"name": "r", "address": "hr:0", "deviceDataType": "UInt16"}],
    })


@pytest.fixture
def drivers() -> Iterator[list[em.DriverModbusRtu]]:
    made: list[em.DriverModbusRtu] = []
    yield made
    for drv in made:
        drv.stop_device()


@pytest.mark.parametrize("engine", ["thread", "loop"])
def test_a_device_joining_a_down_line_gets_its_reason_at_once(
        engine: str, drivers: list[em.DriverModbusRtu]) -> None:
    port = free_port()  # nothing listens: every connect is refused
    first, late = _config(port, 1, engine), _config(port, 2, engine)
    drivers.append(em.DriverModbusRtu())
    assert drivers[0].start_device(first.organization, first.communication, first.address_list)
    wait_for(lambda: first.address_list[0].error_reason is not None,
             what="the first device told the link is down")
    drivers.append(em.DriverModbusRtu())
    assert drivers[1].start_device(late.organization, late.communication, late.address_list)
    assert len(em.DriverModbusRtu.registry.lines()) == 1  # the same line
    # the next try is two minutes away: only the join itself can tell the late device
    wait_for(lambda: late.address_list[0].error_reason is not None,
             what="the late device's reason")
    item = late.address_list[0]
    assert item.status is ItemStatus.INVALID
    assert item.error_reason == first.address_list[0].error_reason
    assert "link down: " in item.error_reason and "refused" in item.error_reason
    assert drivers[1].device_driver_status is DeviceDriverStatus.RECONNECTING
