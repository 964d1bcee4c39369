"""A redundant pair's lease gates the line (line/worker.py ``lease``, csrc/emb_engine.c,
csrc/emb_fault.c, line/link.py ``gate``): past the lease's deadline no request starts,
neither a poll (between passes, in the middle of a pass, a retry) nor a job's request
queued while the lease still held; the link is closed, and polling goes on once the
lease is renewed.  A LeaderDriver (gateway/pair.py) polls a pymodbus slave in its own
process, which counts the requests it receives; the lease's engine is a switch (the
Redis protocol is tested in test_redundant_pair.py), its clock the monotonic one shifted
so that the deadline falls where a test wants it."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from edgemodbus.config import load_device_config
from edgemodbus.errors import ModbusConnectionError
from edgemodbus.gateway.lease import Lease
from edgemodbus.gateway.pair import LeaderDriver
from tests.lease_switch import Switch
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

TTL_MS, RENEW_MS, MARGIN_MS = 1000, 300, 100


class ShiftedClock:
    """time.monotonic() plus an offset: a renewal taken at offset x ends the lease x
    seconds later than a real one would."""

    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.offset


class Rig:
    def __init__(self, slave: PymodbusSlave) -> None:
        self.slave = slave
        self.clock, self.engine = ShiftedClock(), Switch()
        self.lease = Lease(self.engine, TTL_MS, RENEW_MS, margin_ms=MARGIN_MS,
                           clock=self.clock)

    def hold_for(self, seconds: float) -> None:
        """Acquire or renew so that requests may start for ``seconds`` more."""
        self.clock.offset = seconds - (TTL_MS - MARGIN_MS) / 1000
        self.lease.step()
        self.clock.offset = 0.0
        assert self.lease.deadline() == pytest.approx(time.monotonic() + seconds, abs=0.05)

    def requests(self) -> int:
        return sum(self.slave.stats()["perConnection"].values())

    def closed(self) -> bool:
        return not self.slave.stats()["activeConnections"]


@contextmanager
def leader(rig: Rig, items: list[dict[str, Any]], **comm: Any) -> Iterator[LeaderDriver]:
    settings: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": rig.slave.port,
        "slaveId": 1, "readCycle": 100, "readTimeout": 2000, "byteTimeout": 50,
        "retries": 0, "reconnectInterval": 200}
    settings.update(comm)
    cfg = load_device_config({"organization": {"deviceCode": "plc"},
                              "communication": settings, "addressList": items})
    driver = LeaderDriver(rig.lease, cfg)
    assert driver.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        yield driver
    finally:
        driver.stop_device()


def hr(*addresses: int) -> list[dict[str, Any]]:
    return [{"name": f"t{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
            for a in addresses]


def test_no_poll_once_the_lease_is_lost_and_polling_again_once_it_is_held() -> None:
    """The lease lost while polling (another instance holds it): the engine, woken,
    sends nothing more and the link closes; held again: a new link, polling again."""
    with PymodbusSlave("rtu-over-tcp") as slave:
        rig = Rig(slave)
        rig.hold_for(60)
        with leader(rig, hr(0, 1)) as driver:
            wait_for(lambda: rig.requests() >= 3, timeout=30, what="polling")
            rig.engine.free = False
            rig.lease.step()  # the renewal fails: lost
            lost = time.monotonic()
            assert rig.lease.deadline() == 0.0
            wait_for(rig.closed, timeout=30, what="the link closed")
            wait_for(lambda: driver.device_driver_status.value == "Reconnecting",
                     timeout=30, what="the device told why")
            (conn,) = slave.stats()["requestTimes"]
            # at most the transaction in flight when it was lost (it had started before)
            assert slave.stats()["requestTimes"][conn][1] < lost
            count = rig.requests()
            rig.engine.free = True
            rig.lease.step()  # held again
            wait_for(lambda: rig.requests() >= count + 3, timeout=30,
                     what="polling once held again")
            assert slave.stats()["connections"] == 2
            assert driver.device_driver_status.value == "Running"


def test_a_pass_stops_before_its_next_block_once_the_deadline_passed() -> None:
    """Three blocks per pass, each answered after 3 s; the lease is known to hold for
    1.5 s from the start: the first block goes out, the deadline passes while it is in
    flight, the second is never sent (the engine looks before every request, not only
    between passes)."""
    with PymodbusSlave("rtu-over-tcp") as slave:
        rig = Rig(slave)
        slave.set_response_delay(3.0)
        rig.hold_for(1.5)
        with leader(rig, hr(0, 300, 600), readCycle=60_000, readTimeout=5000):
            wait_for(lambda: rig.requests() >= 1, timeout=30, what="the first block sent")
            wait_for(rig.closed, timeout=30, what="the link closed")
            assert rig.requests() == 1, slave.stats()


def test_no_retry_after_the_deadline() -> None:
    """A silent slave, 3 retries, a 2 s response timeout; the lease is known to hold for
    1.5 s from the start: the deadline passes during the first try's timeout, the read
    is not tried again (the retries are made in C, csrc/emb_fault.c)."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        rig = Rig(slave)
        slave.set_offline(1)
        rig.hold_for(1.5)
        with leader(rig, hr(0), readTimeout=2000, retries=3, readCycle=60_000):
            wait_for(lambda: rig.requests() >= 1, timeout=30, what="the first try")
            wait_for(rig.closed, timeout=30, what="the link closed")
            assert rig.requests() == 1, slave.stats()


def test_a_write_queued_while_the_lease_held_is_not_sent_once_it_is_lost() -> None:
    """A write queued behind a poll in flight (the slave answers after 1 s), accepted
    while the lease held; the lease is lost before the poll's reply: the write is
    refused as it is about to go out, nothing reaches the slave."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
        rig = Rig(slave)
        rig.hold_for(60)
        with leader(rig, hr(0), readCycle=100) as driver:
            wait_for(lambda: rig.requests() >= 2, timeout=30, what="polling")
            slave.set_response_delay(1.0)
            seen = rig.requests()
            wait_for(lambda: rig.requests() > seen, timeout=30, what="a slow poll in flight")
            future = driver.submit_writes([("t0", 4321)])  # the lease holds: accepted
            rig.engine.free = False
            rig.lease.step()  # another instance holds the lease now
            assert not rig.lease.held
            with pytest.raises(ModbusConnectionError, match="does not hold the pair's lease"):
                future.result(timeout=30)
            wait_for(rig.closed, timeout=30, what="the link closed")
            stats = slave.stats()
            assert not stats["writesPerConnection"], stats
            assert slave.registers(1, "hr", 0) != [4321]
