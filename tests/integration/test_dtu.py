"""Listen mode (rtu-over-tcp-server): DTUs dial in to the driver's listen port.

The DTUs are our simulator in DTU-client mode (``Simulator.dial``): it connects,
registers and answers as RTU slaves.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

import edgemodbus as em
from edgemodbus import dtu
from edgemodbus.config import DeviceDriverStatus, ItemStatus
from edgemodbus.datatypes import Area
from edgemodbus.simulator import Simulator, default_register
from tests.waiting import wait_for


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def dtu_device(port: int, dtu_id: str, slave: int = 1, addresses: tuple[int, ...] = (0, 1, 7),
               **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": dtu_id, "registration": "text", "registrationTimeout": 400,
        "slaveId": slave, "readTimeout": 300, "readCycle": 100, "reconnectInterval": 300,
        "byteTimeout": 50,
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": f"{dtu_id or 'dtu'}-{slave}"},
        "communication": comm,
        "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in addresses],
    })


@contextmanager
def running(*cfgs: em.DeviceConfig) -> Iterator[list[em.DriverModbusRtu]]:
    drivers = []
    try:
        for cfg in cfgs:
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


def values(cfg: em.DeviceConfig) -> list[Any]:
    return [it.value if it.status is ItemStatus.OK else None for it in cfg.address_list]


def ok(cfg: em.DeviceConfig) -> Callable[[], bool]:
    return lambda: all(it.status is ItemStatus.OK for it in cfg.address_list)


def test_two_dtus_on_one_port_each_feed_their_own_devices() -> None:
    port = free_port()
    a1, a2 = dtu_device(port, "DTU-A", 1), dtu_device(port, "DTU-A", 2)
    b1 = dtu_device(port, "DTU-B", 1)  # same slave id, other DTU
    with ExitStack() as stack:
        sim_a = stack.enter_context(Simulator(slaves=[1, 2]))
        sim_b = stack.enter_context(Simulator(slaves=[1]))
        sim_b.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [11, 12, 13, 14, 15, 16, 17, 18])
        stack.enter_context(running(a1, a2, b1))
        listener = dtu.registry.listener("127.0.0.1", port)
        assert listener is not None  # one listener serves both DTUs
        sim_b.dial("127.0.0.1", port, registration=b"DTU-B")
        sim_a.dial("127.0.0.1", port, registration=b"DTU-A\r\n")
        for cfg in (a1, a2, b1):
            wait_for(ok(cfg), what=f"{cfg.organization.device_code} Ok")
        assert values(a1) == [default_register(1, a) for a in (0, 1, 7)]
        assert values(a2) == [default_register(2, a) for a in (0, 1, 7)]
        assert values(b1) == [11, 12, 18]  # never a value from the other DTU
        assert listener.stats["registered"] == 2


def test_not_connected_then_dial_in_then_a_reconnect_replaces_the_old_link() -> None:
    port = free_port()
    cfg = dtu_device(port, "861234567890123", registration="regex",
                     registrationPattern=r"IMEI:(\d{15})")
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        wait_for(lambda: all(it.status is ItemStatus.INVALID for it in cfg.address_list))
        assert all("DTU not connected" in (it.error_reason or "") for it in cfg.address_list)
        first = sim.dial("127.0.0.1", port, registration=b"IMEI:861234567890123\r\n")
        wait_for(ok(cfg), what="values after dial-in")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        second = sim.dial("127.0.0.1", port, registration=b"IMEI:861234567890123\r\n")
        wait_for(lambda: first.closed, what="the old connection closed")
        assert not second.closed
        requests = drv.stats()["requests"]
        wait_for(lambda: drv.stats()["requests"] > requests + 3, what="polling on the new link")
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING
        assert drv.stats()["line"]["reconnects"] >= 1
        second.close()  # the DTU goes away: Reconnecting, items Invalid
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING)
        wait_for(lambda: all("DTU not connected" in (it.error_reason or "")
                             for it in cfg.address_list), what="DTU not connected")


def test_unknown_and_silent_dtus_are_closed_after_the_timeout_and_take_no_place() -> None:
    port = free_port()
    cfg = dtu_device(port, "GOOD", registrationTimeout=300)
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        good = sim.dial("127.0.0.1", port, registration=b"GOOD")
        wait_for(ok(cfg))
        started = time.monotonic()
        unknown = sim.dial("127.0.0.1", port, registration=b"EVIL")
        silent = sim.dial("127.0.0.1", port)
        wait_for(lambda: unknown.closed and silent.closed, what="both closed")
        assert time.monotonic() - started >= 0.25  # held until the registration timeout
        listener = dtu.registry.listener("127.0.0.1", port)
        assert listener is not None
        assert listener.stats["unknown"] == 1 and listener.stats["silent"] == 1
        assert not good.closed
        requests = drv.stats()["requests"]
        wait_for(lambda: drv.stats()["requests"] > requests + 2)
        assert drv.device_driver_status is DeviceDriverStatus.RUNNING


def test_without_registration_the_single_dtu_takes_the_connection() -> None:
    port = free_port()
    cfg = dtu_device(port, "", registration="none", tcpPort=port, listenPort=None)
    with Simulator(slaves=[1]) as sim, running(cfg):
        sim.dial("127.0.0.1", port)
        wait_for(ok(cfg))
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]


def test_heartbeats_are_discarded_wherever_they_arrive() -> None:
    port = free_port()
    cfg = dtu_device(port, "DTU7", heartbeat="HB")
    with Simulator(slaves=[1]) as sim, running(cfg) as (drv,):
        client = sim.dial("127.0.0.1", port, registration=b"HBDTU7", heartbeat=b"HB",
                          heartbeat_interval=0.03, heartbeat_before_reply=True)
        wait_for(ok(cfg))
        responses = drv.stats()["responses"]
        wait_for(lambda: drv.stats()["responses"] > responses + 5)
        stats = drv.stats()
        assert values(cfg) == [default_register(1, a) for a in (0, 1, 7)]
        assert stats["timeouts"] == 0 and stats["protocolErrors"] == 0
        assert stats["line"]["heartbeats"] >= 5
        assert client.heartbeats_sent >= stats["line"]["heartbeats"] - 1


def test_devices_on_one_port_must_agree_on_its_registration() -> None:
    port = free_port()
    a = dtu_device(port, "A")
    b = dtu_device(port, "0B", registration="hex")
    with running(a):
        drv = em.DriverModbusRtu()
        try:
            drv.start_device(b.organization, b.communication, b.address_list)
        except ValueError as exc:
            assert "registration 'hex'" in str(exc)
        else:
            drv.stop_device()
            raise AssertionError("conflicting registration accepted")
    assert dtu.registry.listener("127.0.0.1", port) is None  # stopped with its last device
