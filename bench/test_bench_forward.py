"""Issue 16, forward mode: the latency a forwarded request adds over a direct read.

A pymodbus slave in its own process serves RTU over TCP; one idle line (no poller) reads
the same 125 holding registers two ways, alternately: ``LineWorker.read`` (the direct
read the driver's own requests make) and ``LineWorker.forward`` of the PDU ``03 0000
007D`` (what the gateway's TCP server hands over).  Each is timed from the call to the
future's result on this thread, in pairs; the added latency is the median of the
paired differences, in transaction times (the median direct read).  A driver's
``forward`` on its own idle line (the public path: the device's slave and timeout
added) is timed too and reported beside it.

Target: forward mode adds at most one transaction time over a direct read on
an idle line; gated at that (measured: a few hundredths, see bench/gate.py).
"""

from __future__ import annotations

import statistics
import struct
import time
from collections.abc import Iterator
from typing import Any

import pytest
from tests.peers import PymodbusSlave, default_register

import edgemodbus as em
from bench import gate
from bench.conftest import report, scale
from edgemodbus.datatypes import Area, DeviceDriverStatus
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.worker import LineWorker

COUNT = 125
PDU = struct.pack(">BHH", 3, 0, COUNT)
EXPECTED = [default_register(1, "hr", a) for a in range(COUNT)]
REPLY = struct.pack(f">BB{COUNT}H", 3, 2 * COUNT, *EXPECTED)


@pytest.fixture(scope="module")
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=1000) as peer:
        yield peer


def timed(call: Any) -> float:
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


@pytest.mark.timeout(300)
def test_forward_latency_over_a_direct_read(slave: PymodbusSlave, benchmark: Any) -> None:
    pairs = scale(600, 80)
    line = LineWorker(TcpEndpoint("127.0.0.1", slave.port), LineTiming(response_timeout=2.0))
    line.start()
    cfg = em.load_device_config({
        "organization": {"deviceCode": "gw"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": slave.port, "slaveId": 1, "readTimeout": 2000,
                          "readCycle": 3_600_000},  # one poll, then idle
        "addressList": [{"name": "r", "address": "hr:0", "deviceDataType": "UInt16"}],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        deadline = time.monotonic() + 30
        while drv.device_driver_status is not DeviceDriverStatus.RUNNING:
            assert time.monotonic() < deadline, "the driver's first poll did not complete"
            time.sleep(0.01)  # poll: until Running (deadline above)

        def direct() -> None:
            assert line.read(1, Area.HOLDING_REGISTER, 0, COUNT).result(5) == EXPECTED

        def forwarded() -> None:
            assert line.forward(1, PDU).result(5) == REPLY

        def driver_forward() -> None:
            assert drv.forward(PDU).result(5) == REPLY

        for call in (direct, forwarded, driver_forward):  # warm up
            for _ in range(10):
                call()
        reads: list[float] = []
        forwards: list[float] = []
        via_driver: list[float] = []
        for k in range(pairs):  # alternate the order: neither always goes first
            order = (direct, forwarded, driver_forward) if k % 2 else (
                driver_forward, forwarded, direct)
            times = {call: timed(call) for call in order}
            reads.append(times[direct])
            forwards.append(times[forwarded])
            via_driver.append(times[driver_forward])
        transaction = statistics.median(reads)
        added = statistics.median(f - r for f, r in zip(forwards, reads, strict=True))
        added_driver = statistics.median(f - r for f, r in zip(via_driver, reads, strict=True))
        ratio = added / transaction
        benchmark.extra_info.update(
            transaction_us=transaction * 1e6, forward_us=statistics.median(forwards) * 1e6,
            driver_forward_us=statistics.median(via_driver) * 1e6,
            added_transactions=ratio, driver_added_transactions=added_driver / transaction,
        )
        report(
            f"forward vs direct read of {COUNT} registers on an idle line, RTU over TCP, "
            f"pymodbus slave, {pairs} paired rounds",
            [
                ("direct LineWorker.read (one transaction), median", transaction * 1e6, "us"),
                ("LineWorker.forward, median", statistics.median(forwards) * 1e6, "us"),
                ("DriverModbusRtu.forward (own idle line), median",
                 statistics.median(via_driver) * 1e6, "us"),
                ("added by forward (median of pairs, gated)", ratio, "txn"),
                ("added by the driver's forward", added_driver / transaction, "txn"),
            ],
        )
        gate.record("forward.added_transactions", ratio)
        benchmark.pedantic(forwarded, rounds=scale(200, 20), iterations=1)
    finally:
        drv.stop_device()
        line.stop()
