"""What a DTU stream's extras and the frame trace cost, against the same fleet without
them, in the same run.

A fleet of simulated DTUs (our simulator in DTU-client mode, in its own process so that
its CPU is not ours; one slave of 100 UInt16 tags each, one read of 100 registers per
cycle) dials in to a listen port, once per phase, and our CPU per tag read (all threads)
is measured while it is polled:

- plain: RTU frames only (the baseline);
- heartbeats: every DTU sends a heartbeat every second (cellular DTUs send one every few
  seconds; once a second makes the cost show in a short window);
- wrapped: edge-MCU frames, each DTU pushing a one-register report per cycle.

Then the frame trace: the plain fleet polled in connect mode (one RTU-over-TCP line per
DTU) with the ``edgemodbus.line`` logger at WARNING, then at DEBUG with a handler that
formats every record (to /dev/null), as ``-vv`` does.  Gated (bench/gate.py): heartbeats
and wrapped over plain, trace over no trace.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import socket
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from typing import Any

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.sim import Simulator

TAGS = 100
CYCLE_MS = 250
SLAVE = 1
ADDRESS_LIST = [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                for a in range(TAGS)]


def _fleet(conn: Connection, n: int) -> None:
    """The child: one simulator (one thread) that dials n DTUs of the kind asked for to
    the port given, pushes the wrapped DTUs' reports once a cycle, and serves n TCP
    ports (the connect-mode lines of the trace phases)."""
    with Simulator([SLAVE], size=TAGS) as sim:
        conn.send([sim.serve_tcp("127.0.0.1", 0) for _ in range(n)])
        clients: list[Any] = []
        pushing = False  # the wrapped fleet is up: a report per DTU and cycle
        while True:
            if conn.poll(CYCLE_MS / 1000):
                try:
                    msg = conn.recv()
                except EOFError:
                    return
                if msg == "stop":
                    return
                kind, port = msg
                clients, pushing = [], kind == "wrapped"
                for k in range(n):
                    registration = f"{kind}{k:03d}".encode()
                    if kind == "heartbeat":
                        clients.append(sim.dial("127.0.0.1", port, registration=registration,
                                                heartbeat=b"HB", heartbeat_interval=1.0))
                    else:
                        clients.append(sim.dial("127.0.0.1", port, registration=registration,
                                                wrapped=kind == "wrapped"))
                conn.send("dialled")
            elif pushing:
                for client in clients:
                    with contextlib.suppress(OSError):
                        client.push_report(SLAVE, Area.HOLDING_REGISTER, 0, 1)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _listen_config(port: int, kind: str, k: int) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": f"{kind}{k:03d}", "registration": "text", "registrationTimeout": 10000,
        "slaveId": SLAVE, "readCycle": CYCLE_MS, "readTimeout": 1000,
        # the fleet dials from one address at once: the caps made for the internet raised
        "maxUnregistered": 1000, "maxUnregisteredPerSource": 1000,
    }
    if kind == "heartbeat":
        comm["heartbeatHex"] = b"HB".hex().upper()
    if kind == "wrapped":
        comm["framing"] = "wrapped-report"
    return em.load_device_config({"organization": {"deviceCode": f"{kind}{k:03d}"},
                                  "communication": comm, "addressList": ADDRESS_LIST})


def _connect_config(tcp_port: int, k: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"tcp{k:03d}"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": tcp_port, "slaveId": SLAVE, "readCycle": CYCLE_MS,
                          "readTimeout": 1000},
        "addressList": ADDRESS_LIST,
    })


@contextlib.contextmanager
def _polling(configs: list[em.DeviceConfig]) -> Iterator[list[em.DriverModbusRtu]]:
    drivers = [em.DriverModbusRtu() for _ in configs]
    try:
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        yield drivers
    finally:
        for drv in drivers:
            drv.stop_device()


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


def test_stream_extras_and_trace_cost(benchmark: Any) -> None:
    n = scale(100, 20)
    window = 4.0 if not QUICK else 1.5
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_fleet, args=(child, n), daemon=True)
    proc.start()
    costs: dict[str, float] = {}
    stats: dict[str, dict[str, int]] = {}
    try:
        assert parent.poll(60), "the simulator did not start"
        tcp_ports = parent.recv()

        def listen_phase(kind: str) -> float:
            port = _free_port()
            configs = [_listen_config(port, kind, k) for k in range(n)]
            with _polling(configs) as drivers:
                parent.send((kind, port))
                assert parent.poll(60) and parent.recv() == "dialled"
                _wait_all_ok(configs, 60)
                time.sleep(CYCLE_MS / 1000)  # pacing: the start-up reads, in step, are behind us
                cost = min(_cpu_per_tag_read(drivers, window) for _ in range(2))
                lines = [d.stats()["line"] for d in drivers]
                stats[kind] = {"heartbeats": sum(s["heartbeats"] for s in lines),
                               "reports": sum(s["reports"] for s in lines),
                               "timeouts": sum(d.stats()["timeouts"] for d in drivers)}
            return cost

        def connect_phase() -> float:
            configs = [_connect_config(tcp_ports[k], k) for k in range(n)]
            with _polling(configs) as drivers:
                _wait_all_ok(configs, 60)
                time.sleep(CYCLE_MS / 1000)  # pacing: the start-up reads, in step, are behind us
                return min(_cpu_per_tag_read(drivers, window) for _ in range(2))

        costs["plain"] = benchmark.pedantic(lambda: listen_phase("plain"), rounds=1,
                                            iterations=1)
        costs["heartbeat"] = listen_phase("heartbeat")
        costs["wrapped"] = listen_phase("wrapped")
        costs["no trace"] = connect_phase()
        line_log = logging.getLogger("edgemodbus.line")
        level, propagate = line_log.level, line_log.propagate
        with open(os.devnull, "w") as sink:
            handler = logging.StreamHandler(sink)
            handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
            line_log.addHandler(handler)
            line_log.setLevel(logging.DEBUG)
            line_log.propagate = False
            try:
                costs["trace"] = connect_phase()
            finally:
                line_log.removeHandler(handler)
                line_log.setLevel(level)
                line_log.propagate = propagate
    finally:
        parent.send("stop")
        proc.join(20)
        parent.close()
        child.close()
    heartbeat = costs["heartbeat"] / costs["plain"]
    wrapped = costs["wrapped"] / costs["plain"]
    trace = costs["trace"] / costs["no trace"]
    benchmark.extra_info.update({"dtus": n, "us_per_tag": costs, "stats": stats,
                                 "heartbeat_vs_plain": heartbeat,
                                 "wrapped_vs_plain": wrapped, "trace_vs_none": trace})
    report(
        f"DTU streams and the frame trace: {n} DTUs x 1 slave x {TAGS} tags, "
        f"readCycle {CYCLE_MS} ms",
        [
            ("plain RTU frames (listen mode)", costs["plain"], "us/tag"),
            ("heartbeat every second", costs["heartbeat"], "us/tag"),
            ("  heartbeats / plain (gated)", heartbeat, "x"),
            ("wrapped, a report per cycle", costs["wrapped"], "us/tag"),
            ("  wrapped / plain (gated)", wrapped, "x"),
            ("connect mode, no trace", costs["no trace"], "us/tag"),
            ("connect mode, frame trace at DEBUG", costs["trace"], "us/tag"),
            ("  trace / no trace (gated)", trace, "x"),
            ("heartbeats counted", stats["heartbeat"]["heartbeats"], ""),
            ("reports received", stats["wrapped"]["reports"], ""),
            ("timeouts", sum(s["timeouts"] for s in stats.values()), ""),
        ],
    )
    assert stats["heartbeat"]["heartbeats"] > 0 and stats["wrapped"]["reports"] > 0
    gate.record("stream.heartbeat_vs_plain", heartbeat)
    gate.record("stream.wrapped_vs_plain", wrapped)
    gate.record("line.trace_vs_none", trace)
