"""Two devices of one template share their read plan and compiled blocks
(poll/plan_cache.py, codec/decoder.py); a change to one device's address list never
reaches the other (a real libmodbus master against a pymodbus slave)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for

TEMPLATE = [{"name": f"t{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
            for a in range(10)]


def _config(port: int, unit: int, items: list[dict[str, Any]]) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dev{unit}"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": unit, "readTimeout": 500,
                          "readCycle": 200, "connectTimeout": 2000},
        "addressList": items,
    })


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2), size=200) as peer:
        yield peer


def test_update_addresses_of_one_device_leaves_a_device_sharing_its_plan_alone(
        slave: PymodbusSlave) -> None:
    a_cfg, b_cfg = (_config(slave.port, unit, TEMPLATE) for unit in (1, 2))
    a, b = em.DriverModbusRtu(), em.DriverModbusRtu()
    assert a.start_device(a_cfg.organization, a_cfg.communication, a_cfg.address_list)
    try:
        assert b.start_device(b_cfg.organization, b_cfg.communication, b_cfg.address_list)
        try:
            pa, pb = a._poller, b._poller
            assert pa is not None and pb is not None
            assert all(x is y for x, y in zip(pa.plan, pb.plan, strict=True))
            da, db = pa.slots[0].decoder, pb.slots[0].decoder
            assert da is not None and db is not None and da._shape is db._shape
            wait_for(lambda: all(it.status is ItemStatus.OK
                                 for it in [*a_cfg.address_list, *b_cfg.address_list]))
            plan_b = b.read_plan()
            changed = _config(slave.port, 1, [{"name": "x", "address": "hr:50",
                                               "deviceDataType": "Int32"}])
            a.update_addresses(changed.address_list)
            wait_for(lambda: changed.address_list[0].status is ItemStatus.OK)
            assert [blk["items"] for blk in a.read_plan()] == [["x"]]
            assert b.read_plan() == plan_b  # b keeps its plan, items and values
            for k, item in enumerate(b_cfg.address_list):
                assert item.status is ItemStatus.OK
                assert item.value == default_register(2, "hr", k)
            assert b.address_items == b_cfg.address_list
        finally:
            b.stop_device()
    finally:
        a.stop_device()
