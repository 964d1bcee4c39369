"""Listen mode at scale: 5,000 DTUs dialled in to one listen port of one process.

The target of issue 13 for DTUs that dial in (docs/architecture.md): 5,000 DTUs, each
with 1 slave of 20 UInt16 tags read every 5 s, dial in to one port of this process (the
gateway: one driver per DTU).  The DTUs are a :class:`DtuFleet` in a process of its own
(one asyncio loop, so that its CPU is not ours).  Reported: the time from the first dial
to every value Ok, what the listener accepted and registered, and the gateway's CPU per
DTU per second, RSS per DTU and threads (one line worker per DTU).

Quick mode (``EDGEMODBUS_BENCH_QUICK=1``) uses 300 DTUs.  Environment knobs:
``EDGEMODBUS_BENCH_DTUS`` any count (e.g. 1000); ``EDGEMODBUS_BENCH_DIAL_RATE`` the fleet's
dials per second (1000); ``EDGEMODBUS_BENCH_CYCLE_MS`` the readCycle (5000; 1000 DTUs at
1000 ms make the request rate of 5,000 at 5 s); ``EDGEMODBUS_BENCH_STACK_KB`` the stack
size of the threads this process starts, the line workers (default: RLIMIT_STACK, 8 MB on
Linux), to see what smaller stacks save; ``EDGEMODBUS_BENCH_CRLF=1`` ends each registration
with CR LF (by default it has no end, so the listener takes it after its 0.5 s quiet gap,
line/registration.py).  Memory is per DTU configured (every driver has its thread and
objects, connected or not), CPU per DTU whose values are Ok.  The fleet dials from one
address, so the caps on connections waiting to register (maxUnregistered and
maxUnregisteredPerSource, made for the internet) are raised to the fleet's size.

The run asserts, after its report, that every value became Ok and that no connection
was turned away: the listener registered every connection it accepted (none unknown,
silent or closed for another reason) and no DTU had to dial twice.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import re
import resource
import socket
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import pytest

import edgemodbus as em
from bench.conftest import QUICK, cpu_seconds, report, scale
from edgemodbus.datatypes import ItemStatus
from edgemodbus.line import dtu_registry
from edgemodbus.sim import DtuFleet, raise_open_files_limit

TAGS = 20
SLAVE = 1
CYCLE_MS = int(os.environ.get("EDGEMODBUS_BENCH_CYCLE_MS", "5000"))
ID = "DTU{n:05d}"
N_DTUS = int(os.environ.get("EDGEMODBUS_BENCH_DTUS", "0")) or scale(5000, 300)
DIAL_RATE = float(os.environ.get("EDGEMODBUS_BENCH_DIAL_RATE", "1000"))
END = "\r\n" if os.environ.get("EDGEMODBUS_BENCH_CRLF") == "1" else ""
STACK_KB = int(os.environ.get("EDGEMODBUS_BENCH_STACK_KB", "0"))
STALL = 30.0  # seconds without a new DTU Ok: the rest will not come


def _fleet(conn: Connection, port: int, n: int) -> None:
    """The child: one DtuFleet (one thread, one event loop) until told to stop."""
    logging.getLogger("edgemodbus").setLevel(logging.ERROR)
    fleet = DtuFleet("127.0.0.1", port, n, registration=ID + END, slaves=[SLAVE], size=TAGS,
                     dial_rate=DIAL_RATE, reconnect=1.0, reconnect_max=10.0,
                     connect_timeout=10.0)
    with fleet:
        conn.send("dialling")
        while True:
            try:
                command = conn.recv()
            except EOFError:
                return
            if command == "stop":
                return
            conn.send((fleet.stats(), time.process_time()))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(port: int, n: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dtu{n:05d}"},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
            "dtuId": ID.format(n=n), "registration": "text", "registrationTimeout": 10000,
            "slaveId": SLAVE, "readCycle": CYCLE_MS, "readTimeout": 1000,
            # the whole fleet dials from one address, and an unterminated registration
            # waits the quiet gap: up to dial rate x 0.5 s connections wait at once
            "maxUnregistered": N_DTUS, "maxUnregisteredPerSource": N_DTUS,
        },
        "addressList": [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in range(TAGS)],
    })


def _status() -> dict[str, int]:
    """VmRSS, VmSize (kB) and Threads of this process."""
    out: dict[str, int] = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmSize", "Threads"):
                out[key] = int(value.split()[0])
    return out


def _thread_stacks(stack_kb: int) -> tuple[int, int]:
    """(count, resident kB) of the mappings that are pthread stacks of ``stack_kb`` (less
    the guard page glibc takes from it)."""
    count = rss = 0
    size = 0
    with open("/proc/self/smaps") as f:
        for line in f:
            if re.match(r"^[0-9a-f]+-[0-9a-f]+ ", line):
                size = 0
            elif line.startswith("Size:"):
                size = int(line.split()[1])
            elif line.startswith("Rss:") and stack_kb - 8 <= size <= stack_kb:
                count += 1
                rss += int(line.split()[1])
    return count, rss


def _all_ok(cfg: em.DeviceConfig) -> bool:
    return all(it.status is ItemStatus.OK for it in cfg.address_list)


@pytest.mark.timeout(900)  # 5,000 drivers start in about 20 s; dialling, 3 cycles, stop
def test_5000_dtus_on_one_listen_port(benchmark: Any) -> None:
    n = N_DTUS
    window = 15.0 if not QUICK else 10.0  # 3 (2) read cycles
    logging.getLogger("edgemodbus").setLevel(logging.CRITICAL)  # a warning per DTU at start
    raise_open_files_limit(n + 256)
    old_stack = threading.stack_size(STACK_KB * 1024)
    port = _free_port()
    base = _status()
    configs = [_config(port, k) for k in range(n)]
    with_configs = _status()
    drivers = [em.DriverModbusRtu() for _ in configs]
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_fleet, args=(child, port, n), daemon=True)
    try:
        started = time.monotonic()
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        start_s = time.monotonic() - started
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        proc.start()
        assert parent.poll(120), "the DTU fleet did not start"
        assert parent.recv() == "dialling"
        dialled = time.monotonic()
        pending = set(range(n))
        last_progress = dialled
        deadline = dialled + (300 if not QUICK else 60)
        while pending and time.monotonic() < deadline:
            done = {k for k in pending if _all_ok(configs[k])}
            if done:
                pending -= done
                last_progress = time.monotonic()
            elif time.monotonic() - last_progress > STALL:
                break
            time.sleep(0.2)
        n_ok = n - len(pending)
        to_all_ok = last_progress - dialled
        listened = dict(listener.stats)

        def fleet_stats() -> tuple[dict[str, int], float]:
            parent.send("stats")
            stats: tuple[dict[str, int], float] = parent.recv()
            return stats

        def responses() -> int:
            return sum(d.stats()["responses"] for d in drivers)

        def measure() -> tuple[float, float, float]:
            """Our CPU seconds per second (all threads), the fleet's (its process), and
            connections accepted per second meanwhile (DTUs dialling again)."""
            cpu0, fleet0, reads0 = cpu_seconds(), fleet_stats()[1], responses()
            accepted0, t0 = listener.stats["accepted"], time.monotonic()
            time.sleep(window)
            wall = time.monotonic() - t0
            assert responses() > reads0
            return ((cpu_seconds() - cpu0) / wall, (fleet_stats()[1] - fleet0) / wall,
                    (listener.stats["accepted"] - accepted0) / wall)

        cpu, fleet_cpu, churn = benchmark.pedantic(measure, rounds=1, iterations=1)
        status = _status()
        stacks, stacks_kb = _thread_stacks(
            STACK_KB or resource.getrlimit(resource.RLIMIT_STACK)[0] // 1024)
        fstats = fleet_stats()[0]
        timeouts = sum(d.stats()["timeouts"] for d in drivers)
    finally:
        threading.stack_size(old_stack)
        for drv in drivers:
            drv.stop_device()
        if proc.is_alive():
            with contextlib.suppress(OSError):
                parent.send("stop")
            proc.join(30)
        parent.close()
        child.close()
    threads = threading.active_count()
    stack_kb = STACK_KB or resource.getrlimit(resource.RLIMIT_STACK)[0] // 1024
    rss_kb = status["VmRSS"] - base["VmRSS"]
    per_ok = 1e6 * cpu / max(1, n_ok)
    benchmark.extra_info.update({
        "dtus": n, "dtus_ok": n_ok, "seconds_to_all_ok": to_all_ok, "listener": listened,
        "cpu_us_per_dtu_s": per_ok, "rss_kb_per_dtu": rss_kb / n,
        "threads": status["Threads"], "stack_kb": stack_kb, "fleet": fstats})
    report(
        f"listen mode: {n} DTUs x 1 slave x {TAGS} tags on one port, readCycle {CYCLE_MS} ms "
        f"(fleet dials {DIAL_RATE:g}/s, registration {(ID + END)!r}; thread stacks {stack_kb} kB)",
        [
            ("start the drivers", start_s, "s"),
            ("DTUs with every value Ok", n_ok, f"of {n}"),
            ("first dial to the last DTU Ok", to_all_ok, "s"),
            ("listener: accepted", listened["accepted"], "connections"),
            ("listener: registered", listened["registered"], ""),
            ("listener: unknown or silent", listened["unknown"] + listened["silent"], ""),
            ("  accepted per second while measuring", churn, "/s"),
            ("fleet: connections made", fstats["connections"], ""),
            ("fleet: dials failed", fstats["dial_failures"], ""),
            ("timeouts while measuring", timeouts, ""),
            ("our CPU, all threads", 100 * cpu, "% of one core"),
            ("  per DTU Ok", per_ok, "us/s"),
            ("  per tag read", per_ok * CYCLE_MS / 1000 / TAGS, "us"),
            ("the fleet's CPU per DTU", 1e6 * fleet_cpu / n, "us/s (its own process)"),
            ("RSS, configs + drivers", rss_kb / 1024, "MB"),
            ("  per DTU", rss_kb / n, "kB"),
            ("  of it the device configs", (with_configs["VmRSS"] - base["VmRSS"]) / n, "kB"),
            ("virtual memory per DTU", (status["VmSize"] - base["VmSize"]) / n, "kB"),
            ("threads (one line worker per DTU)", status["Threads"], ""),
            ("thread stacks mapped", stacks, f"x {stack_kb} kB"),
            ("  resident per stack", stacks_kb / max(1, stacks), "kB"),
            ("threads left after stop", threads, ""),
        ],
    )
    assert n_ok == n, f"{n - n_ok} of {n} DTUs never had every value Ok"
    turned_away = listened["accepted"] - listened["registered"]
    assert turned_away == 0, f"{turned_away} connections accepted but not registered"
    assert fstats["connections"] == n and fstats["dial_failures"] == 0, (
        f"{fstats['connections'] - n} DTUs had to dial again; {fstats['dial_failures']} dials "
        "failed or timed out (a full listen backlog drops the DTUs' SYNs)")
