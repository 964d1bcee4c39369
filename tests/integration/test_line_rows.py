"""Issue #25's line-scheduling rows again, with independent masters (pymodbus clients,
each its own connection, in a closed loop) against the gateway's Modbus TCP server, a
pymodbus slave in its own process (RTU framing over TCP: an endpoint line on the thread
engine, or a loop thread whose jobs run on a job thread: the ``engine`` fixture), and the
reads on demand added since (``driver.read_now()``, what MQTT ``$read`` and Sparkplug
read commands call: each a job).  Every row: the bystander device (slave
1, polled every 100 ms) keeps at least half its quiet rate, counted over windows in the
same test (a loaded machine slows both alike).  docs/fault-checklist.md "The line (jobs
and polling)" has the figures."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

import edgemodbus as em
from tests.closed_loops import ClosedLoops
from tests.conftest import SlaveFactory
from tests.engines import with_engine
from tests.integration.test_line_fairness import (
    BYSTANDER,
    DEAD_UNIT,
    FORWARD_UNIT,
    SERVED,
    SERVED_UNIT,
    TARGET,
    Line,
)
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

DEMAND = 4  # the slave of the device read on demand

pytestmark = pytest.mark.usefixtures("engine")


class Masters(ClosedLoops):
    """``n`` threads each calling ``ask()`` of their own in a closed loop (the next as
    soon as the answer came), answers counted by kind."""

    def __init__(self, asks: list[Callable[[], str]]) -> None:
        self.answers: Counter[str] = Counter()
        self.errors: list[str] = []
        super().__init__([(ask,) for ask in asks], "test-ask")

    def total(self) -> int:
        with self._lock:
            return sum(self.answers.values())

    def _run(self, ask: Callable[[], str]) -> None:
        try:
            while not self._stop.is_set():
                kind = ask()
                with self._lock:
                    self.answers[kind] += 1
        except Exception as exc:  # (reported by the test)
            with self._lock:
                self.errors.append(repr(exc))


def pymodbus_masters(port: int, n: int, call: Callable[[ModbusTcpClient], Any]
                     ) -> tuple[Masters, list[ModbusTcpClient]]:
    clients = [ModbusTcpClient("127.0.0.1", port=port, timeout=20, retries=0)
               for _ in range(n)]
    for client in clients:
        assert client.connect()

    def asker(client: ModbusTcpClient) -> Callable[[], str]:
        def ask() -> str:
            reply = call(client)
            return f"exception {reply.exception_code:02X}" if reply.isError() else "ok"
        return ask

    return Masters([asker(c) for c in clients]), clients


def demand_device(peer: PymodbusSlave, blocks: int) -> em.DeviceConfig:
    """Items far apart: one block each, as many transactions per read of them all."""
    return em.load_device_config({
        "organization": {"deviceCode": "demand"},
        "communication": with_engine({
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": peer.port,
            "slaveId": DEMAND, "readCycle": 60_000, "readTimeout": 700, "retries": 0,
            "maxMergeAddressGap": 0, "reconnectInterval": 300,
            "offlineAfterFailedCycles": 1000}),
        "addressList": [{"name": f"d{k}", "address": f"hr:{8 * k}",
                         "deviceDataType": "UInt16"} for k in range(blocks)],
    })


@pytest.fixture
def peer(slave_factory: SlaveFactory) -> PymodbusSlave:
    """A slave that takes 10 ms for every answer (units 1-4; 7 is silent)."""
    return slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED, DEMAND), size=200,
                         response_delay=0.01)


def row(gw: Line, masters: Masters, what: str, started: Callable[[], bool]) -> None:
    quiet = gw.rate()
    with masters:
        wait_for(started, 15, f"{what}: the flood under way")
        flooded = gw.rate()
        answered = masters.total()
    stats = gw.line_stats()
    print(f"\n{what}: bystander quiet {quiet:.2f} cycles/s, during {flooded:.2f} cycles/s "
          f"({flooded / quiet:.0%}); answers {dict(masters.answers)} ({answered}); line "
          f"jobs {stats['jobs']}, jobsAheadOfPolls {stats['jobsAheadOfPolls']}, "
          f"pollsDelayed {stats['pollsDelayed']}, targetBackoffs {stats['targetBackoffs']}")
    assert not masters.errors, masters.errors
    assert flooded >= 0.5 * quiet, (what, quiet, flooded)


def test_two_scada_masters_forwarding_to_a_live_slave(peer: PymodbusSlave) -> None:
    gw = Line(peer)
    try:
        masters, clients = pymodbus_masters(
            gw.port, 2, lambda c: c.read_holding_registers(0, count=4, device_id=FORWARD_UNIT))
        row(gw, masters, "two masters forwarding FC03 to a live slave (10 ms)",
            lambda: masters.total() >= 10)
        assert set(masters.answers) == {"ok"}
    finally:
        for client in clients:
            client.close()
        gw.close()


def test_fc06_flood_to_a_served_unit(peer: PymodbusSlave) -> None:
    gw = Line(peer)
    try:
        masters, clients = pymodbus_masters(
            gw.port, 2, lambda c: c.write_register(1, 1234, device_id=SERVED_UNIT))
        row(gw, masters, "two masters writing FC06 to a served unit",
            lambda: masters.total() >= 10)
        assert set(masters.answers) == {"ok"}
        assert peer.registers(SERVED, "hr", 1) == [1234]
    finally:
        for client in clients:
            client.close()
        gw.close()


def test_one_master_forwarding_to_a_dead_slave(peer: PymodbusSlave) -> None:
    gw = Line(peer, dead=True, forward_timeout=0.7)
    try:
        masters, clients = pymodbus_masters(
            gw.port, 1, lambda c: c.read_holding_registers(0, count=1, device_id=DEAD_UNIT))
        row(gw, masters, "one master forwarding back-to-back to a dead slave (0.7 s)",
            lambda: gw.line_stats()["targetBackoffs"] >= 1)
        assert set(masters.answers) == {"exception 0B"}
    finally:
        for client in clients:
            client.close()
        gw.close()


@pytest.mark.parametrize(("threads", "blocks"), [(1, 8), (4, 24)])
def test_a_flood_of_reads_on_demand(peer: PymodbusSlave, threads: int, blocks: int) -> None:
    """Each ``read_now()`` of a device of several blocks is one job of as many
    transactions: the line owes due polling as many poll transactions after it (one
    per job before: 24 blocks left the bystander a third of its rate)."""
    gw = Line(peer)
    try:
        cfg = demand_device(peer, blocks)
        demand = gw._start_cfg(cfg)
        wait_for(lambda: demand.device_driver_status is em.DeviceDriverStatus.RUNNING, 15,
                 "the demand device polled")

        def ask() -> str:
            entries = demand.read_now().result(30)
            return "ok" if all(e["status"] == "Ok" for e in entries.values()) else "invalid"

        masters = Masters([ask] * threads)
        row(gw, masters, f"{threads} threads calling read_now() of {blocks} blocks in a loop",
            lambda: masters.total() >= 3)
        assert set(masters.answers) == {"ok"}
    finally:
        gw.close()
