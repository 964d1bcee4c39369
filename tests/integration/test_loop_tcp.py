"""Modbus TCP lines (``transport: "tcp"``) on the loop engine (``engine: "loop"``): the
Dialer's non-blocking connect (line/loop_connect.py), then the loop link's MBAP framing
(csrc/emb_loop_io.c: our transaction ids, the header checked), against pymodbus TCP
slaves in their own processes.  Every line runs on one loop thread (``loopThreads`` 1)."""

from __future__ import annotations

from typing import Any

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from tests.integration.test_loop_connect import all_ok, device, engine_threads, exact, running
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for


def tcp_device(port: int, slave: int = 1, **extra: Any) -> em.DeviceConfig:
    return device(port, slave, transport="tcp", **extra)


def test_tcp_endpoints_share_one_loop_thread_and_values_are_exact() -> None:
    with PymodbusSlave("tcp", units=(1, 2)) as a, PymodbusSlave("tcp", units=(1,)) as b:
        configs = [tcp_device(a.port, 1), tcp_device(a.port, 2), tcp_device(b.port, 1)]
        with running(*configs) as drivers:
            wait_for(lambda: all_ok(*configs), timeout=60, what="every value Ok")
            assert engine_threads() == ["loop"]  # no line worker thread
            assert exact(configs[0], 1) and exact(configs[1], 2) and exact(configs[2], 1)
            assert all(d.device_driver_status is DeviceDriverStatus.RUNNING for d in drivers)
            cycles = [d.stats()["cycles"] for d in drivers]
            wait_for(lambda: all(d.stats()["cycles"] >= c + 3
                                 for d, c in zip(drivers, cycles, strict=True)),
                     timeout=60, what="three more cycles of every device")
            assert all(d.stats()["timeouts"] == 0 for d in drivers)
            assert exact(configs[0], 1) and exact(configs[1], 2) and exact(configs[2], 1)
    wait_for(lambda: not engine_threads(), what="the loop thread gone with its last line")


def test_a_tcp_write_goes_out_on_the_loop_and_is_read_back() -> None:
    with PymodbusSlave("tcp", units=(1,)) as slave:
        cfg = tcp_device(slave.port)
        with running(cfg) as (drv,):
            wait_for(lambda: all_ok(cfg), timeout=60, what="values Ok")
            assert drv.write_address("h3", 4242) == (True, None)
            assert slave.registers(1, "hr", 3) == [4242]
            assert drv.write_addresses([("h4", 7), ("h5", 65535)]) == (True, None)
            assert slave.registers(1, "hr", 4, 2) == [7, 65535]
            item = {it.name: it for it in cfg.address_list}
            wait_for(lambda: (item["h3"].value, item["h4"].value, item["h5"].value)
                     == (4242, 7, 65535), timeout=60, what="the written values read back")


def test_a_tcp_slave_that_goes_away_and_comes_back() -> None:
    with PymodbusSlave("tcp", units=(1,)) as gone, PymodbusSlave("tcp", units=(1,)) as steady:
        cfg, other = tcp_device(gone.port), tcp_device(steady.port)
        with running(cfg, other) as (drv, other_drv):
            wait_for(lambda: all_ok(cfg, other), timeout=60, what="values Ok")
            gone.kill()
            wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING,
                     what="Reconnecting")
            item = cfg.address_list[0]
            assert item.status is ItemStatus.INVALID
            assert item.value == default_register(1, "hr", 0)  # the last good value stays
            wait_for(lambda: "connect failed: Connection refused" in (item.error_reason or ""),
                     what="the refused connect as the reason")
            ok, err = drv.write_address("h1", 5)
            assert not ok and "link is down" in (err or "")
            cycles = other_drv.stats()["cycles"]
            wait_for(lambda: other_drv.stats()["cycles"] >= cycles + 5,
                     what="the other endpoint polled while this one is down")
            assert all_ok(other) and exact(other, 1)
            gone.restart()
            wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING,
                     timeout=60, what="Running again")
            wait_for(lambda: all_ok(cfg), timeout=60, what="values Ok again")
            assert exact(cfg, 1) and drv.stats()["reconnects"] >= 1
            assert engine_threads() == ["loop"]
