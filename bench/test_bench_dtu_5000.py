"""Listen mode at scale: 5,000 DTUs dialled in to one listen port of one process, on
both DTU engines in the same run (docs/scale.md "Many links on few threads").

5,000 DTUs, each with 1 slave of 20 UInt16 tags read every 5 s, dial in to one port of
the gateway process (one driver per DTU), once with ``engine: "thread"`` (a line worker
thread per DTU) and once with ``engine: "loop"`` (the default: a few loop threads).
Each engine runs in a fresh process of its own (``python -c``), so that neither inherits
the other's threads, allocations or caches; the DTUs are a
:class:`~edgemodbus.sim.FleetProcesses` (asyncio fleets in processes of their own,
dialling from two or more loopback source addresses), so their CPU is not ours.

Measured per engine: the time to start the drivers, from the first dial to every value
Ok, the wrong values (each DTU's slave holds its number in register 0: a value read
through another DTU's link is wrong), the threads, RSS per DTU (configs and drivers), CPU
per DTU per second; then the redial phase: every connection reset at once (RST), the
DTUs dial again after about 1 s, and the time until every device read its values
again through a new link, with the listener's refusals.  Issue 27's targets are for the
loop engine (bench/gate.py: threads, RSS, CPU, time to Ok, time to Ok after the redial,
and the loop against the thread engine).

Quick mode (``EDGEMODBUS_BENCH_QUICK=1``, in ``make bench-quick``) uses 300 DTUs.
Environment knobs: ``EDGEMODBUS_BENCH_DTUS`` any count (20000, 50000: past the gateway's
hard open-files limit the run says so and stops); ``EDGEMODBUS_BENCH_ENGINES`` which
engines (``loop``, ``thread``, or both: ``thread,loop``, the default);
``EDGEMODBUS_BENCH_CYCLE_MS`` the readCycle (5000); ``EDGEMODBUS_BENCH_DIAL_RATE`` the
fleet's dials per second (1000); ``EDGEMODBUS_BENCH_FLEET_PROCS`` the fleet's processes
(one per 2,500 DTUs); ``EDGEMODBUS_BENCH_STACK_KB`` the stack size of the threads the
gateway process starts (default RLIMIT_STACK, 8 MB).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from typing import Any

import pytest
from tests.integration.test_dtu_redial import REFUSALS
from tests.peers import free_port

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from edgemodbus.datatypes import ItemStatus
from edgemodbus.line import dtu_registry
from edgemodbus.sim import FleetProcesses, default_register, loopback_sources
from edgemodbus.sim import raise_open_files_limit as raise_limit

TAGS = 20
SLAVE = 1
CYCLE_MS = int(os.environ.get("EDGEMODBUS_BENCH_CYCLE_MS", "5000"))
ID = "DTU{n:05d}\r\n"
N_DTUS = int(os.environ.get("EDGEMODBUS_BENCH_DTUS", "0")) or scale(5000, 300)
ENGINES = tuple(os.environ.get("EDGEMODBUS_BENCH_ENGINES", "thread,loop").split(","))
DIAL_RATE = float(os.environ.get("EDGEMODBUS_BENCH_DIAL_RATE", "1000"))
FLEET_PROCS = int(os.environ.get("EDGEMODBUS_BENCH_FLEET_PROCS", "0")) or -(-N_DTUS // 2500)
STACK_KB = int(os.environ.get("EDGEMODBUS_BENCH_STACK_KB", "0"))
OK_DEADLINE = 300.0 if not QUICK else 60.0  # seconds from the first dial
STALL = 30.0  # seconds without a new DTU Ok: the rest will not come
WINDOW = 15.0 if not QUICK else 10.0  # 3 (2) read cycles of CPU measured
_CHILD = "from bench.test_bench_dtu_5000 import child; child()"


def _config(port: int, n: int, engine: str) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"dtu{n:05d}"},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
            "dtuId": ID.format(n=n).strip(), "registration": "text",
            "registrationTimeout": 10000, "slaveId": SLAVE, "readCycle": CYCLE_MS,
            "readTimeout": 1000, "engine": engine,
            # the whole fleet dials from a few addresses, and redials at once: the caps on
            # connections waiting to register (made for the internet) sized for the fleet
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


def _want(n: int) -> list[int]:
    return [n & 0xFFFF] + [default_register(SLAVE, a) for a in range(1, TAGS)]


def _ok(cfg: em.DeviceConfig) -> bool:
    return all(it.status is ItemStatus.OK for it in cfg.address_list)


def _wait_all(done: Any, n: int, deadline_s: float) -> tuple[int, float]:
    """(how many of ``range(n)`` became ``done(k)``, seconds to the last of them),
    polling every 0.2 s until all, the deadline, or STALL seconds without progress."""
    pending = set(range(n))
    started = last = time.monotonic()
    while pending and time.monotonic() < started + deadline_s:
        finished = {k for k in pending if done(k)}
        if finished:
            pending -= finished
            last = time.monotonic()
        elif time.monotonic() - last > STALL:
            break
        time.sleep(0.2)  # poll: until all finished or stalled
    return n - len(pending), last - started


def _measure(engine: str, port: int) -> dict[str, Any]:
    """One engine in this process: the figures (see the module)."""
    n = N_DTUS
    raise_limit(n + 256)  # OSError naming the hard limit when it is too low
    threading.stack_size(STACK_KB * 1024)
    base = _status()
    configs = [_config(port, k, engine) for k in range(n)]
    after_configs = _status()
    drivers = [em.DriverModbusRtu() for _ in configs]
    sources = loopback_sources(n)
    sources = sources if len(sources) > 1 else ("127.0.0.1", "127.0.0.2")
    fleet = FleetProcesses("127.0.0.1", port, n, processes=FLEET_PROCS, registration=ID,
                           slaves=[SLAVE], size=TAGS, mark=0, dial_rate=DIAL_RATE,
                           reconnect=1.0, reconnect_max=10.0, connect_timeout=10.0,
                           sources=sources)
    out: dict[str, Any] = {"engine": engine, "dtus": n, "fleet_processes": FLEET_PROCS,
                           "sources": len(sources)}
    try:
        started = time.monotonic()
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        out["start_s"] = time.monotonic() - started
        # RSS per DTU in three parts (docs/scale.md "Memory per DTU"): the validated
        # configs, the started drivers (none dialled in yet), and the rest measured with
        # the CPU below (the links, values read, what the fleet's traffic left behind)
        after_start = _status()
        out["rss_kb_per_dtu_configs"] = (after_configs["VmRSS"] - base["VmRSS"]) / n
        out["rss_kb_per_dtu_started"] = (after_start["VmRSS"] - after_configs["VmRSS"]) / n
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        fleet.start()
        out["dtus_ok"], out["to_all_ok_s"] = _wait_all(lambda k: _ok(configs[k]), n,
                                                       OK_DEADLINE)
        responses0 = sum(d.stats()["responses"] for d in drivers)
        cpu0, fleet0, t0 = cpu_seconds(), fleet.cpu_seconds(), time.monotonic()
        time.sleep(WINDOW)  # pacing: the window measured
        wall = time.monotonic() - t0
        out["cpu_us_per_dtu_s"] = 1e6 * (cpu_seconds() - cpu0) / wall / max(1, out["dtus_ok"])
        out["fleet_cpu_us_per_dtu_s"] = 1e6 * (fleet.cpu_seconds() - fleet0) / wall / n
        out["reads_in_window"] = sum(d.stats()["responses"] for d in drivers) - responses0
        status = _status()
        out["threads"] = status["Threads"]
        out["rss_kb_per_dtu"] = (status["VmRSS"] - base["VmRSS"]) / n
        out["rss_kb_per_dtu_dialled"] = (status["VmRSS"] - after_start["VmRSS"]) / n
        out["vm_kb_per_dtu"] = (status["VmSize"] - base["VmSize"]) / n
        out["wrong"] = sum(1 for k, cfg in enumerate(configs)
                           if _ok(cfg) and [it.value for it in cfg.address_list] != _want(k))
        out["listener"] = dict(listener.stats)
        out["fleet"] = fleet.stats()
        # the redial: every connection reset at once; each device Ok again through a
        # link made after it (a reconnect, then a reply more than at that moment)
        fleet.reset_all()
        reset_at = time.monotonic()
        relinked: dict[int, int] = {}

        def again(k: int) -> bool:
            stats = drivers[k].stats()
            if k not in relinked:
                if stats["line"]["reconnects"] < 1:
                    return False
                relinked[k] = int(stats["responses"])
                return False
            return int(stats["responses"]) > relinked[k] and _ok(configs[k])

        out["dtus_ok_again"], _ = _wait_all(again, n, OK_DEADLINE)
        out["to_all_ok_again_s"] = time.monotonic() - reset_at if \
            out["dtus_ok_again"] == n else float("inf")
        out["wrong_after_redial"] = sum(
            1 for k, cfg in enumerate(configs)
            if _ok(cfg) and [it.value for it in cfg.address_list] != _want(k))
        out["listener_after_redial"] = dict(listener.stats)
        out["fleet_after_redial"] = fleet.stats()
    finally:
        for drv in drivers:
            drv.stop_device()
        fleet.stop()
    out["threads_after_stop"] = threading.active_count()
    return out


def child() -> None:
    """A run of one engine (``python -c`` of :data:`_CHILD`): the engine and the port on
    stdin, the figures as the last line of stdout (JSON; ``{"error": ...}`` when the
    process cannot hold the fleet)."""
    logging.getLogger("edgemodbus").setLevel(logging.CRITICAL)  # a warning per DTU at start
    engine, port = sys.stdin.readline().split()
    try:
        figures = _measure(engine, int(port))
    except OSError as exc:
        figures = {"error": str(exc)}
    print(json.dumps(figures), flush=True)


def _run(engine: str) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, "-c", _CHILD], input=f"{engine} {free_port()}\n",
                          capture_output=True, text=True, timeout=1800, check=False)
    lines = proc.stdout.strip().splitlines()
    assert proc.returncode == 0 and lines, f"{engine}: exit {proc.returncode}\n{proc.stderr}"
    figures: dict[str, Any] = json.loads(lines[-1])
    return figures


def _rows(f: dict[str, Any]) -> list[tuple[str, float, str]]:
    e, li, again = f["engine"], f["listener"], f["listener_after_redial"]
    refused = sum(again[k] for k in REFUSALS)
    return [
        (f"{e}: start the drivers", f["start_s"], "s"),
        (f"{e}: DTUs with every value Ok", f["dtus_ok"], f"of {f['dtus']}"),
        (f"{e}: first dial to the last DTU Ok", f["to_all_ok_s"], "s"),
        (f"{e}: wrong values (devices)", f["wrong"], ""),
        (f"{e}: listener accepted / registered", li["accepted"], f"/ {li['registered']}"),
        (f"{e}: our CPU per DTU", f["cpu_us_per_dtu_s"], "us/s"),
        (f"{e}:   per tag read", f["cpu_us_per_dtu_s"] * CYCLE_MS / 1000 / TAGS, "us"),
        (f"{e}: the fleet's CPU per DTU", f["fleet_cpu_us_per_dtu_s"], "us/s (its processes)"),
        (f"{e}: reads while measuring", f["reads_in_window"], f"in {WINDOW:g} s"),
        (f"{e}: RSS per DTU", f["rss_kb_per_dtu"], "kB (configs + drivers)"),
        (f"{e}:   the configs", f["rss_kb_per_dtu_configs"], "kB"),
        (f"{e}:   the drivers started", f["rss_kb_per_dtu_started"], "kB (none dialled in)"),
        (f"{e}:   dialled in and polled", f["rss_kb_per_dtu_dialled"], "kB (links, values)"),
        (f"{e}: virtual memory per DTU", f["vm_kb_per_dtu"], "kB"),
        (f"{e}: threads", f["threads"], ""),
        (f"{e}: redial: DTUs Ok again", f["dtus_ok_again"], f"of {f['dtus']}"),
        (f"{e}: redial: reset to the last DTU Ok", f["to_all_ok_again_s"], "s"),
        (f"{e}: redial: wrong values", f["wrong_after_redial"], ""),
        (f"{e}: redial: refused by the listener", refused, "connections"),
        (f"{e}: redial: dials failed or timed out", f["fleet_after_redial"]["dial_failures"]
         - f["fleet"]["dial_failures"], "(SYNs dropped by a full listen backlog)"),
        (f"{e}: redial: accepted / registered", again["accepted"], f"/ {again['registered']}"),
        (f"{e}: threads left after stop", f["threads_after_stop"], ""),
    ]


@pytest.mark.timeout(3600)
def test_5000_dtus_on_one_listen_port_on_both_engines(benchmark: Any) -> None:
    results: dict[str, dict[str, Any]] = {}

    def measure() -> None:
        for engine in ENGINES:
            results[engine] = _run(engine)

    benchmark.pedantic(measure, rounds=1, iterations=1)
    errors = {e: f["error"] for e, f in results.items() if "error" in f}
    if errors:
        pytest.skip(f"{N_DTUS} DTUs in one process: " + "; ".join(
            f"{e}: {why}" for e, why in errors.items()))
    rows = [row for engine in ENGINES for row in _rows(results[engine])]
    benchmark.extra_info.update(results)
    report(f"listen mode: {N_DTUS} DTUs x 1 slave x {TAGS} tags on one port, readCycle "
           f"{CYCLE_MS} ms, fleet in {FLEET_PROCS} process(es) dialling {DIAL_RATE:g}/s",
           rows)
    loop = results.get("loop")
    if loop is not None:
        gate.record("dtu_fleet.loop_threads", loop["threads"])
        gate.record("dtu_fleet.loop_rss_kb_per_dtu", loop["rss_kb_per_dtu"])
        gate.record("dtu_fleet.loop_cpu_us_per_dtu_s", loop["cpu_us_per_dtu_s"])
        gate.record("dtu_fleet.loop_to_all_ok_s", loop["to_all_ok_s"])
        gate.record("dtu_fleet.loop_redial_to_all_ok_s", loop["to_all_ok_again_s"])
        thread = results.get("thread")
        if thread is not None:
            gate.record("dtu_fleet.loop_vs_thread_cpu",
                        loop["cpu_us_per_dtu_s"] / thread["cpu_us_per_dtu_s"])
    for engine, f in results.items():
        n = f["dtus"]
        assert f["dtus_ok"] == n, f"{engine}: {n - f['dtus_ok']} of {n} DTUs never Ok"
        assert f["wrong"] == f["wrong_after_redial"] == 0, engine
        li, again = f["listener"], f["listener_after_redial"]
        assert li["accepted"] == li["registered"] == n, (engine, li)
        assert f["dtus_ok_again"] == n, f"{engine}: {n - f['dtus_ok_again']} not Ok again"
        assert f["fleet"]["dial_failures"] == 0, (engine, f["fleet"])
    if loop is not None:
        # The redial on the loop engine (issue 27's target): every connection the
        # listener accepted registered, none refused.  Dials that time out are reported,
        # not failed: with every DTU dialling within a second, SYNs beyond the listen
        # backlog (SOMAXCONN) are dropped by the kernel and sent again by the DTU (0 at
        # 5,000; 10,011 of 19,000 on a saturated machine, docs/scale.md), before the
        # listener sees them.  The thread engine, the baseline, is reported only: on a
        # saturated machine its 5,000 threads took 120 s to take the redial, and 14
        # connections whose DTU had given up (its connect timed out while the
        # connection waited in the backlog) were accepted later and closed as silent.
        again = loop["listener_after_redial"]
        assert again["accepted"] == again["registered"], again
        assert sum(again[k] for k in REFUSALS) == 0, again
