"""Parallel connections to one Modbus TCP endpoint (``connections``, docs/links.md):
devices spread by unit id (or ``channel``) over that many connections, each its own
line, so a dead slave behind one port of a multi-port gateway costs only its own
connection time.  A pymodbus Modbus TCP slave in its own process plays the gateway."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any

import pytest

import edgemodbus as em
from tests.conftest import SlaveFactory
from tests.integration.test_driver import Running
from tests.waiting import wait_for


def config(port: int, unit: int, **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": unit,
        "readCycle": 50, "readTimeout": 300, "retries": 0,
        "offlineAfterFailedCycles": 1000,  # the dead one keeps timing out
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": f"unit{unit}"}, "communication": comm,
        "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}],
    })


@pytest.mark.parametrize("connections", [1, 4])
def test_a_dead_slave_times_out_only_on_its_own_connection(
        slave_factory: SlaveFactory, connections: int) -> None:
    gateway = slave_factory("tcp", units=(1, 2))  # unit 3 is silent: a dead slave
    with ExitStack() as stack:
        drivers = {unit: stack.enter_context(Running(
            config(gateway.port, unit, connections=connections))) for unit in (1, 2, 3)}
        wait_for(lambda: drivers[3].stats()["line"]["timeouts"] >= 2, 15,
                 "the dead slave's timeouts")
        wait_for(lambda: all(drivers[u].stats()["cycles"] >= 5 for u in (1, 2)), 15,
                 "the live slaves' cycles")
        lines = {u: drivers[u].stats()["line"] for u in (1, 2, 3)}
        if connections == 1:  # one line: everybody waits for the dead slave's timeouts
            assert lines[1]["timeouts"] >= 2 and lines[2]["timeouts"] >= 2
        else:  # units 1, 2, 3 on channels 1, 2, 3: the live lines never saw a timeout
            assert lines[1]["timeouts"] == 0 and lines[2]["timeouts"] == 0
            assert all(lines[u]["connects"] == 1 for u in (1, 2, 3))
        for u in (1, 2):
            assert drivers[u].address_items[0].status == "Ok"


def test_an_explicit_channel_puts_devices_on_one_connection(
        slave_factory: SlaveFactory) -> None:
    gateway = slave_factory("tcp", units=(1, 2))
    with Running(config(gateway.port, 1, connections=2, channel=1)) as one, \
            Running(config(gateway.port, 2, connections=2, channel=1)) as two:
        wait_for(lambda: one.stats()["cycles"] >= 2 and two.stats()["cycles"] >= 2, 15,
                 "both devices polled")
        # one line: the same counters (its requests are both devices')
        assert one.stats()["line"]["requests"] >= one.stats()["requests"] + 2


def test_devices_of_one_endpoint_must_agree_on_connections(
        slave_factory: SlaveFactory) -> None:
    gateway = slave_factory("tcp", units=(1, 2))
    with Running(config(gateway.port, 1, connections=4)):
        cfg = config(gateway.port, 2, connections=2)
        drv = em.DriverModbusRtu()
        with pytest.raises(ValueError, match=r"polled over 4 connection\(s\); this device "
                                             r"asks for 2: devices of one endpoint must "
                                             r"agree on connections"):
            drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
