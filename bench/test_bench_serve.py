"""Issue 16, serve mode: 10 Modbus TCP masters reading 125 registers, from the gateway's
server (csrc/emb_serve.c, the register image of a polled device) and from a pymodbus
TCP server with the same map (125 holding registers of unit 1), in the same run.

The masters are one process of their own (bench/tcp_masters.py: 10 connections, one
request in flight each, as fast as replies come).  Each server is loaded for the same
window, alternately, several rounds; measured per window: replies per second, and the
server's CPU per reply (ours: this process, where the gateway's server and its driver
run; pymodbus: its process, from /proc).  The figures are the medians over the rounds.

Gated (bench/gate.py): pymodbus' CPU per reply over ours, and our replies per second
over pymodbus'.  The masters and both servers share the machine's two cores, so the
rates are bounded by the masters too; the CPU per reply is the cleaner figure.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from tests.peers import PymodbusSlave, default_register

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.serve import ModbusTcpServer

COUNT = 125
MASTERS = 10
TOP = Path(__file__).resolve().parents[1]
TICKS = os.sysconf("SC_CLK_TCK")


def process_cpu(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def load(port: int, seconds: float, cpu: Any) -> tuple[float, float]:
    """Run the masters against ``port`` for ``seconds``: (replies/s, CPU s per reply)
    with ``cpu()`` the server's CPU seconds so far."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "bench.tcp_masters", "127.0.0.1", str(port), "1",
         str(MASTERS), str(COUNT), str(seconds)],
        cwd=TOP, stdout=subprocess.PIPE, text=True)
    time.sleep(0.3)  # pacing: the masters' interpreter starting is not the server's time
    start = cpu()
    out, _ = proc.communicate(timeout=seconds + 30)
    used = cpu() - start
    result = json.loads(out)
    assert "error" not in result, result
    assert result["bad"] == 0 and result["first"] == default_register(1, "hr", 0), result
    replies = result["ok"]
    return replies / result["seconds"], used / replies


@pytest.fixture(scope="module")
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=COUNT) as peer:
        yield peer


@pytest.fixture(scope="module")
def pymodbus_server() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("tcp", units=(1,), size=COUNT) as peer:
        yield peer


@pytest.mark.timeout(600)
def test_serve_mode_against_pymodbus(slave: PymodbusSlave, pymodbus_server: PymodbusSlave,
                                     benchmark: Any) -> None:
    rounds, seconds = scale(5, 2), 1.0 if QUICK else 2.0
    cfg = em.load_device_config({
        "organization": {"deviceCode": "meter"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": slave.port, "slaveId": 1, "readCycle": 1000},
        "addressList": [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
                        for a in range(COUNT)],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    server = ModbusTcpServer("127.0.0.1", 0, max_connections=MASTERS + 2)
    try:
        server.serve_device(1, drv, cfg)
        server.start()
        deadline = time.monotonic() + 30
        while drv.device_driver_status is not DeviceDriverStatus.RUNNING:
            assert time.monotonic() < deadline, "the driver's first poll did not complete"
            time.sleep(0.01)  # poll: until Running (deadline above)
        pid = pymodbus_server.pid
        assert pid is not None
        ours_rate: list[float] = []
        ours_cpu: list[float] = []
        theirs_rate: list[float] = []
        theirs_cpu: list[float] = []
        load(server.port, 0.3, cpu_seconds)  # warm up
        for k in range(rounds):  # alternate which goes first
            for mine in ((True, False) if k % 2 else (False, True)):
                if mine:
                    rate, per = load(server.port, seconds, cpu_seconds)
                    ours_rate.append(rate)
                    ours_cpu.append(per)
                else:
                    rate, per = load(pymodbus_server.port, seconds,
                                     lambda: process_cpu(pid))
                    theirs_rate.append(rate)
                    theirs_cpu.append(per)
        rate, their_rate = statistics.median(ours_rate), statistics.median(theirs_rate)
        cpu, their_cpu = statistics.median(ours_cpu), statistics.median(theirs_cpu)
        benchmark.extra_info.update(rps=rate, pymodbus_rps=their_rate, cpu_us=cpu * 1e6,
                                    pymodbus_cpu_us=their_cpu * 1e6)
        report(
            f"serve mode: {MASTERS} TCP masters reading {COUNT} registers, "
            f"{rounds} rounds of {seconds:g} s each",
            [
                ("gateway server: replies/s, median", rate, "/s"),
                ("pymodbus TCP server: replies/s, median", their_rate, "/s"),
                ("gateway server: CPU per reply, median", cpu * 1e6, "us"),
                ("pymodbus TCP server: CPU per reply, median", their_cpu * 1e6, "us"),
                ("replies/s, gateway / pymodbus (gated)", rate / their_rate, "x"),
                ("CPU per reply, pymodbus / gateway (gated)", their_cpu / cpu, "x"),
            ],
        )
        gate.record("serve.rps_vs_pymodbus", rate / their_rate)
        gate.record("serve.pymodbus_cpu_vs_ours", their_cpu / cpu)
        benchmark.pedantic(lambda: None, rounds=1, iterations=1)
    finally:
        server.stop()
        drv.stop_device()
