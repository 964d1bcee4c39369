"""Fair line scheduling (issue #25): queued jobs (forwarded requests, served writes) and
polling share a line so that neither starves; a forward target that timed out backs
off; a forward's timeout counts from its arrival; a line with too many jobs waiting
answers exception 06.  Real libmodbus on our side, pymodbus (own process) as the slaves
of an RTU-over-TCP line, raw-socket masters against the gateway's Modbus TCP server.
Every test runs on both engines (the ``engine`` fixture, tests/engines.py): a line
thread, and a loop thread where the line's jobs run on a job thread
(line/loop_jobs.py) under the same rule.

Rates are counted over windows (cycles of a bystander device) and compared with the
quiet rate measured in the same test: a loaded machine slows both alike."""

from __future__ import annotations

import itertools
import logging
import socket
import struct
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.errors import TargetBackoffError
from edgemodbus.serve import ModbusTcpServer
from edgemodbus.sim import Simulator
from tests.closed_loops import ClosedLoops
from tests.conftest import SlaveFactory
from tests.engines import with_engine
from tests.integration.test_driver import Running, all_ok, device
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

WINDOW = 3.0  # seconds a rate is counted over
BYSTANDER, TARGET, SERVED, DEAD = 1, 2, 3, 7  # slave ids on the line (7 answers nothing)
FORWARD_UNIT, SERVED_UNIT, DEAD_UNIT = 9, 3, 7  # the server's unit ids

pytestmark = pytest.mark.usefixtures("engine")


def comm(peer: PymodbusSlave, slave: int, **extra: Any) -> dict[str, Any]:
    base = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": peer.port,
            "slaveId": slave, "readTimeout": 700, "readCycle": 100, "retries": 0,
            "reconnectInterval": 300, "offlineAfterFailedCycles": 1000}
    base.update(extra)
    return with_engine(base)


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def recv_adu(sock: socket.socket) -> bytes:
    data = b""
    while len(data) < 6 or len(data) < 6 + struct.unpack(">H", data[4:6])[0]:
        chunk = sock.recv(260)
        if not chunk:
            raise ConnectionError("the server closed the connection")
        data += chunk
    return data


class Line:
    """Drivers on one pymodbus peer (one line) and the gateway's server: the bystander
    (slave 1, polled every 100 ms), a forward unit for slave 2, a served unit for
    slave 3 and, with ``dead``, a forward unit for slave 7, which never answers."""

    def __init__(self, peer: PymodbusSlave, dead: bool = False, forward_timeout: float = 0.7,
                 served_cycle: int = 1000, max_age: float | None = None,
                 server_args: dict[str, Any] | None = None, **extra: Any) -> None:
        self.peer = peer
        self.drivers: list[em.DriverModbusRtu] = []
        self.server = ModbusTcpServer("127.0.0.1", 0, **{
            "max_connections": 16, "idle_timeout": 0, **(server_args or {})})
        try:
            self.bystander = self._start(comm(peer, BYSTANDER, **extra))
            self.target = self._start(comm(peer, TARGET, readCycle=1000, **extra))
            served_cfg = self._config(comm(peer, SERVED, readCycle=served_cycle, **extra))
            self.served = self._start_cfg(served_cfg)
            self.server.forward_device(FORWARD_UNIT, self.target, timeout=forward_timeout)
            self.server.serve_device(SERVED_UNIT, self.served, served_cfg, max_age=max_age)
            if dead:
                self.dead = self._start(comm(peer, DEAD, readCycle=3_600_000, **extra))
                self.server.forward_device(DEAD_UNIT, self.dead, timeout=forward_timeout)
                wait_for(lambda: self.dead.stats().get("timeouts", 0) >= 1, 15,
                         "the dead slave's first poll")
            self.server.start()
            self.port = self.server.port
            for drv in self.drivers:
                if drv is not getattr(self, "dead", None):
                    wait_for(lambda d=drv: d.device_driver_status
                             is em.DeviceDriverStatus.RUNNING, 15, "the devices polled")
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _config(communication: dict[str, Any]) -> em.DeviceConfig:
        return em.load_device_config({
            "organization": {"deviceCode": f"dev{communication['slaveId']}"},
            "communication": communication,
            "addressList": [{"name": f"r{a}", "address": f"hr:{a}",
                             "deviceDataType": "UInt16"} for a in range(4)],
        })

    def _start(self, communication: dict[str, Any]) -> em.DriverModbusRtu:
        return self._start_cfg(self._config(communication))

    def _start_cfg(self, cfg: em.DeviceConfig) -> em.DriverModbusRtu:
        drv = em.DriverModbusRtu()
        self.drivers.append(drv)
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        return drv

    def line_stats(self) -> dict[str, Any]:
        return self.bystander.stats()["line"]

    def rate(self, seconds: float = WINDOW) -> float:
        """The bystander's cycles per second over a window of ``seconds``."""
        before, start = self.bystander.stats()["cycles"], time.monotonic()
        time.sleep(seconds)  # pacing: a measuring window, not a wait for an event
        return (self.bystander.stats()["cycles"] - before) / (time.monotonic() - start)

    def close(self) -> None:
        self.server.stop()
        for drv in reversed(self.drivers):
            drv.stop_device()


class Flood(ClosedLoops):
    """``masters`` raw-socket masters sending ``pdu`` to ``unit`` in a closed loop (the
    next request as soon as the answer came); answers counted by kind."""

    def __init__(self, port: int, unit: int, pdu: bytes, masters: int = 2) -> None:
        self.answers: Counter[str] = Counter()
        self.errors: list[str] = []
        super().__init__([(port, unit, pdu)] * masters, "test-master", join_s=15)

    def total(self) -> int:
        with self._lock:
            return sum(self.answers.values())

    def _run(self, port: int, unit: int, pdu: bytes) -> None:
        tid = 0
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=15) as sock:
                while not self._stop.is_set():
                    tid = (tid + 1) & 0xFFFF
                    sock.sendall(mbap(tid, unit, pdu))
                    adu = recv_adu(sock)
                    assert struct.unpack(">H", adu[:2])[0] == tid, "an answer to another request"
                    kind = f"exception {adu[8]:02X}" if adu[7] & 0x80 else "ok"
                    with self._lock:
                        self.answers[kind] += 1
        except (OSError, AssertionError) as exc:
            with self._lock:
                self.errors.append(repr(exc))


@pytest.fixture
def peer(slave_factory: SlaveFactory) -> PymodbusSlave:
    """A slave that takes 10 ms for every answer, units 1-3 (7 is silent)."""
    return slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200,
                         response_delay=0.01)


@pytest.fixture
def line(peer: PymodbusSlave) -> Iterator[Line]:
    gw = Line(peer)
    try:
        yield gw
    finally:
        gw.close()


def check_fair(quiet: float, flooded: float, flood: Flood) -> None:
    print(f"bystander: quiet {quiet:.2f} cycles/s, flooded {flooded:.2f} cycles/s; "
          f"answers {dict(flood.answers)}")
    assert not flood.errors, flood.errors
    assert flooded >= 0.5 * quiet, (quiet, flooded)


# -- floods of jobs ----------------------------------------------------------------------
def test_a_closed_loop_forward_flood_leaves_polling_its_rate(line: Line) -> None:
    quiet = line.rate()
    with Flood(line.port, FORWARD_UNIT, struct.pack(">BHH", 3, 0, 4)) as flood:
        wait_for(lambda: flood.total() >= 10, 15, "the masters' first answers")
        flooded = line.rate()
        answered = flood.total()
    check_fair(quiet, flooded, flood)
    assert set(flood.answers) == {"ok"}  # the jobs had their share too
    assert answered >= 20
    stats = line.line_stats()
    assert stats["jobs"] >= answered
    assert stats["jobsAheadOfPolls"] >= 1  # the flood did meet due polling


def test_the_rule_holds_when_the_line_steps_in_python(peer: PymodbusSlave,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    """With the frame trace on (the engine writes every frame into the link's trace
    ring, the worker logs them): the same rule."""
    caplog.set_level(logging.DEBUG, logger="edgemodbus.line")
    gw = Line(peer)
    try:
        quiet = gw.rate()
        with Flood(gw.port, FORWARD_UNIT, struct.pack(">BHH", 3, 0, 4)) as flood:
            wait_for(lambda: flood.total() >= 10, 15, "the masters' first answers")
            flooded = gw.rate()
        check_fair(quiet, flooded, flood)
        assert set(flood.answers) == {"ok"}
        assert any(" TX " in r.getMessage() for r in caplog.records)
    finally:
        gw.close()


def test_a_write_flood_to_a_served_unit_leaves_polling_its_rate(line: Line) -> None:
    quiet = line.rate()
    with Flood(line.port, SERVED_UNIT, struct.pack(">BHH", 6, 1, 1234)) as flood:
        wait_for(lambda: flood.total() >= 10, 15, "the masters' first answers")
        flooded = line.rate()
    check_fair(quiet, flooded, flood)
    assert set(flood.answers) == {"ok"}
    assert line.peer.registers(SERVED, "hr", 1) == [1234]


def test_forwards_to_a_dead_slave_back_off(peer: PymodbusSlave) -> None:
    gw = Line(peer, dead=True, forward_timeout=0.7)
    try:
        quiet = gw.rate()
        with Flood(gw.port, DEAD_UNIT, struct.pack(">BHH", 3, 0, 1), masters=1) as flood:
            # the first forward costs the line its timeout and the settle; then 0B at once
            wait_for(lambda: gw.line_stats()["targetBackoffs"] >= 1, 15,
                     "a forward answered by the dead slave's backoff")
            flooded = gw.rate()
        check_fair(quiet, flooded, flood)
        assert set(flood.answers) == {"exception 0B"}
        stats = gw.line_stats()
        # a dead target costs the line a timeout per backoff, not one per request
        assert stats["targetBackoffs"] > 10 * stats["forwardTimeouts"], stats
    finally:
        gw.close()


def test_the_backoff_ends_when_the_slave_answers_again(line: Line) -> None:
    line.peer.set_offline(TARGET)
    request = struct.pack(">BHH", 3, 0, 1)
    # (3 s: sent even behind a poll of the silent slave, its timeout and settle)
    with pytest.raises(em.ModbusTimeoutError) as first:
        line.target.forward(request, 3.0).result(15)
    assert not isinstance(first.value, TargetBackoffError)
    start = time.monotonic()
    with pytest.raises(TargetBackoffError, match="slave 2 did not answer"):
        line.target.forward(request, 3.0).result(15)
    assert time.monotonic() - start < 1.0  # at once (at most behind a poll in flight)
    assert line.line_stats()["targetBackoffs"] == 1
    line.peer.set_offline(TARGET, False)
    # its device's next poll gets an answer: the slave is alive, forwards go out
    polled = line.target.stats()["responses"]
    wait_for(lambda: line.target.stats()["responses"] > polled, 15, "a good poll")
    reply = line.target.forward(struct.pack(">BHH", 3, 5, 2), 3.0).result(15)
    assert reply == b"\x03\x04" + struct.pack(">2H", *line.peer.registers(TARGET, "hr", 5, 2))


def test_writes_to_a_silent_served_slave_back_off(peer: PymodbusSlave) -> None:
    # (the served device polls once a minute: only the writes reach the silent slave)
    gw = Line(peer, served_cycle=60_000)
    try:
        quiet = gw.rate()
        peer.set_offline(SERVED)
        with Flood(gw.port, SERVED_UNIT, struct.pack(">BHH", 6, 2, 77)) as flood:
            wait_for(lambda: gw.line_stats()["targetBackoffs"] >= 1, 15,
                     "a write answered by the silent slave's backoff")
            flooded = gw.rate()
        check_fair(quiet, flooded, flood)
        assert set(flood.answers) == {"exception 0B"}
        stats = gw.line_stats()
        assert stats["targetBackoffs"] > 10 * stats["timeouts"], stats
        why = gw.served.write_address("r2", 5)
        assert not why[0] and "did not answer" in str(why[1]), why
    finally:
        gw.close()


def test_jobs_and_reads_alternate_while_blocks_are_due(monkeypatch: pytest.MonkeyPatch,
                                                       engine: str) -> None:
    """The rule at the request level (csrc/emb_engine.c): 12 writes queued at once on a
    line whose 20 blocks are always due go out with a read between each two, and the
    first one waits for the read in flight only."""
    with Simulator([1]) as sim:
        slave = sim.slave(1)
        slave.faults.delay = 0.005
        seen: list[int] = []
        execute = slave._execute

        def recording(pdu: bytes) -> bytes:
            seen.append(pdu[0])
            return execute(pdu)

        monkeypatch.setattr(slave, "_execute", recording)
        port = sim.serve_tcp("127.0.0.1", 0)
        items = [{"name": f"t{k}", "address": f"hr:{10 * k}", "deviceDataType": "UInt16"}
                 for k in range(20)]
        cfg = device(port, items, readCycle=10, maxMergeAddressGap=0, readTimeout=1000,
                     engine=engine)
        with Running(cfg) as drv:
            wait_for(all_ok(cfg), 15, "every item read")
            mark = len(seen)
            futures = [drv.submit_writes([(f"t{k}", 100 + k)]) for k in range(12)]
            for future in futures:
                assert future.result(15) == (True, None)
        order = seen[mark:]
        writes = [i for i, fc in enumerate(order) if fc in (6, 16)]
        assert len(writes) == 12, order
        assert writes[0] <= 1, order  # after the read in flight
        gaps = [b - a for a, b in itertools.pairwise(writes)]
        assert min(gaps) >= 2, order  # a read (at least) between two writes


# -- the bound: exception 06 ---------------------------------------------------------------
def test_masters_over_the_lines_bound_get_06(slave_factory: SlaveFactory,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("edgemodbus.line.worker.MAX_PENDING", 2)
    slow = slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200)
    gw = Line(slow, forward_timeout=10.0, readTimeout=3000)
    socks: list[socket.socket] = []
    try:
        slow.set_response_delay(0.5)  # every job holds the line half a second
        for tid in range(8):
            sock = socket.create_connection(("127.0.0.1", gw.port), timeout=30)
            socks.append(sock)
            sock.sendall(mbap(tid, FORWARD_UNIT, struct.pack(">BHH", 3, tid, 1)))
        answers = [recv_adu(sock) for sock in socks]  # every master gets an answer
        busy = [a for a in answers if a[7:] == b"\x83\x06"]
        good = [a for a in answers if a[7] == 3]
        assert len(busy) + len(good) == 8, answers
        assert busy and len(good) >= 2, answers
        assert gw.line_stats()["jobsRefused"] == len(busy)
        assert gw.server.stats()["busy"] == len(busy)
    finally:
        for sock in socks:
            sock.close()
        gw.close()


# -- timeouts count from arrival ------------------------------------------------------------
def test_a_forward_is_answered_by_its_timeout_counted_from_arrival(
        peer: PymodbusSlave) -> None:
    # a long settle after the dead slave's timeout holds the line 0.8 + 2 s
    gw = Line(peer, dead=True, forward_timeout=0.8, settleTimeout=2000)
    try:
        with socket.create_connection(("127.0.0.1", gw.port), timeout=15) as dead_master, \
                socket.create_connection(("127.0.0.1", gw.port), timeout=15) as master:
            sent = gw.line_stats()["forwarded"]
            dead_master.sendall(mbap(1, DEAD_UNIT, struct.pack(">BHH", 3, 0, 1)))
            wait_for(lambda: gw.line_stats()["forwarded"] > sent, 15,
                     "the dead slave's forward on the line")
            start = time.monotonic()
            master.sendall(mbap(7, FORWARD_UNIT, struct.pack(">BHH", 3, 0, 1)))
            reply = recv_adu(master)
            elapsed = time.monotonic() - start
            print(f"answered after {elapsed:.3f} s (timeout 0.8 s, the line busy 2.8 s)")
            assert reply[:2] == b"\x00\x07" and reply[7:] == b"\x83\x0b"
            assert elapsed < 2.0, elapsed  # not after the dead slave's timeout and settle
            assert recv_adu(dead_master)[7:] == b"\x83\x0b"
            assert gw.server.stats()["forwardExpired"] >= 1
            # once the line is through the settle, its next request gets its own
            # answer, not a late one of the first
            cycles = gw.bystander.stats()["cycles"]
            wait_for(lambda: gw.bystander.stats()["cycles"] >= cycles + 2, 15,
                     "the line polling again")
            master.sendall(mbap(8, FORWARD_UNIT, struct.pack(">BHH", 3, 10, 3)))
            reply = recv_adu(master)
            assert reply[:2] == b"\x00\x08"
            assert reply[7:] == b"\x03\x06" + struct.pack(
                ">3H", *gw.peer.registers(TARGET, "hr", 10, 3))
    finally:
        gw.close()


def test_a_late_reply_is_dropped_not_given_to_the_next_request(line: Line) -> None:
    line.peer.set_response_delay(0.4)  # the slave answers after the forward's 0.2 s
    with pytest.raises(em.ModbusTimeoutError):
        line.target.forward(struct.pack(">BHH", 3, 20, 1), 0.2).result(15)
    line.peer.set_response_delay(0.0)
    polled = line.target.stats()["responses"]  # (the backoff ends with a good poll)
    wait_for(lambda: line.target.stats()["responses"] > polled, 15, "a good poll")
    reply = line.target.forward(struct.pack(">BHH", 3, 30, 2), 1.0).result(15)
    assert reply == b"\x03\x04" + struct.pack(">2H", *line.peer.registers(TARGET, "hr", 30, 2))
