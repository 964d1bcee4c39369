"""Connect mode at scale: N RTU-over-TCP endpoints polled from one process, the loop
engine (``engine: "loop"``: line/loop.py, line/loop_connect.py) against the thread
engine (a line worker thread per endpoint), in the same run.

Our simulator serves the N endpoints on 127.0.0.1, one port each, in a process of its
own (its CPU is not ours; one slave of 20 UInt16 tags each, one read of 20 registers per
cycle).  Each engine polls them from a fresh process of its own (spawned, so that
neither phase inherits the other's memory), which reports: the time from the first
start_device to every value Ok, its threads, RSS per endpoint (polling against the
same process before its drivers started), CPU per tag read (all its threads; the least
of two windows), wrong values (against the simulator's formula) and timeouts.  Each
engine runs twice, in turn, and the cheaper run of each is compared (the load of a
shared machine drifts).  The loop phase runs ``loopThreads`` 1 unless told otherwise
(one loop thread holds thousands of links; two measured about the same, docs/scale.md).
Gated (bench/gate.py): the loop's CPU per tag read over the thread engine's.

Quick mode: 100 endpoints, readCycle 250 ms, windows of 2 s.  Full: 2,000 endpoints,
readCycle 5 s (the simulator answers 400 reads a second then), windows of 10 s.
``EDGEMODBUS_BENCH_ENDPOINTS``, ``EDGEMODBUS_BENCH_CYCLE_MS``,
``EDGEMODBUS_BENCH_SECONDS`` and ``EDGEMODBUS_BENCH_LOOP_THREADS`` set them.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time
from multiprocessing.connection import Connection
from typing import Any

import pytest

import edgemodbus as em
from bench import gate
from bench.conftest import cpu_seconds, report, scale
from edgemodbus.datatypes import ItemStatus
from edgemodbus.sim import Simulator
from edgemodbus.sim.slave import default_register

N = int(os.environ.get("EDGEMODBUS_BENCH_ENDPOINTS", scale(2000, 100)))
CYCLE_MS = int(os.environ.get("EDGEMODBUS_BENCH_CYCLE_MS", scale(5000, 250)))
SECONDS = float(os.environ.get("EDGEMODBUS_BENCH_SECONDS", scale(10, 2)))
WINDOWS = 2  # per phase; the CPU per tag read is the least of an engine's windows
ROUNDS = 2  # phases per engine, in turn (loop, thread, loop, thread): a shared machine
LOOP_THREADS = int(os.environ.get("EDGEMODBUS_BENCH_LOOP_THREADS", 1))
TAGS = 20
SLAVE = 1
ADDRESS_LIST = [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                for a in range(TAGS)]


def _serve(conn: Connection, n: int) -> None:
    """The simulator's process: n ports, served until the parent says stop."""
    with Simulator([SLAVE], size=TAGS) as sim:
        conn.send([sim.serve_tcp("127.0.0.1", 0) for _ in range(n)])
        with contextlib.suppress(EOFError):
            conn.recv()


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _config(port: int, k: int, engine: str) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"ep{k:04d}"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": SLAVE, "readCycle": CYCLE_MS,
                          "readTimeout": 3000, "connectTimeout": 5000, "engine": engine,
                          "loopThreads": LOOP_THREADS},
        "addressList": ADDRESS_LIST,
    })


def _poll(conn: Connection, engine: str, ports: list[int]) -> None:
    """One engine's process: poll every port, measure, stop, send the figures."""
    configs = [_config(port, k, engine) for k, port in enumerate(ports)]
    rss0 = _rss()
    drivers = [em.DriverModbusRtu() for _ in configs]
    start = time.monotonic()
    try:
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        started = time.monotonic() - start
        deadline = start + 120 + len(ports) / 20
        while not all(it.status is ItemStatus.OK for c in configs for it in c.address_list):
            assert time.monotonic() < deadline, f"{engine}: not every value Ok in time"
            time.sleep(0.05)  # poll: until all Ok (deadline above)
        all_ok = time.monotonic() - start
        time.sleep(CYCLE_MS / 1000)  # pacing: the start-up reads, in step, are behind us
        threads = len(os.listdir("/proc/self/task"))
        rss = _rss()

        def tag_reads() -> int:
            return sum(d.stats()["responses"] for d in drivers) * TAGS

        costs, rates = [], []
        for _ in range(WINDOWS):
            reads0, cpu0 = tag_reads(), cpu_seconds()
            time.sleep(SECONDS)  # pacing: the window measured
            reads, cpu = tag_reads() - reads0, cpu_seconds() - cpu0
            assert reads > 0
            costs.append(1e6 * cpu / reads)
            rates.append(reads / SECONDS)
        want = [default_register(SLAVE, a) for a in range(TAGS)]
        wrong = sum(it.value != want[i] or it.status is not ItemStatus.OK
                    for c in configs for i, it in enumerate(c.address_list))
        figures = {"started_s": started, "all_ok_s": all_ok, "threads": threads,
                   "rss_kb_per_endpoint": (rss - rss0) / 1024 / len(ports),
                   "us_per_tag": min(costs), "tag_reads_per_s": min(rates),
                   "wrong": wrong, "timeouts": sum(d.stats()["timeouts"] for d in drivers)}
    finally:
        for drv in drivers:
            drv.stop_device()
    conn.send(figures)


def _phase(ctx: Any, engine: str, ports: list[int]) -> dict[str, float]:
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_poll, args=(child, engine, ports), daemon=True)
    proc.start()
    try:
        limit = 240 + len(ports) / 10 + SECONDS * WINDOWS
        assert parent.poll(limit), f"{engine}: the polling process sent nothing"
        figures: dict[str, float] = parent.recv()
    finally:
        proc.join(60)
        if proc.is_alive():
            proc.kill()
            proc.join()
        parent.close()
        child.close()
    return figures


@pytest.mark.timeout(1800)  # four phases; 2,000 endpoints take a few minutes
def test_connect_mode_at_scale_loop_vs_thread(benchmark: Any) -> None:
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    sim = ctx.Process(target=_serve, args=(child, N), daemon=True)
    sim.start()
    try:
        assert parent.poll(120), "the simulator did not start"
        ports: list[int] = parent.recv()
        runs: dict[str, list[dict[str, float]]] = {"loop": [], "thread": []}
        runs["loop"].append(benchmark.pedantic(lambda: _phase(ctx, "loop", ports),
                                               rounds=1, iterations=1))
        runs["thread"].append(_phase(ctx, "thread", ports))
        for _ in range(ROUNDS - 1):
            runs["loop"].append(_phase(ctx, "loop", ports))
            runs["thread"].append(_phase(ctx, "thread", ports))
    finally:
        parent.send("stop")
        sim.join(30)
        if sim.is_alive():
            sim.kill()
            sim.join()
        parent.close()
        child.close()
    loop, thread = (min(runs[e], key=lambda f: f["us_per_tag"]) for e in ("loop", "thread"))
    for engine in ("loop", "thread"):  # every round's count, not only the cheapest's
        best = loop if engine == "loop" else thread
        best["wrong"] = sum(f["wrong"] for f in runs[engine])
        best["all_ok_s"] = max(f["all_ok_s"] for f in runs[engine])
    ratio = loop["us_per_tag"] / thread["us_per_tag"]
    benchmark.extra_info.update({"endpoints": N, "cycle_ms": CYCLE_MS,
                                 "loop_threads": LOOP_THREADS, "loop": loop,
                                 "thread": thread, "loop_vs_thread_cpu": ratio})
    rows: list[tuple[str, float, str]] = []
    for key, unit in (("all_ok_s", "s"), ("threads", ""), ("rss_kb_per_endpoint", "kB"),
                      ("us_per_tag", "us/tag"), ("tag_reads_per_s", "/s"), ("wrong", ""),
                      ("timeouts", "")):
        rows += [(f"loop   {key}", loop[key], unit), (f"thread {key}", thread[key], unit)]
    rows.append(("CPU/tag read, loop / thread (gated)", ratio, "x"))
    report(f"Connect mode at scale: {N} RTU-over-TCP endpoints x 1 slave x {TAGS} tags, "
           f"readCycle {CYCLE_MS} ms, loopThreads {LOOP_THREADS}, least of {ROUNDS} x "
           f"{WINDOWS} windows of {SECONDS:g} s", rows)
    assert loop["wrong"] == 0 and thread["wrong"] == 0
    assert loop["threads"] < thread["threads"]
    gate.record("connect.loop_vs_thread_cpu", ratio)
