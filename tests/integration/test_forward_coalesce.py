"""Read coalescing in forward mode (``forwardCoalesce``): a forwarded read that a block
polled within the configured age covers is answered from that block, with no line
traffic; anything else, and anything after a write, goes to the slave (pymodbus, its own
process, over RTU on TCP).  The replies are checked against the slave's own values,
packed by the test (not by our reply builder)."""

from __future__ import annotations

import random
import struct
import time
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.errors import ModbusTimeoutError
from tests.conftest import SlaveFactory
from tests.integration.test_forward import packed
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

# the device's items: the blocks the line polls (one per area)
SPANS = {"co": (3, 20), "di": (0, 8), "hr": (10, 40), "ir": (5, 6)}
FUNCTION = {"co": 1, "di": 2, "hr": 3, "ir": 4}


def expected(peer: PymodbusSlave, area: str, address: int, count: int) -> bytes:
    """The reply PDU the slave's values make (6.1-6.4)."""
    if area in ("co", "di"):
        data = packed(peer.bits(1, area, address, count))
    else:
        data = struct.pack(f">{count}H", *peer.registers(1, area, address, count))
    return bytes((FUNCTION[area], len(data))) + data


@pytest.fixture
def peer(slave_factory: SlaveFactory) -> PymodbusSlave:
    slave = slave_factory("rtu-over-tcp", units=(1,), size=200)
    rng = random.Random(7)
    for area, (start, count) in SPANS.items():
        if area in ("co", "di"):
            slave.set_bits(1, area, start, [rng.random() < 0.5 for _ in range(count)])
        else:
            slave.set_registers(1, area, start, [rng.randrange(65536) for _ in range(count)])
    return slave


@pytest.fixture
def drivers() -> Iterator[list[em.DriverModbusRtu]]:
    started: list[em.DriverModbusRtu] = []
    yield started
    for drv in started:
        drv.stop_device()


def start(drivers: list[em.DriverModbusRtu], peer: PymodbusSlave, **extra: Any
          ) -> em.DriverModbusRtu:
    communication = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                     "tcpPort": peer.port, "slaveId": 1, "readTimeout": 300,
                     "readCycle": 50, "retries": 0, "reconnectInterval": 300, **extra}
    prefix = {"co": "coil", "di": "di", "hr": "hr", "ir": "ir"}
    items = [{"name": f"{area}{a}", "address": f"{prefix[area]}:{a}",
              "deviceDataType": "Bool" if area in ("co", "di") else "UInt16"}
             for area, (start_, count) in SPANS.items() for a in range(start_, start_ + count)]
    cfg = em.load_device_config({"organization": {"deviceCode": "meter"},
                                 "communication": communication, "addressList": items})
    drv = em.DriverModbusRtu()
    drivers.append(drv)
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING, 15,
             "the device polled")
    return drv


def forward(drv: em.DriverModbusRtu, function: int, address: int, count: int) -> bytes:
    return drv.forward(struct.pack(">BHH", function, address, count)).result(15)


def test_covered_reads_are_answered_from_the_polled_blocks(
        peer: PymodbusSlave, drivers: list[em.DriverModbusRtu]) -> None:
    drv = start(drivers, peer, forwardCoalesce=5000)
    rng = random.Random(11)
    cases = []
    for area, (first, count) in SPANS.items():
        cases.append((area, first, count))  # the whole block
        for _ in range(10):  # random spans inside it
            at = rng.randrange(first, first + count)
            cases.append((area, at, rng.randrange(1, first + count - at + 1)))
    for area, address, count in cases:
        assert forward(drv, FUNCTION[area], address, count) == expected(
            peer, area, address, count), (area, address, count)
    line = drv.stats()["line"]
    assert line["forwardCoalesced"] == len(cases)
    assert line["forwarded"] == 0  # not one of them went to the slave


def test_a_read_not_wholly_inside_a_block_goes_to_the_slave(
        peer: PymodbusSlave, drivers: list[em.DriverModbusRtu]) -> None:
    drv = start(drivers, peer, forwardCoalesce=5000)
    first, count = SPANS["hr"]
    for address, n in ((first - 1, 2), (first + count - 1, 2), (first + count, 1), (0, 125)):
        assert forward(drv, 3, address, n) == expected(peer, "hr", address, n)
    line = drv.stats()["line"]
    assert line["forwarded"] == 4 and line["forwardCoalesced"] == 0


def test_off_by_default(peer: PymodbusSlave, drivers: list[em.DriverModbusRtu]) -> None:
    drv = start(drivers, peer)
    assert forward(drv, 3, *SPANS["hr"]) == expected(peer, "hr", *SPANS["hr"])
    line = drv.stats()["line"]
    assert line["forwarded"] == 1 and line["forwardCoalesced"] == 0


def test_a_read_after_a_write_sees_the_written_value(
        peer: PymodbusSlave, drivers: list[em.DriverModbusRtu]) -> None:
    # a slow poll: the block read before the write would still be "fresh" for 60 s
    drv = start(drivers, peer, forwardCoalesce=60000, readCycle=60000)
    address = SPANS["hr"][0] + 3
    for value in (0x1234, 0xBEEF):
        request = struct.pack(">BHH", 6, address, value)
        assert drv.forward(request).result(15) == request
        assert forward(drv, 3, address, 1) == b"\x03\x02" + struct.pack(">H", value)
    # and a write of the driver's own (write_address) counts the same
    assert drv.write_address("hr13", 7)[0]
    assert forward(drv, 3, address, 1) == b"\x03\x02\x00\x07"
    coil = SPANS["co"][0]
    assert drv.forward(struct.pack(">BHH", 5, coil, 0xFF00)).result(15)
    assert forward(drv, 1, coil, 1) == b"\x01\x01\x01"
    assert drv.stats()["line"]["forwarded"] >= 6  # the reads after writes went out


def test_data_older_than_the_age_is_not_used(
        peer: PymodbusSlave, drivers: list[em.DriverModbusRtu]) -> None:
    drv = start(drivers, peer, forwardCoalesce=200, readTimeout=200)
    assert forward(drv, 4, *SPANS["ir"]) == expected(peer, "ir", *SPANS["ir"])
    peer.set_offline(1)  # polling fails from now on: the blocks age
    time.sleep(0.4)  # pacing: the blocks age past forwardCoalesce
    future = drv.forward(struct.pack(">BHH", 4, *SPANS["ir"]))
    with pytest.raises(ModbusTimeoutError):
        future.result(15)
    assert drv.stats()["line"]["forwardTimeouts"] == 1
