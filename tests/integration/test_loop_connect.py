"""Connect-mode RTU-over-TCP lines on the loop engine (``engine: "loop"``; line/loop.py,
line/loop_connect.py): libmodbus framing on our side is replaced by the loop link's
(csrc/emb_loop_link.c), pymodbus slaves in their own processes on the other.

Every test runs its lines on one loop thread (``loopThreads`` 1), so a connect or a
read that blocked the loop would show as a late cycle of every other line."""

from __future__ import annotations

import contextlib
import itertools
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from tests.peers import PymodbusSlave, default_register, free_port
from tests.waiting import wait_for

REGISTERS = 10


def comm(port: int, slave: int = 1, **extra: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
        "slaveId": slave, "readCycle": 100, "readTimeout": 300, "byteTimeout": 50,
        "reconnectInterval": 200, "connectTimeout": 1000, "engine": "loop",
        "loopThreads": 1,
    }
    base.update(extra)
    return base


def device(port: int, slave: int = 1, code: str = "", **extra: Any) -> em.DeviceConfig:
    items = [{"name": f"h{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
             for a in range(REGISTERS)]
    items.append({"name": "i7", "address": "ir:7", "deviceDataType": "UInt16"})
    return em.load_device_config({
        "organization": {"deviceCode": code or f"dev{port}-{slave}"},
        "communication": comm(port, slave, **extra), "addressList": items})


@contextlib.contextmanager
def running(*configs: em.DeviceConfig, **callbacks: Any) -> Iterator[list[em.DriverModbusRtu]]:
    drivers: list[em.DriverModbusRtu] = []
    try:
        for cfg in configs:
            drv = em.DriverModbusRtu()
            for name, fn in callbacks.items():
                setattr(drv, name, fn)
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


def all_ok(*configs: em.DeviceConfig) -> bool:
    return all(it.status is ItemStatus.OK for cfg in configs for it in cfg.address_list)


def exact(cfg: em.DeviceConfig, unit: int) -> bool:
    """Every value is the slave's (tests/peers.py default_register)."""
    values = {it.name: it.value for it in cfg.address_list}
    want = {f"h{a}": default_register(unit, "hr", a) for a in range(REGISTERS)}
    want["i7"] = default_register(unit, "ir", 7)
    return values == want


def engine_threads() -> list[str]:
    """The engines' threads alive, line workers by name, loop workers as "loop"."""
    names = [t.name for t in threading.enumerate()]
    return sorted([n for n in names if n.startswith("edgemodbus-line")] +
                  ["loop" for n in names if n.startswith("edgemodbus-loop ")])


def test_endpoints_share_one_loop_thread_and_values_are_exact() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as a, \
            PymodbusSlave("rtu-over-tcp", units=(1,)) as b:
        configs = [device(a.port, 1), device(a.port, 2), device(b.port, 1)]
        with running(*configs) as drivers:
            wait_for(lambda: all_ok(*configs), what="every value Ok")
            assert engine_threads() == ["loop"]  # no thread per line
            assert exact(configs[0], 1) and exact(configs[1], 2) and exact(configs[2], 1)
            assert all(d.device_driver_status is DeviceDriverStatus.RUNNING for d in drivers)
            cycles = [d.stats()["cycles"] for d in drivers]
            wait_for(lambda: all(d.stats()["cycles"] >= c + 3
                                 for d, c in zip(drivers, cycles, strict=True)),
                     what="three more cycles of every device")
    wait_for(lambda: not engine_threads(), what="the loop thread gone with its last line")


def test_a_write_goes_out_on_the_loop_and_is_read_back() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        cfg = device(slave.port)
        with running(cfg) as (drv,):
            wait_for(lambda: all_ok(cfg), what="values Ok")
            assert drv.write_address("h3", 4242) == (True, None)
            assert slave.registers(1, "hr", 3) == [4242]
            ok, err = drv.write_addresses([("h4", 7), ("h5", 65535)])
            assert (ok, err) == (True, None)
            assert slave.registers(1, "hr", 4, 2) == [7, 65535]
            item = {it.name: it for it in cfg.address_list}
            wait_for(lambda: (item["h3"].value, item["h4"].value, item["h5"].value)
                     == (4242, 7, 65535), what="the written values read back")


def test_a_slave_that_goes_away_and_comes_back() -> None:
    """The line worker's semantics: link down with the reason, Reconnecting, connects
    refused and retried with backoff, writes failing at once meanwhile; then up again
    with exact values; the other endpoint on the same loop thread polls throughout."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as gone, \
            PymodbusSlave("rtu-over-tcp", units=(1,)) as steady:
        cfg, other = device(gone.port), device(steady.port)
        with running(cfg, other) as (drv, other_drv):
            wait_for(lambda: all_ok(cfg, other), what="values Ok")
            gone.kill()
            wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RECONNECTING,
                     what="Reconnecting")
            item = cfg.address_list[0]
            assert item.status is ItemStatus.INVALID and "link" in (item.error_reason or "")
            assert item.value == default_register(1, "hr", 0)  # the last good value stays
            wait_for(lambda: "connect failed: Connection refused" in (item.error_reason or ""),
                     what="the refused connect as the reason")
            failures = drv.stats()["line"]["connectFailures"]
            wait_for(lambda: drv.stats()["line"]["connectFailures"] >= failures + 2,
                     what="connects retried")
            ok, err = drv.write_address("h1", 5)
            assert not ok and "link is down" in (err or "")
            cycles = other_drv.stats()["cycles"]
            wait_for(lambda: other_drv.stats()["cycles"] >= cycles + 5,
                     what="the other endpoint polled while this one is down")
            assert all_ok(other)
            gone.restart()
            wait_for(lambda: drv.device_driver_status is DeviceDriverStatus.RUNNING,
                     what="Running again")
            wait_for(lambda: all_ok(cfg), what="values Ok again")
            assert exact(cfg, 1) and drv.stats()["reconnects"] >= 1
            assert engine_threads() == ["loop"]


@contextlib.contextmanager
def hanging_port() -> Iterator[int]:
    """A port whose connects hang: a listening socket whose accept queue is full
    (never accepted), so the kernel drops further SYNs (the peer retransmits)."""
    listener = socket.socket()
    fillers: list[socket.socket] = []
    try:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        for _ in range(8):
            filler = socket.socket()
            filler.settimeout(0.5)
            try:
                filler.connect(listener.getsockname())
            except OSError:  # the queue is full: this one hangs too
                filler.close()
                break
            fillers.append(filler)
        else:
            pytest.fail("the accept queue never filled")
        yield int(listener.getsockname()[1])
    finally:
        for filler in fillers:
            filler.close()
        listener.close()


def test_dead_endpoints_do_not_delay_the_others() -> None:
    """A refused endpoint, one whose connect hangs until connectTimeout (3 s), and one
    that accepts but never answers share the loop thread with a good one: the good
    one's cycle start-to-start stays well under the connect timeout across a hanging
    connect (a connect blocking the loop would stop every link for 3 s; the margin is
    for a loaded machine)."""
    refused = free_port()
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(16)  # connects complete in the kernel; nothing is ever read
    stamps: list[float] = []
    measuring = threading.Event()

    def stamp(_batch: object) -> None:  # reportMode cycle: one batch per cycle
        if measuring.is_set():
            stamps.append(time.monotonic())

    extra = {"retries": 0, "offlineAfterFailedCycles": 1, "maxBackoff": 1000}
    try:
        with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave, hanging_port() as hang:
            good = device(slave.port, reportMode="cycle")
            dead = [device(refused, code="refused", **extra),
                    device(hang, code="hanging", connectTimeout=3000, **extra),
                    device(silent.getsockname()[1], code="silent", **extra)]
            with running(good, addresses_updated_callback=stamp), \
                    running(*dead) as (d_refused, d_hang, d_silent):
                wait_for(lambda: all_ok(good), what="the good device Ok")
                hang_item = dead[1].address_list[0]
                wait_for(lambda: "connect timed out after 3 s" in
                         (hang_item.error_reason or ""), what="the hanging connect timed out")
                wait_for(lambda: d_silent.stats()["timeouts"] >= 2, what="silent timeouts")
                assert "Connection refused" in (dead[0].address_list[0].error_reason or "")
                assert engine_threads() == ["loop"]
                measuring.set()
                hangs = d_hang.stats()["line"]["connectFailures"]
                wait_for(lambda: d_hang.stats()["line"]["connectFailures"] >= hangs + 1,
                         what="another hanging connect, measured across")
                measuring.clear()
                assert all_ok(good) and exact(good, 1)
                assert d_refused.device_driver_status is DeviceDriverStatus.RECONNECTING
    finally:
        silent.close()
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert len(gaps) >= 5, gaps
    assert max(gaps) < 2.0, gaps  # readCycle 0.1 s; a blocking connect would be >= 3 s


def test_a_host_name_is_resolved_off_the_loop() -> None:
    """tcpHost "localhost": resolved on the resolver thread, which ends once done;
    each address is tried in turn (::1 may refuse: the pymodbus slave is on 127.0.0.1)."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        cfg = device(slave.port, tcpHost="localhost")
        with running(cfg):
            wait_for(lambda: all_ok(cfg), what="values Ok over a host name")
            assert exact(cfg, 1)
        wait_for(lambda: all(t.name != "edgemodbus-resolve" for t in threading.enumerate()),
                 what="the resolver thread ended")
