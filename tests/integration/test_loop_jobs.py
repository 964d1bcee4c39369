"""A job on a loop line never blocks its loop thread (issue #25 "a bad device never
stalls the good ones", on the loop engine: line/loop_jobs.py).

Several DTUs dial in to one listen port and are served by ONE loop thread
(``loopThreads`` 1); each DTU is a relay (tests/integration/test_dtu.py SegmentedDtu)
in front of a pymodbus slave in its own process.  Writes and forwards (the gateway's
Modbus TCP server, raw-socket masters) flood one DTU: to slaves that never answer, or to
a live but slow one; the bystander DTUs on the same thread keep at least half the
polling rate they had before the flood (counted over windows, against the quiet rate
measured in the same test: a loaded machine slows both alike)."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.line.loop_pool import pool
from edgemodbus.serve import ModbusTcpServer
from tests.closed_loops import ClosedLoops
from tests.conftest import SlaveFactory
from tests.integration.test_dtu import SegmentedDtu, free_port
from tests.integration.test_line_fairness import Flood
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

WINDOW = 3.0  # seconds a rate is counted over
BYSTANDERS = 3
DEAD_SLAVES = (7, 8, 9, 10)  # slave ids nobody answers (pymodbus serves unit 1 only)


def dtu_config(port: int, dtu_id: str, slave: int, **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": port,
        "dtuId": dtu_id, "registration": "text", "registrationTimeout": 2000,
        "slaveId": slave, "readTimeout": 500, "readCycle": 100, "reconnectInterval": 300,
        "byteTimeout": 50, "retries": 0, "offlineAfterFailedCycles": 1000,
        "engine": "loop", "loopThreads": 1,
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": f"{dtu_id}-{slave}"},
        "communication": comm,
        "addressList": [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
                        for a in range(4)],
    })


class Site:
    """The bystander DTUs (slave 1 each, polled every 100 ms) and one flooded DTU with
    the devices ``flooded`` gives (slave id and extra settings), all on one port and
    one loop thread; a Modbus TCP server in front, each flooded device's slave id its
    forward unit."""

    def __init__(self, stack: ExitStack, fast: PymodbusSlave, flooded_peer: PymodbusSlave,
                 flooded: list[tuple[int, dict[str, Any]]]) -> None:
        port = free_port()
        self.drivers: list[em.DriverModbusRtu] = []
        stack.callback(self._stop_drivers)
        self.bystanders = [self._start(dtu_config(port, f"BY{k}", 1))
                           for k in range(BYSTANDERS)]
        self.flooded = [self._start(dtu_config(port, "FLOOD", slave, **extra))
                        for slave, extra in flooded]
        self.server = ModbusTcpServer("127.0.0.1", 0, max_connections=16, idle_timeout=0)
        stack.callback(self.server.stop)
        for (slave, _extra), drv in zip(flooded, self.flooded, strict=True):
            self.server.forward_device(slave, drv, timeout=2.0)
        self.server.start()
        for k in range(BYSTANDERS):
            stack.callback(SegmentedDtu(port, [f"BY{k}".encode()], fast.port).close)
        stack.callback(SegmentedDtu(port, [b"FLOOD"], flooded_peer.port).close)
        for drv in self.bystanders:
            wait_for(lambda d=drv: d.device_driver_status is em.DeviceDriverStatus.RUNNING,
                     30, "the bystanders polled")
        wait_for(lambda: all(d.stats()["requests"] >= 1 for d in self.flooded), 30,
                 "the flooded DTU polled")
        assert pool.workers == 1  # every line on one loop thread

    def _start(self, cfg: em.DeviceConfig) -> em.DriverModbusRtu:
        drv = em.DriverModbusRtu()
        self.drivers.append(drv)
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        return drv

    def _stop_drivers(self) -> None:
        for drv in reversed(self.drivers):
            drv.stop_device()

    def cycles(self) -> list[int]:
        return [d.stats()["cycles"] for d in self.bystanders]

    def rate(self, seconds: float = WINDOW) -> float:
        """The slowest bystander's cycles per second over a window of ``seconds``."""
        before, start = self.cycles(), time.monotonic()
        time.sleep(seconds)  # pacing: a measuring window, not a wait for an event
        elapsed = time.monotonic() - start
        return min(b - a for a, b in zip(before, self.cycles(), strict=True)) / elapsed


class Writes(ClosedLoops):
    """One thread per driver writing register 1 in a closed loop (the next write as
    soon as the last one ended); outcomes counted."""

    def __init__(self, drivers: list[em.DriverModbusRtu]) -> None:
        self.done = 0
        self.failed = 0
        super().__init__([(drv,) for drv in drivers], "test-writer")

    def _run(self, drv: em.DriverModbusRtu) -> None:
        value = 0
        while not self._stop.is_set():
            value = (value + 1) & 0xFFFF
            try:
                ok = drv.submit_writes([("r1", value)]).result(30)[0]
            except em.ModbusError:  # a timeout, or refused by the target backoff
                ok = False
            with self._lock:
                self.done += 1
                self.failed += not ok


@pytest.fixture
def fast(slave_factory: SlaveFactory) -> PymodbusSlave:
    peer: PymodbusSlave = slave_factory("rtu-over-tcp", units=(1,), size=100)
    return peer


@pytest.fixture
def site_stack() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


def check(quiet: float, flooded: float, what: str) -> None:
    print(f"bystanders ({what}): quiet {quiet:.2f} cycles/s, flooded {flooded:.2f} cycles/s")
    assert flooded >= 0.5 * quiet, (what, quiet, flooded)


def test_writes_and_forwards_to_dead_slaves_leave_the_thread_s_other_dtus_their_rate(
        fast: PymodbusSlave, site_stack: ExitStack) -> None:
    # each dead slave has its own target backoff: four of them cost the old loop thread
    # a timeout and a settle (1 s) every few seconds each
    site = Site(site_stack, fast, fast,
                [(s, {"readCycle": 3_600_000, "maxBackoff": 1000}) for s in DEAD_SLAVES])
    quiet = site.rate()
    assert quiet >= 3, quiet
    with Writes(site.flooded[:2]) as writes, \
            Flood(site.server.port, DEAD_SLAVES[2], struct.pack(">BHH", 3, 0, 1), 1) as f1, \
            Flood(site.server.port, DEAD_SLAVES[3], struct.pack(">BHH", 6, 1, 5), 1) as f2:
        wait_for(lambda: writes.failed >= 2 and f1.total() >= 1 and f2.total() >= 1, 30,
                 "the first answers to the flood")
        flooded = site.rate()
    check(quiet, flooded, "dead slaves flooded")
    assert not f1.errors and not f2.errors, (f1.errors, f2.errors)
    assert writes.failed == writes.done  # nobody answers them
    assert set(f1.answers) | set(f2.answers) <= {"exception 0B"}
    line = site.flooded[0].stats()["line"]
    assert line["targetBackoffs"] >= 1 and line["jobs"] >= 4, line


def test_a_forward_flood_to_a_live_slave_leaves_the_thread_s_other_dtus_their_rate(
        fast: PymodbusSlave, slave_factory: SlaveFactory, site_stack: ExitStack) -> None:
    slow: PymodbusSlave = slave_factory("rtu-over-tcp", units=(5,), size=100,
                                        response_delay=0.05)
    site = Site(site_stack, fast, slow, [(5, {"readCycle": 60_000})])
    quiet = site.rate()
    assert quiet >= 3, quiet
    with Flood(site.server.port, 5, struct.pack(">BHH", 3, 0, 4), masters=2) as flood:
        wait_for(lambda: flood.total() >= 5, 30, "the masters' first answers")
        flooded = site.rate()
        answered = flood.total()
    check(quiet, flooded, "a live slave flooded")
    assert not flood.errors and set(flood.answers) == {"ok"}, (flood.errors, flood.answers)
    assert answered >= 10
    assert site.flooded[0].stats()["line"]["forwarded"] >= answered


def _job_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if " job " in t.name]


def test_a_line_stopped_while_its_job_waits_for_a_dead_slave_fails_it_cleanly(
        fast: PymodbusSlave) -> None:
    """The stop cuts the socket of the job in flight (it fails at once, not after its
    timeout and settle), fails the jobs queued behind it, and leaves no job thread
    behind; the other DTU of the thread polls on."""
    port = free_port()
    with ExitStack() as stack:
        drivers: list[em.DriverModbusRtu] = []
        for cfg in (dtu_config(port, "BY0", 1),
                    dtu_config(port, "DEAD", 7, readTimeout=3000, readCycle=3_600_000)):
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
            stack.callback(drv.stop_device)
        good, dead = drivers
        stack.callback(SegmentedDtu(port, [b"BY0"], fast.port).close)
        stack.callback(SegmentedDtu(port, [b"DEAD"], fast.port).close)
        wait_for(lambda: good.device_driver_status is em.DeviceDriverStatus.RUNNING, 30,
                 "the good DTU polled")
        wait_for(lambda: dead.stats()["requests"] >= 1, 30, "the dead DTU polled")
        in_flight = dead.submit_writes([("r1", 1)])
        queued = [dead.submit_writes([("r2", k)]) for k in range(3)]
        wait_for(lambda: _job_threads() != [], 15, "the write on a job thread")
        cycles = good.stats()["cycles"]
        wait_for(lambda: good.stats()["cycles"] >= cycles + 3, 15,
                 "the good DTU polled while the write waits")
        start = time.monotonic()
        dead.stop_device()
        elapsed = time.monotonic() - start
        print(f"stopped after {elapsed:.2f} s (readTimeout 3 s)")
        assert elapsed < 2.0, elapsed
        for future in (in_flight, *queued):  # none left hanging, none confirmed
            assert future.done()
            assert future.exception() is not None or future.result()[0] is False
        print(f"the write in flight: {in_flight.exception() or in_flight.result()}; "
              f"the first queued: {queued[0].exception() or queued[0].result()}")
        cycles = good.stats()["cycles"]
        wait_for(lambda: good.stats()["cycles"] >= cycles + 3, 15, "the good DTU polling on")
    wait_for(lambda: _job_threads() == [], 15, "no job thread left")


def test_a_dtu_lost_during_a_job_fails_the_job_and_is_polled_again_when_it_redials(
        fast: PymodbusSlave) -> None:
    port = free_port()
    cfg = dtu_config(port, "LOST", 7, readTimeout=3000, readCycle=3_600_000)
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        dtu = SegmentedDtu(port, [b"LOST"], fast.port)
        try:
            wait_for(lambda: drv.stats()["requests"] >= 1, 30, "the DTU polled")
            future = drv.forward(struct.pack(">BHH", 3, 0, 1), 10.0)
            wait_for(lambda: _job_threads() != [], 15, "the forward on a job thread")
            start = time.monotonic()
        finally:
            dtu.close()  # the DTU hangs up while the forward waits for its slave
        with pytest.raises(em.ModbusError):
            future.result(15)
        print(f"the forward failed {time.monotonic() - start:.2f} s after the hang-up")
        assert time.monotonic() - start < 2.5  # at the hang-up, not after readTimeout
        dtu = SegmentedDtu(port, [b"LOST"], fast.port)
        try:
            wait_for(lambda: drv.stats()["line"]["reconnects"] >= 1, 30,
                     "the DTU's link up again")
            with pytest.raises(em.ModbusTimeoutError):  # slave 7 still answers nothing
                drv.forward(struct.pack(">BHH", 3, 0, 1), 10.0).result(15)
        finally:
            dtu.close()
    finally:
        drv.stop_device()


def test_a_job_runs_on_a_job_thread_that_counts_as_its_line_s_worker(
        fast: PymodbusSlave) -> None:
    """A job's callbacks may not wait for a job of their own line (it would wait for
    itself): on the job thread the line says it is on its worker, as on its loop thread;
    another line's job thread is not its worker."""
    port = free_port()
    cfgs = [dtu_config(port, f"W{k}", 1) for k in range(2)]
    with ExitStack() as stack:
        drivers = []
        for cfg in cfgs:
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            stack.callback(drv.stop_device)
            drivers.append(drv)
        for k in range(2):
            stack.callback(SegmentedDtu(port, [f"W{k}".encode()], fast.port).close)
        for drv in drivers:
            wait_for(lambda d=drv: d.stats()["requests"] >= 1, 30, "the DTUs polled")
        mine, other = (drv._line for drv in drivers)
        assert mine is not None and other is not None
        seen = mine.submit(lambda _link: (threading.current_thread().name, mine.on_worker(),
                                          other.on_worker())).result(15)
    name, on_mine, on_other = seen
    assert " job " in name and name.startswith("edgemodbus-loop"), name
    assert on_mine and not on_other
    assert not mine.on_worker()  # (this thread)
