"""Starting thousands of DTU devices of one template: through the gateway service (a
folder of device files, one reload) and through the library (``start_device`` in a
loop, inside ``edgemodbus.bulk.starting_in_bulk`` and without it), on the loop engine;
then stopping them.

N listen-mode DTU devices (one template: 20 UInt16 tags, each its own dtuId, none
dialled in, ``engine: "loop"``) on one listen port, each run in a fresh process.
Reported: seconds (wall and CPU) to start all and per device, seconds to stop all, the
threads after the start.  The bare reference, measured in the same process just before:
reading and decoding the N files (``json.loads`` of each file's bytes), the least a
start of a folder does.  The gate (bench/gate.py ``bulk.gateway_start_vs_read``): the
gateway's CPU per device started over the reference's CPU per file (docs/scale.md,
"Starting thousands of devices").

Quick mode (``EDGEMODBUS_BENCH_QUICK=1``) uses 500 devices, else 5,000
(``EDGEMODBUS_BENCH_BULK`` any count).  ``EDGEMODBUS_BENCH_PROFILE=1`` prints a
cProfile table of the gateway's start (with ``-s``).
"""

from __future__ import annotations

import contextlib
import cProfile
import io
import json
import logging
import multiprocessing
import os
import pstats
import socket
import tempfile
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import pytest

from bench import gate
from bench.conftest import report, scale

N = int(os.environ.get("EDGEMODBUS_BENCH_BULK", "0")) or scale(5000, 500)
PROFILE = os.environ.get("EDGEMODBUS_BENCH_PROFILE") == "1"
LINES_PER_LOOP = 8000  # a loop thread serves at most 8,192 lines (line/loop.py)


def _device(k: int, port: int, n: int) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": f"dtu{k:05d}"},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "dtuId": f"DTU{k:05d}", "registration": "text",
            "engine": "loop", "loopThreads": max(2, -(-n // LINES_PER_LOOP)), "slaveId": 1,
            "readCycle": 5000, "maxUnregistered": n, "maxUnregisteredPerSource": n},
        "addressList": [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
                        for a in range(20)],
    }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _reference(files: list[Path]) -> tuple[float, float]:
    """(wall, CPU) seconds to read and decode every file: the bare reference."""
    began, cpu = time.perf_counter(), time.process_time()
    for path in files:
        json.loads(path.read_bytes())
    return time.perf_counter() - began, time.process_time() - cpu


def _run(conn: Connection, n: int, via: str, profile: bool) -> None:
    """The child: start ``n`` template devices ``via`` the gateway or the library,
    report, stop them."""
    import edgemodbus as em
    from edgemodbus.bulk import starting_in_bulk
    from edgemodbus.gateway import Gateway, load_gateway_config
    from edgemodbus.sim import raise_open_files_limit

    logging.getLogger("edgemodbus").setLevel(logging.CRITICAL)
    raise_open_files_limit(min(n, 4096) + 256)  # (no connection: no socket per DTU)
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        files = []
        for k in range(n):
            path = folder / f"dtu{k:05d}.json"
            path.write_text(json.dumps(_device(k, port, n)))
            files.append(path)
        gateway_file = folder / "gateway.json"
        gateway_file.write_text("{}")
        _reference(files)  # warm the page cache and the JSON decoder
        refs = [_reference(files) for _ in range(3)]
        ref_wall, ref_cpu = min(r[0] for r in refs), min(r[1] for r in refs)
        profiler = cProfile.Profile() if profile else None
        gateway: Gateway | None = None
        drivers: list[em.DriverModbusRtu] = []
        configs = ([em.load_device_config(path) for path in files] if via != "gateway"
                   else [])
        began, cpu = time.perf_counter(), time.process_time()
        if profiler is not None:
            profiler.enable()
        if via == "gateway":
            gateway = Gateway(folder, load_gateway_config(gateway_file), gateway_file)
            gateway.start()
            started_count = len(gateway.devices)
        else:
            with starting_in_bulk() if via == "library in bulk" else contextlib.nullcontext():
                for cfg in configs:
                    drv = em.DriverModbusRtu()
                    assert drv.start_device(cfg.organization, cfg.communication,
                                            cfg.address_list)
                    drivers.append(drv)
            started_count = len(drivers)
        if profiler is not None:
            profiler.disable()
        started, started_cpu = time.perf_counter() - began, time.process_time() - cpu
        threads = threading.active_count()
        began = time.perf_counter()
        if gateway is not None:
            gateway.stop()
        for drv in drivers:
            drv.stop_device()
        stopped = time.perf_counter() - began
    table = ""
    if profiler is not None:
        out = io.StringIO()
        pstats.Stats(profiler, stream=out).sort_stats("cumulative").print_stats(30)
        table = out.getvalue()
    conn.send((started_count, started, started_cpu, stopped, threads, ref_wall, ref_cpu,
               table))


def _measure(n: int, via: str) -> tuple[Any, ...]:
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_run, args=(child, n, via, PROFILE and via == "gateway"))
    proc.start()
    try:
        if not parent.poll(900):
            raise AssertionError("the devices' process did not report within 900 s")
        result: tuple[Any, ...] = parent.recv()
    finally:
        proc.join(60)
        if proc.is_alive():
            proc.kill()
            proc.join()
    assert proc.exitcode == 0, proc.exitcode
    return result


@pytest.mark.timeout(2000)
def test_bulk_start_of_template_devices(benchmark: Any) -> None:
    rows: list[tuple[str, float, str]] = []
    figures: dict[str, tuple[Any, ...]] = {}
    for via in ("gateway", "library in bulk", "library"):
        count, wall, cpu, stopped, threads, ref_wall, ref_cpu, table = \
            figures[via] = _measure(N, via)
        assert count == N, f"{via}: {count} of {N} devices started"
        if table:
            print(f"\n--- profile of the gateway's start ---\n{table}")
        rows += [
            (f"{via}: start all", wall, "s"),
            (f"{via}: start all, CPU", cpu, "s"),
            (f"{via}: per device", 1000 * wall / N, "ms"),
            (f"{via}: per device, CPU", 1000 * cpu / N, "ms"),
            (f"{via}: stop all", stopped, "s"),
            (f"{via}: threads after the start", threads, ""),
            (f"{via}: reference, read+decode per file", 1e6 * ref_wall / N, "us"),
            (f"{via}: reference, read+decode per file, CPU", 1e6 * ref_cpu / N, "us"),
            (f"{via}: CPU per device / reference", cpu / max(ref_cpu, 1e-9), "x"),
        ]
    report(f"{N} template DTU devices (loop engine): start and stop", rows)
    _, _, cpu, _, _, _, ref_cpu, _ = figures["gateway"]
    gate.record("bulk.gateway_start_vs_read", cpu / max(ref_cpu, 1e-9))
    benchmark.extra_info.update(
        gateway_start_s=figures["gateway"][1], gateway_start_cpu_s=cpu,
        library_start_s=figures["library"][1], gateway_stop_s=figures["gateway"][3],
        library_in_bulk_start_s=figures["library in bulk"][1])
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
