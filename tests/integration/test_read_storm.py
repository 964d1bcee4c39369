"""A storm of reads on demand (the MQTT ``$read`` and Sparkplug read commands are
``driver.read_now``) costs the line one job per read that waits, not one per request:
a read of items that a waiting read (queued, not started) will read joins it
(poll/on_demand.py ``DemandReads``), counted in ``readsCoalesced``.  Against a pymodbus
slave that takes 20 ms a request, so reads pile up behind one another."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from concurrent.futures import Future, wait
from typing import Any

import pytest

import edgemodbus as em
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

ITEMS: list[dict[str, Any]] = [
    {"name": "p", "address": "hr:0", "deviceDataType": "UInt16"},
    {"name": "d", "address": "hr:40", "deviceDataType": "UInt16", "readCycle": "demand"},
    {"name": "e", "address": "hr:41", "deviceDataType": "UInt16", "readCycle": "demand"},
]


@pytest.fixture
def started() -> Iterator[tuple[em.DriverModbusRtu, PymodbusSlave]]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=100, fill="zero",
                       response_delay=0.02) as slave:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "dev1"},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": slave.port, "slaveId": 1, "readCycle": 100,
                              "readTimeout": 2000, "reconnectInterval": 200},
            "addressList": ITEMS})
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: drv.stats()["cycles"] >= 1, timeout=20, what="first cycle")
            yield drv, slave
        finally:
            drv.stop_device()


def test_a_storm_of_one_read_is_one_job_at_a_time_and_every_read_is_answered(
        started: tuple[em.DriverModbusRtu, PymodbusSlave]) -> None:
    drv, slave = started
    n = 1000
    before = slave.request_count(1)
    cycles = drv.stats()["cycles"]
    futures: list[Future[dict[str, dict[str, Any]]]] = []
    for _ in range(n):  # as fast as a command thread takes them: far past the line's 64
        futures.append(drv.read_now(["d"]))
    done, _ = wait(futures, timeout=60)
    assert len(done) == n
    answers = [f.result() for f in futures]  # none refused (LineBusyError before)
    assert all(list(a) == ["d"] and a["d"]["status"] == "Ok" for a in answers)
    coalesced = drv.stats()["readsCoalesced"]
    requests = slave.request_count(1) - before
    polls = drv.stats()["cycles"] - cycles
    # each job that ran is one request; the others joined one waiting
    assert coalesced >= n - (requests - polls)
    assert requests - polls < n // 10, (requests, polls, coalesced)
    wait_for(lambda: drv.stats()["cycles"] >= cycles + polls + 3, what="polling goes on")


def test_a_joined_read_answers_values_read_after_it_was_asked(
        started: tuple[em.DriverModbusRtu, PymodbusSlave]) -> None:
    """Each read is asked right after the slave's register was set to a larger number:
    its answer is never older than that (a join is only into a read not started)."""
    drv, slave = started
    asked: list[tuple[int, Future[dict[str, dict[str, Any]]]]] = []
    for value in range(1, 120):
        slave.set_registers(1, "hr", 41, [value])
        asked.append((value, drv.read_now(["e"] if value % 3 else None)))
    for value, future in asked:
        got = future.result(timeout=60)
        assert got["e"]["value"] >= value, (value, got["e"])
        assert set(got) == ({"e"} if value % 3 else {"p", "d", "e"})


def test_reads_from_many_threads_join_and_all_resolve(
        started: tuple[em.DriverModbusRtu, PymodbusSlave]) -> None:
    drv, _ = started
    results: list[Any] = []
    lock = threading.Lock()

    def storm(names: list[str] | None) -> None:
        mine = [drv.read_now(names) for _ in range(150)]
        got = [f.result(timeout=60) for f in mine]
        with lock:
            results.extend(got)

    threads = [threading.Thread(target=storm, args=(names,))
               for names in (["d"], ["e"], ["d", "e"], None)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=90)
    assert not any(t.is_alive() for t in threads)
    assert len(results) == 600
    assert drv.stats()["readsCoalesced"] > 300
