"""The fault policy inside the line engine (csrc/emb_fault.c), end to end: each outcome
(retry, timeout and offline with backoff probing, exception 02 bisection) against a real
slave, counted once, and how often the line worker enters Python for it.

The retry test uses our simulator (it drops exactly every Nth reply); the others a
pymodbus slave in its own process (tests/peers.py), so the peer is not our code."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.line.worker import LineWorker
from edgemodbus.poll.poller import Poller
from tests.integration.test_faults import Rig, hr_items, stop_and_count
from tests.peers import ExceptionRange, PymodbusSlave, default_register
from tests.waiting import wait_for

OK, INVALID = ItemStatus.OK, ItemStatus.INVALID
RUNNING, OFFLINE = DeviceDriverStatus.RUNNING, DeviceDriverStatus.OFFLINE


class Entries:
    """Counts calls of a class's methods (any thread): how often the line worker came
    back to Python, and for what."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, cls: type, *names: str) -> None:
        self.calls = dict.fromkeys(names, 0)
        for name in names:
            if hasattr(cls, name):  # (a method another version may not have: never called)
                monkeypatch.setattr(cls, name, self._counted(name, getattr(cls, name)))

    def _counted(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def counted(*args: Any, **kwargs: Any) -> Any:
            self.calls[name] += 1
            return fn(*args, **kwargs)
        return counted

    def total(self) -> int:
        return sum(self.calls.values())


def device(port: int, items: list[dict[str, Any]], slave: int = 1,
           **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
        "slaveId": slave, "readTimeout": 150, "readCycle": 100, "byteTimeout": 30,
        "reconnectInterval": 300, "connectTimeout": 1000, "retries": 0,
    }
    comm.update(extra)
    return em.load_device_config({"organization": {"deviceCode": f"dev{slave}"},
                                  "communication": comm, "addressList": items})


class Started:
    """Drivers started for configs, stopped at the end of the with-block."""

    def __init__(self, *cfgs: em.DeviceConfig) -> None:
        self.cfgs = cfgs
        self.drivers = [em.DriverModbusRtu() for _ in cfgs]

    def __enter__(self) -> list[em.DriverModbusRtu]:
        for drv, cfg in zip(self.drivers, self.cfgs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        return self.drivers

    def __exit__(self, *exc: object) -> None:
        for drv in self.drivers:
            drv.stop_device()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    try:
        yield r
    finally:
        r.close()


def test_a_retry_that_gets_through_is_counted_once_and_costs_no_python(
        rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every 4th reply dropped, one retry: each drop is one timeout and one retry, in the
    device's and the line's counters alike, and the retry runs in C: the worker never
    enters the poller for it (the values do not change)."""
    p = rig.start(hr_items(0, 10), retries=1)
    rig.settle(p)
    entries = Entries(monkeypatch, Poller, "engine_cycle", "engine_failed", "engine_split")
    rig.sim.slave(1).faults.drop_every = 4
    rig.wait_faults("drop_every", 6)
    assert entries.total() == 0, entries.calls
    stats, drops = stop_and_count(rig, p, "drop_every")
    line = stats["line"]
    assert stats["timeouts"] == stats["retries"] == drops
    assert stats["failedCycles"] == stats["skippedBlocks"] == 0
    assert stats["requests"] == stats["responses"] + stats["timeouts"]
    # one device on the line: the line counted each request exactly as the device did
    for key in ("requests", "responses", "timeouts", "crcErrors", "protocolErrors"):
        assert line[key] == stats[key], key


def test_a_silent_slave_goes_offline_is_probed_once_per_backoff_and_comes_back() -> None:
    """pymodbus slave 1 goes silent: the block that timed out and the rest of the pass
    are Invalid ("device not responding"); after 3 failed cycles the slave is Offline and
    probed with one request per backoff interval (100 ms doubling to 800 ms); once it
    answers again it is Running and every item Ok."""
    items = [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
             for a in (0, 300, 600)]  # three blocks
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=1000) as peer:
        cfg = device(peer.port, items, offlineAfterFailedCycles=3, maxBackoff=800,
                     readTimeout=100)
        with Started(cfg) as (drv,):
            wait_for(lambda: all(it.status is OK for it in cfg.address_list), what="Ok")
            base = drv.stats()
            peer.set_offline(1)
            wait_for(lambda: drv.device_driver_status is OFFLINE, what="Offline")
            reasons = {it.error_reason for it in cfg.address_list}
            assert all(it.status is INVALID for it in cfg.address_list)
            assert reasons == {"device not responding: slave 1 FC03 @0+1: no response "
                               "(timeout)"}, reasons
            went = drv.stats()
            assert went["failedCycles"] - base["failedCycles"] == 3
            assert went["skippedBlocks"] - base["skippedBlocks"] == 3 * 2
            start = time.monotonic()
            time.sleep(2.0)  # pacing: the window the probes are counted in (not a wait)
            after = drv.stats()
            elapsed = time.monotonic() - start
            probes = after["requests"] - went["requests"]
            # 0.1 + 0.2 + 0.4 + 0.8 + 0.8 ... s apart: at most 1 + elapsed / 0.1 ... but
            # doubling, so about five within 2 s; never one per cycle (20)
            assert 2 <= probes <= 6, (probes, elapsed)
            assert after["timeouts"] - went["timeouts"] == probes
            assert after["skippedBlocks"] - went["skippedBlocks"] == 2 * probes
            peer.set_offline(1, False)
            wait_for(lambda: drv.device_driver_status is RUNNING, timeout=20, what="Running")
            wait_for(lambda: all(it.status is OK for it in cfg.address_list), what="Ok again")
            values = [it.value for it in cfg.address_list]
            assert values == [default_register(1, "hr", a) for a in (0, 300, 600)]


def test_exception_02_splits_down_to_the_single_bad_address(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """pymodbus refuses hr:5 with exception 02: the block hr:0..9 is split until only
    hr5 fails; the split is kept (no second split, one exception per cycle), and once
    the failure is known the worker no longer enters Python for it."""
    items = [{"name": f"hr{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
             for a in range(10)]
    caplog.set_level(logging.INFO, logger="edgemodbus")
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=100,
                       exception_ranges=[ExceptionRange(5, 6, 2, area="hr")]) as peer:
        cfg = device(peer.port, items)
        by_name = {it.name: it for it in cfg.address_list}
        with Started(cfg) as (drv,):
            wait_for(lambda: by_name["hr5"].status is INVALID
                     and all(by_name[f"hr{a}"].status is OK for a in range(10) if a != 5),
                     what="only hr5 Invalid")
            assert "illegal data address" in (by_name["hr5"].error_reason or "")
            for a in range(10):
                if a != 5:
                    assert by_name[f"hr{a}"].value == default_register(1, "hr", a)
            splits = [r for r in caplog.records if "split into" in r.getMessage()]
            assert splits[0].getMessage().endswith("split into @0+5, @5+5")
            start = drv.stats()
            entries = Entries(monkeypatch, Poller, "engine_cycle", "engine_split",
                              "engine_failed")
            wait_for(lambda: drv.stats()["cycles"] >= start["cycles"] + 10, what="10 cycles")
            end = drv.stats()
            cycles = end["cycles"] - start["cycles"]
            refused = end["exceptions"].get(2, 0) - start["exceptions"].get(2, 0)
            assert cycles - 1 <= refused <= cycles + 1, (cycles, refused)
            assert entries.total() == 0, entries.calls  # the same failure: no news
            assert len([r for r in caplog.records if "split into" in r.getMessage()]) \
                == len(splits)


def test_five_devices_on_one_line_enter_python_once_per_round(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Five slaves on one line, every pass with changes (reportMode "cycle"): the engine
    hands Python the passes of a round together, one entry per round, not one per
    device."""
    items = [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
             for a in range(10)]
    with PymodbusSlave("rtu-over-tcp", units=(1, 2, 3, 4, 5), size=100) as peer:
        cfgs = [device(peer.port, items, slave=s, reportMode="cycle", readCycle=200,
                       readTimeout=500) for s in (1, 2, 3, 4, 5)]
        with Started(*cfgs) as drivers:
            assert len(em.DriverModbusRtu.registry.lines()) == 1
            wait_for(lambda: all(it.status is OK for cfg in cfgs for it in cfg.address_list),
                     what="every item Ok")
            entries = Entries(monkeypatch, LineWorker, "_dispatch")
            cycles = Entries(monkeypatch, Poller, "engine_cycle")
            start = [drv.stats()["cycles"] for drv in drivers]
            wait_for(lambda: drivers[0].stats()["cycles"] >= start[0] + 15, timeout=20,
                     what="15 rounds")
            rounds = [drv.stats()["cycles"] - s for drv, s in zip(drivers, start, strict=True)]
            assert min(rounds) >= 10, rounds
            # every pass had changes and reached Python, in a few entries per round
            assert cycles.calls["engine_cycle"] >= sum(rounds) - 5
            # one entry per device's pass would be sum(rounds) (5 per round); quiet, it is
            # about one per round; a loaded machine spreads the passes' due times, and a
            # line that idles between two of them hands over early: allow up to half
            assert entries.calls["_dispatch"] <= sum(rounds) / 2 + 2, (entries.calls, rounds)
