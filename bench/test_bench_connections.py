"""Parallel connections to one Modbus TCP endpoint (docs/links.md, ``connections``).

A pymodbus Modbus TCP slave in its own process plays a multi-port gateway: units 1..4,
each answering after 50 ms (its serial side).  Four devices, one per unit, poll as fast
as they may (readCycle 10 ms: every cycle overruns).  Over one connection the line
serializes them: a round of the four costs 4 x 50 ms; over four connections (one per
unit) the rounds overlap.  Measured: the time until every device made ``cycles`` more
cycles, 1 connection over 4 connections (target 4, the number of connections; gated at
2.5, bench/gate.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest
from tests.peers import PymodbusSlave

import edgemodbus as em
from bench import gate
from bench.conftest import report, scale

UNITS = (1, 2, 3, 4)
DELAY = 0.05


@pytest.fixture(scope="module")
def gateway() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("tcp", units=UNITS, size=100, response_delay=DELAY) as peer:
        yield peer


def config(port: int, unit: int, connections: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"unit{unit}"},
        "communication": {"transport": "tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
                          "slaveId": unit, "connections": connections, "readCycle": 10,
                          "readTimeout": 2000},
        "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}],
    })


def time_cycles(port: int, connections: int, cycles: int) -> float:
    """Seconds until every device made ``cycles`` cycles after its first."""
    with ExitStack() as stack:
        drivers = []
        for unit in UNITS:
            cfg = config(port, unit, connections)
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            stack.callback(drv.stop_device)
            drivers.append(drv)
        deadline = time.monotonic() + 60
        while not all(d.stats()["cycles"] >= 1 for d in drivers):
            assert time.monotonic() < deadline, "the first cycles did not complete"
            time.sleep(0.005)  # poll: until the first cycles (deadline above)
        start = time.monotonic()
        base = [d.stats()["cycles"] for d in drivers]
        while not all(d.stats()["cycles"] >= b + cycles for d, b in zip(drivers, base,
                                                                         strict=True)):
            assert time.monotonic() < deadline + 120, "the cycles did not complete"
            time.sleep(0.005)  # poll: until the cycles (deadline above)
        return time.monotonic() - start


@pytest.mark.timeout(600)
def test_four_connections_against_one(gateway: PymodbusSlave, benchmark: Any) -> None:
    cycles = scale(40, 10)
    one = time_cycles(gateway.port, 1, cycles)
    four = time_cycles(gateway.port, 4, cycles)
    ratio = one / four
    benchmark.extra_info.update(one_connection_s=one, four_connections_s=four, ratio=ratio)
    report(f"4 slaves behind one Modbus TCP endpoint answering in {DELAY * 1000:g} ms, "
           f"{cycles} cycles of each", [
               ("1 connection", one, "s"),
               ("4 connections", four, "s"),
               ("cycle rate, 4 connections / 1 (gated)", ratio, "x"),
           ])
    gate.record("connections.four_vs_one", ratio)
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
