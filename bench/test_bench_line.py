"""Client CPU per transaction: 125 holding registers over loopback RTU-over-TCP from a
pymodbus slave in its own process; our LineWorker against pymodbus' own sync client, measured
in the same run.  Target: ours at most one third of pymodbus' (the ratio worker /
pymodbus is gated: bench/gate.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from pymodbus import FramerType
from pymodbus.client import ModbusTcpClient
from tests.peers import PymodbusSlave, default_register

from bench import gate
from bench.conftest import cpu_per_call, report, scale
from edgemodbus.datatypes import Area
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.link import Link
from edgemodbus.line.worker import LineWorker

EXPECTED = [default_register(1, "hr", a) for a in range(125)]


@pytest.fixture(scope="module")
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=1000) as peer:
        yield peer


def test_cpu_per_transaction_vs_pymodbus(slave: PymodbusSlave, benchmark) -> None:
    calls = scale(2000, 200)
    line = LineWorker(TcpEndpoint("127.0.0.1", slave.port), LineTiming(response_timeout=2.0))
    line.start()
    client = ModbusTcpClient("127.0.0.1", port=slave.port, framer=FramerType.RTU, timeout=2)
    assert client.connect()
    try:
        assert line.read(1, Area.HOLDING_REGISTER, 0, 125).result(5) == EXPECTED
        assert client.read_holding_registers(0, count=125, device_id=1).registers == EXPECTED

        def worker_loop(link: Link) -> None:  # what the driver does: reads on the worker
            for _ in range(calls):
                link.read(1, Area.HOLDING_REGISTER, 0, 125)

        def ours_worker() -> None:
            line.submit(worker_loop).result(60)

        def ours_future() -> None:
            line.read(1, Area.HOLDING_REGISTER, 0, 125).result(5)

        def theirs() -> None:
            client.read_holding_registers(0, count=125, device_id=1)

        worker = cpu_per_call(ours_worker, 1) / calls
        future = cpu_per_call(ours_future, calls)
        pym = cpu_per_call(theirs, calls)
        benchmark.extra_info.update(
            ours_worker_us=worker * 1e6, ours_future_us=future * 1e6, pymodbus_us=pym * 1e6,
            ratio_worker=worker / pym, ratio_future=future / pym,
        )
        report(
            "client CPU per 125-register read, RTU over TCP (us)",
            [
                ("edgemodbus, on the line worker (driver path)", worker * 1e6, "us"),
                ("edgemodbus, Future from another thread", future * 1e6, "us"),
                ("pymodbus 3.16.1 sync client", pym * 1e6, "us"),
                ("ratio worker / pymodbus", worker / pym, "x"),
                ("ratio future / pymodbus", future / pym, "x"),
            ],
        )
        gate.record("line.worker_vs_pymodbus", worker / pym)
        benchmark.pedantic(ours_future, rounds=scale(200, 20), iterations=1)
    finally:
        client.close()
        line.stop()
