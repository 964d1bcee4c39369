"""Wrapped report framing (edge MCU: FF AA + register address + RTU frame + 0D) end to
end: unsolicited reports update items, integrity polls and writes go wrapped, bad frames
are dropped and counted.  The peer is our simulator in wrapped mode."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import edgemodbus as em
from edgemodbus.config import DeviceDriverStatus, ItemStatus
from edgemodbus.datatypes import Area
from edgemodbus.simulator import DtuClient, Simulator
from tests.integration.test_dtu import free_port, wait_for

ADDRESSES = (1, 2, 30, 80)


def wrapped_device(comm: dict[str, Any]) -> em.DeviceConfig:
    base: dict[str, Any] = {
        "framing": "wrapped-report", "slaveId": 1, "readTimeout": 300,
        "reconnectInterval": 300, "byteTimeout": 50,
    }
    base.update(comm)
    return em.load_device_config({
        "organization": {"deviceCode": "mcu"},
        "communication": base,
        "addressList": [{"name": f"r{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in ADDRESSES],
    })


@contextmanager
def running(cfg: em.DeviceConfig, **callbacks: Any) -> Iterator[em.DriverModbusRtu]:
    drv = em.DriverModbusRtu()
    for name, fn in callbacks.items():
        setattr(drv, name, fn)
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        yield drv
    finally:
        drv.stop_device()


def value_of(cfg: em.DeviceConfig, name: str) -> Any:
    item = next(it for it in cfg.address_list if it.name == name)
    return item.value if item.status is ItemStatus.OK else None


def test_report_only_device_takes_unsolicited_reports_in_listen_mode() -> None:
    port = free_port()
    cfg = wrapped_device({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": "MCU1", "registration": "text",
                          "readCycle": 0, "heartbeatHex": "FE"})
    seen: list[tuple[str, Any]] = []
    with Simulator(slaves=[1]) as sim, running(
        cfg, address_updated_callback=lambda it: seen.append((it.name, it.value))
    ) as drv:
        regs = list(range(100, 180))
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 1, regs)
        client: DtuClient = sim.dial("127.0.0.1", port, registration=b"MCU1", wrapped=True)
        wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING)
        # a batch report of 80 registers from address 1 (the seed's second example's shape)
        client.push_report(1, Area.HOLDING_REGISTER, 1, 80)
        wait_for(lambda: value_of(cfg, "r80") is not None, what="batch report applied")
        assert [value_of(cfg, f"r{a}") for a in ADDRESSES] == [100, 101, 129, 179]
        assert ("r30", 129) in seen
        # a single report (seed example 1: address 1 = 773), split over two segments,
        # behind a heartbeat and garbage, plus a frame with a bad CRC
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 1, [773])
        good = bytes.fromhex("FFAA0001010302030578B70D")
        bad_crc = bytes.fromhex("FFAA0001010302030578B80D")
        client.send(b"\xfe" + bad_crc + b"\x00\x13" + good[:5])
        time.sleep(0.05)
        client.send(good[5:])
        wait_for(lambda: value_of(cfg, "r1") == 773, what="single report applied")
        stats = drv.stats()
        assert stats["reports"] == 2
        assert stats["line"]["droppedFrames"] >= 2  # bad CRC, then the noise before FF AA
        assert stats["line"]["heartbeats"] == 1
        assert stats["requests"] == 0  # report-only: never polled
        # a report for another slave or area touches nothing of this device
        sim.add_slave(2)
        client.push_report(2, Area.HOLDING_REGISTER, 1, 2)
        client.push_report(1, Area.INPUT_REGISTER, 1, 2)
        wait_for(lambda: drv.stats()["line"]["reports"] >= 4)
        assert value_of(cfg, "r1") == 773 and drv.stats()["reports"] == 2


def test_client_mode_integrity_poll_and_wrapped_writes() -> None:
    with Simulator(slaves=[1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0, wrapped=True)
        cfg = wrapped_device({"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": port, "readCycle": 150,
                              "maxMergeAddressGap": 100})
        sim.slave(1).set_registers(Area.HOLDING_REGISTER, 0, list(range(500, 600)))
        with running(cfg) as drv:
            wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                     what="integrity poll")
            assert [value_of(cfg, f"r{a}") for a in ADDRESSES] == [501, 502, 530, 580]
            ok, err = drv.write_address("r30", 4242)
            assert ok, err
            assert sim.slave(1).get_registers(Area.HOLDING_REGISTER, 30) == [4242]
            # a report pushed between polls is applied too
            sim.slave(1).set_registers(Area.HOLDING_REGISTER, 2, [7])
            (client,) = sim.clients()
            client.push_report(1, Area.HOLDING_REGISTER, 2, 1)
            wait_for(lambda: value_of(cfg, "r2") == 7)
            # no wrapped echo within the response timeout: the write failed
            sim.slave(1).set_faults(silent=True)
            started = time.monotonic()
            ok, err = drv.write_address("r1", 1)
            assert not ok and err is not None and "timeout" in err
            assert time.monotonic() - started >= 0.25
            assert drv.stats()["writeErrors"] == 1
