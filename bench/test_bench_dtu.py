"""Scale of listen mode: many DTUs dial in to one port.

200 simulated DTUs (our simulator in DTU-client mode, in its own process so that its CPU
is not ours) each with 2 slaves of 100 UInt16 tags dial in to one listen port and
register; 400 drivers poll them (one read of 100 registers per slave and cycle).
Reported: the time from start to every value Ok, and our CPU per tag read while
polling (all threads of this process: 200 line workers and the listener).

The baseline, measured in the same run once the listen-mode drivers stopped: the same
fleet in connect mode, each DTU's 2 slaves behind a TCP port of the same simulator (one
RTU-over-TCP line per DTU, the same readCycle).  The ratio listen / connect of CPU per
tag read is gated (bench/gate.py): listen mode should cost no more than connect mode.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import socket
import time
from multiprocessing.connection import Connection
from typing import Any

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.sim import Simulator

TAGS = 100
SLAVES = (1, 2)
CYCLE_MS = 1000
ADDRESS_LIST = [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                for a in range(TAGS)]


def _dtu_fleet(conn: Connection, port: int, n: int) -> None:
    """The child: one simulator (one thread) whose n DTU connections dial in, and which
    serves the same slaves on n TCP ports (the connect-mode baseline)."""
    with Simulator(list(SLAVES), size=TAGS) as sim:
        tcp_ports = [sim.serve_tcp("127.0.0.1", 0) for _ in range(n)]
        for k in range(n):
            sim.dial("127.0.0.1", port, registration=f"DTU{k:03d}".encode())
        conn.send(("dialled", tcp_ports))
        with contextlib.suppress(EOFError):
            conn.recv()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(port: int, k: int, slave: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dtu{k:03d}-{slave}"},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
            "dtuId": f"DTU{k:03d}", "registration": "text", "registrationTimeout": 10000,
            "slaveId": slave, "readCycle": CYCLE_MS, "readTimeout": 1000,
        },
        "addressList": ADDRESS_LIST,
    })


def _connect_config(tcp_port: int, k: int, slave: int) -> em.DeviceConfig:
    """The baseline: DTU ``k``'s slave polled in connect mode (a TCP line of its own)."""
    return em.load_device_config({
        "organization": {"deviceCode": f"tcp{k:03d}-{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": tcp_port,
            "slaveId": slave, "readCycle": CYCLE_MS, "readTimeout": 1000,
        },
        "addressList": ADDRESS_LIST,
    })


def _wait_all_ok(configs: list[em.DeviceConfig], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not all(it.status is ItemStatus.OK for cfg in configs for it in cfg.address_list):
        assert time.monotonic() < deadline, f"not every value Ok within {timeout} s"
        time.sleep(0.05)  # poll: until all Ok (deadline above)


def _cpu_per_tag_read(drivers: list[em.DriverModbusRtu], window: float) -> float:
    """Our CPU (all threads) per tag read over ``window`` seconds of polling, in us."""

    def tag_reads() -> int:
        return sum(d.stats()["responses"] for d in drivers) * TAGS

    reads0, cpu0 = tag_reads(), cpu_seconds()
    time.sleep(window)  # pacing: the window measured
    reads, cpu = tag_reads() - reads0, cpu_seconds() - cpu0
    assert reads > 0
    return 1e6 * cpu / reads


def test_200_dtus_on_one_listen_port(benchmark: Any) -> None:
    n_dtus = scale(200, 20)
    window = 5.0 if not QUICK else 2.0
    port = _free_port()
    configs = [_config(port, k, s) for k in range(n_dtus) for s in SLAVES]
    drivers = [em.DriverModbusRtu() for _ in configs]
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_dtu_fleet, args=(child, port, n_dtus), daemon=True)
    started = time.monotonic()
    connect_drivers: list[em.DriverModbusRtu] = []
    try:
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        proc.start()
        assert parent.poll(60), "the DTU fleet did not dial in"
        status, tcp_ports = parent.recv()
        assert status == "dialled"
        _wait_all_ok(configs, 60)
        all_ok = time.monotonic() - started
        assert all(d.device_driver_status is DeviceDriverStatus.RUNNING for d in drivers)
        us_per_tag = min(benchmark.pedantic(lambda: _cpu_per_tag_read(drivers, window),
                                            rounds=1, iterations=1),
                         _cpu_per_tag_read(drivers, window))
        timeouts = sum(d.stats()["timeouts"] for d in drivers)
        for drv in drivers:
            drv.stop_device()

        # the baseline: the same fleet in connect mode
        connect_configs = [_connect_config(tcp_ports[k], k, s)
                           for k in range(n_dtus) for s in SLAVES]
        for cfg in connect_configs:
            drv = em.DriverModbusRtu()
            connect_drivers.append(drv)
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        _wait_all_ok(connect_configs, 60)
        time.sleep(CYCLE_MS / 1000)  # pacing: the start-up reads, in step, are behind us
        connect_us_per_tag = min(_cpu_per_tag_read(connect_drivers, window)
                                 for _ in range(2))
    finally:
        for drv in drivers + connect_drivers:
            drv.stop_device()
        if proc.is_alive() or proc.exitcode is None:
            parent.send("stop")
            proc.join(20)
        parent.close()
        child.close()
    n_tags = len(configs) * TAGS
    ratio = us_per_tag / connect_us_per_tag
    benchmark.extra_info.update({"dtus": n_dtus, "tags": n_tags, "seconds_to_all_ok": all_ok,
                                 "us_per_tag": us_per_tag, "timeouts": timeouts,
                                 "connect_mode_us_per_tag": connect_us_per_tag,
                                 "ratio_listen_connect": ratio})
    report(
        f"listen mode: {n_dtus} DTUs x {len(SLAVES)} slaves x {TAGS} tags on one port, "
        f"readCycle {CYCLE_MS} ms",
        [
            ("start to every value Ok", all_ok, "s"),
            ("our CPU per tag read (all threads)", us_per_tag, "us/tag"),
            ("  the same fleet in connect mode (baseline)", connect_us_per_tag, "us/tag"),
            ("  listen / connect (gated)", ratio, "x"),
            ("tag reads per second", n_tags * 1000 / CYCLE_MS, "/s (nominal)"),
            ("timeouts while measuring", timeouts, ""),
        ],
    )
    gate.record("dtu.listen_vs_connect", ratio)
