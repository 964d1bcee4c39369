"""Starting thousands of drivers of one template: time and memory per driver.

N listen-mode DTU drivers (one template: 20 UInt16 tags, each DTU its own dtuId, none
dialled in) start on one listen port, then stop.  Measured twice, each in a fresh
process (so that RSS is the drivers' own): with the read plans and compiled blocks
shared between devices (poll/plan_cache.py, codec/shared.py) and with that sharing off
(every device plans and compiles its own, as before issue 27).  Reported: seconds to
start all, ms per driver, RSS kB per driver, seconds to stop all, and the ratio shared /
own of the start time and of the memory (docs/scale.md, "Starting thousands of devices").

Quick mode (``EDGEMODBUS_BENCH_QUICK=1``) uses 500 drivers, else 5,000
(``EDGEMODBUS_BENCH_BULK`` any count).  Where the rest of a start goes (the line worker
thread each DTU has, the item validation) is profiled with ``-s``'s cProfile table when
``EDGEMODBUS_BENCH_PROFILE=1``.
"""

from __future__ import annotations

import cProfile
import io
import logging
import multiprocessing
import os
import pstats
import socket
import time
from multiprocessing.connection import Connection
from typing import Any

import pytest

from bench.conftest import report, scale

N = int(os.environ.get("EDGEMODBUS_BENCH_BULK", "0")) or scale(5000, 500)
PROFILE = os.environ.get("EDGEMODBUS_BENCH_PROFILE") == "1"


class _Unshared:
    """A stand-in for a SharedCache that shares nothing: every get makes a new value."""

    def get(self, key: object, make: Any) -> Any:
        return make()


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise AssertionError("no VmRSS in /proc/self/status")


def _run(conn: Connection, n: int, shared: bool, profile: bool) -> None:
    """The child: start ``n`` template drivers, report, stop them."""
    import edgemodbus as em
    from edgemodbus.codec import decoder
    from edgemodbus.poll import plan_cache
    from edgemodbus.sim import raise_open_files_limit

    logging.getLogger("edgemodbus").setLevel(logging.CRITICAL)
    raise_open_files_limit(n + 256)
    if not shared:
        decoder._SHAPES = _Unshared()  # type: ignore[assignment]
        plan_cache.PLANS = _Unshared()  # type: ignore[assignment]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    configs = [em.load_device_config({
        "organization": {"deviceCode": f"dtu{k:05d}"},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "dtuId": f"DTU{k:05d}", "registration": "text",
            "slaveId": 1, "readCycle": 5000, "maxUnregistered": n,
            "maxUnregisteredPerSource": n},
        "addressList": [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in range(20)],
    }) for k in range(n)]
    drivers = [em.DriverModbusRtu() for _ in configs]
    before = _rss_kb()
    profiler = cProfile.Profile() if profile else None
    began = time.perf_counter()
    if profiler is not None:
        profiler.enable()
    for drv, cfg in zip(drivers, configs, strict=True):
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    if profiler is not None:
        profiler.disable()
    started = time.perf_counter() - began
    rss = _rss_kb() - before
    began = time.perf_counter()
    for drv in drivers:
        drv.stop_device()
    stopped = time.perf_counter() - began
    table = ""
    if profiler is not None:
        out = io.StringIO()
        pstats.Stats(profiler, stream=out).sort_stats("cumulative").print_stats(25)
        table = out.getvalue()
    conn.send((started, rss, stopped, table))


def _measure(n: int, shared: bool) -> tuple[float, int, float, str]:
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_run, args=(child, n, shared, PROFILE))
    proc.start()
    try:
        if not parent.poll(600):
            raise AssertionError("the drivers' process did not report within 600 s")
        result: tuple[float, int, float, str] = parent.recv()
    finally:
        proc.join(60)
        if proc.is_alive():
            proc.kill()
            proc.join()
    assert proc.exitcode == 0, proc.exitcode
    return result


@pytest.mark.timeout(1300)
def test_bulk_start_of_template_drivers(benchmark: Any) -> None:
    own = _measure(N, shared=False)
    shared = _measure(N, shared=True)
    for label, (_, _, _, table) in (("own", own), ("shared", shared)):
        if table:
            print(f"\n--- profile of the start, {label} plans ---\n{table}")
    report(f"{N} template DTU drivers: start and stop", [
        ("own plans: start all", own[0], "s"),
        ("own plans: per driver", 1000 * own[0] / N, "ms"),
        ("own plans: RSS per driver", own[1] / N, "kB"),
        ("own plans: stop all", own[2], "s"),
        ("shared plans: start all", shared[0], "s"),
        ("shared plans: per driver", 1000 * shared[0] / N, "ms"),
        ("shared plans: RSS per driver", shared[1] / N, "kB"),
        ("shared plans: stop all", shared[2], "s"),
        ("start time shared / own", shared[0] / own[0], "x"),
        ("RSS shared / own", shared[1] / max(own[1], 1), "x"),
    ])
    benchmark.extra_info.update(own_start_s=own[0], shared_start_s=shared[0],
                                own_rss_kb=own[1], shared_rss_kb=shared[1])
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
