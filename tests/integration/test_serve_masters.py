"""The gateway's Modbus TCP server under jobs that compete for a line (issue #25): one
master's requests waiting for lines are bounded across its connections (exception 06
over the bound, other masters still served), and a served unit's reads answered 0B are
counted and logged with why (polling delayed by jobs on the line, an item Invalid).
pymodbus (own process) as the slaves of an RTU-over-TCP line, pymodbus clients as the
masters (a second source address, 127.0.0.2, for the other master)."""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import Counter
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

import edgemodbus as em
from tests.conftest import SlaveFactory
from tests.integration.test_line_fairness import (
    BYSTANDER,
    FORWARD_UNIT,
    SERVED,
    SERVED_UNIT,
    TARGET,
    Flood,
    Line,
)
from tests.waiting import wait_for


def client(port: int, source: str = "127.0.0.1", timeout: float = 20.0) -> ModbusTcpClient:
    master = ModbusTcpClient("127.0.0.1", port=port, timeout=timeout, retries=0,
                             source_address=(source, 0))
    assert master.connect(), f"a master from {source} could not connect"
    return master


def answer(master: ModbusTcpClient, unit: int, address: int) -> str:
    """One FC03 read of ``unit``: "ok" or "exception NN"."""
    reply = master.read_holding_registers(address, count=1, device_id=unit)
    return f"exception {reply.exception_code:02X}" if reply.isError() else "ok"


def test_one_master_over_its_bound_gets_06_and_another_is_still_served(
        slave_factory: SlaveFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """A master with nine connections to a slow slave (0.5 s an answer) waits for the
    line with at most maxPendingPerMaster (3) requests, the rest answered 06 at once;
    so the line's own bound (5 here) keeps room and a master from another address is
    answered.  Before: the nine filled the line's bound and the other master got 06."""
    monkeypatch.setattr("edgemodbus.line.worker.MAX_PENDING", 5)
    slow = slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200)
    gw = Line(slow, forward_timeout=15.0, readTimeout=3000,
              server_args={"max_pending_per_master": 3})
    masters = [client(gw.port) for _ in range(9)]
    other = client(gw.port, "127.0.0.2")
    answers: Counter[str] = Counter()
    lock = threading.Lock()

    def ask(master: ModbusTcpClient, address: int) -> None:
        kind = answer(master, FORWARD_UNIT, address)
        with lock:
            answers[kind] += 1

    try:
        slow.set_response_delay(0.5)  # every job holds the line half a second
        threads = [threading.Thread(target=ask, args=(m, k), name=f"test-master-{k}")
                   for k, m in enumerate(masters)]
        for thread in threads:
            thread.start()
        wait_for(lambda: gw.server.stats()["busyMaster"] + gw.server.stats()["busy"] >= 1,
                 15, "a master over a bound")
        assert answer(other, FORWARD_UNIT, 50) == "ok"  # the line had room for it
        for thread in threads:
            thread.join(30)
        assert not any(t.is_alive() for t in threads)
        stats = gw.server.stats()
        print(f"the nine: {dict(answers)}; server {stats['busyMaster']} busyMaster, "
              f"{stats['busy']} busy; line jobsRefused {gw.line_stats()['jobsRefused']}")
        assert set(answers) <= {"ok", "exception 06"}, answers
        assert answers["exception 06"] == stats["busyMaster"] >= 1, (answers, stats)
        assert answers["ok"] >= 3
        assert stats["busy"] == 0 and gw.line_stats()["jobsRefused"] == 0
        # answered: the master's count is back to none waiting (one more is served)
        assert answer(masters[0], FORWARD_UNIT, 60) == "ok"
    finally:
        for master in [*masters, other]:
            master.close()
        gw.close()


def test_the_bound_counts_requests_until_answered_in_every_way(
        slave_factory: SlaveFactory) -> None:
    """Every way a request ends gives its place back (a reply, a 0B at its deadline, an
    exception the server answers itself, a served write): a master that asked 40 times
    in turn, one connection after the other, is never answered 06."""
    peer = slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200)
    gw = Line(peer, server_args={"max_pending_per_master": 1})
    master = client(gw.port)
    try:
        kinds: Counter[str] = Counter()
        peer.set_offline(TARGET)  # forwards end by their timeout, then by the backoff
        for k in range(10):
            kinds[answer(master, FORWARD_UNIT, k)] += 1
        peer.set_offline(TARGET, False)
        for k in range(10):
            reply = master.write_register(1, k, device_id=SERVED_UNIT)
            kinds["written" if not reply.isError() else f"{reply.exception_code:02X}"] += 1
        for _ in range(10):  # 01: not a function the forward path passes
            reply = master.read_device_information(device_id=FORWARD_UNIT)
            kinds["ok" if not reply.isError() else f"{reply.exception_code:02X}"] += 1
        polled = gw.target.stats()["responses"]  # (a good poll ends the backoff)
        wait_for(lambda: gw.target.stats()["responses"] > polled, 15, "a good poll")
        for k in range(10):
            kinds[answer(master, FORWARD_UNIT, k)] += 1
        print(dict(kinds))
        assert "exception 06" not in kinds and "06" not in kinds, kinds
        assert gw.server.stats()["busyMaster"] == 0
        assert kinds["written"] == 10
    finally:
        master.close()
        gw.close()


def test_a_served_unit_made_stale_by_jobs_says_why(
        slave_factory: SlaveFactory, caplog: pytest.LogCaptureFixture) -> None:
    """Forwards in a closed loop, one between each two polls of a slave that takes
    0.15 s, leave the served device's data older than its maxAgeMs (0.5 s): its reads
    answered 0B are counted as pollingDelayed and logged, rate-limited, with the unit,
    the age and maxAgeMs (before: a silent 0B)."""
    caplog.set_level(logging.WARNING, logger="edgemodbus.serve")
    peer = slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200,
                         response_delay=0.15)
    gw = Line(peer, served_cycle=100, max_age=0.5, forward_timeout=3.0, readTimeout=2000)
    reader = client(gw.port)
    try:
        kinds: Counter[str] = Counter()
        with Flood(gw.port, FORWARD_UNIT, struct.pack(">BHH", 3, 0, 4)) as flood:
            wait_for(lambda: flood.total() >= 4, 15, "the masters' first answers")
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and kinds["exception 0B"] < 3:
                kinds[answer(reader, SERVED_UNIT, 0)] += 1
        print(f"served reads during the flood: {dict(kinds)}; flood {dict(flood.answers)}")
        stale: dict[str, Any] = gw.server.stats()["staleReplies"][SERVED_UNIT]
        print(f"staleReplies {stale}; line {gw.line_stats()}")
        assert kinds["exception 0B"] >= 3, kinds
        assert stale["pollingDelayed"] >= 1, stale
        assert sum(stale.values()) >= kinds["exception 0B"]
        assert gw.line_stats()["pollsDelayed"] >= 1
        lines = [r.getMessage() for r in caplog.records
                 if r.name == "edgemodbus.serve" and "answered 0B" in r.getMessage()]
        assert any("unit 3 (dev3)" in m and "over maxAgeMs 500" in m
                   and "polling delayed by jobs on the line" in m for m in lines), lines
        assert len(lines) <= 3 * 4, lines  # three per 10 s and a summary, at most
    finally:
        reader.close()
        gw.close()


def test_a_served_read_of_an_invalid_item_says_which(
        slave_factory: SlaveFactory, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.serve")
    peer = slave_factory("rtu-over-tcp", units=(BYSTANDER, TARGET, SERVED), size=200)
    gw = Line(peer, served_cycle=100)
    reader = client(gw.port)
    try:
        assert answer(reader, SERVED_UNIT, 0) == "ok"
        peer.set_offline(SERVED)
        wait_for(lambda: gw.served.address_items[0].status is em.ItemStatus.INVALID, 15,
                 "the served items Invalid")
        assert answer(reader, SERVED_UNIT, 0) == "exception 0B"
        wait_for(lambda: gw.server.stats()["staleReplies"][SERVED_UNIT]["invalid"] >= 1, 15,
                 "the 0B counted")
        wait_for(lambda: any("unit 3 (dev3): 1 reads answered 0B: an item is Invalid"
                             in r.getMessage() and "e.g. r0: " in r.getMessage()
                             for r in caplog.records), 15, "the 0B logged")
    finally:
        reader.close()
        gw.close()
