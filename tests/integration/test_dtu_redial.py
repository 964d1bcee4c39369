"""A fleet's DTUs dial from several source addresses and processes (sim/dialling.py,
sim/fleet_procs.py), and the whole fleet redials at once after its connections are
reset, as after a network outage: every value Ok again through a new link, none wrong,
no DTU refused while the listener's caps are sized for the fleet."""

from __future__ import annotations

import time

import pytest

from edgemodbus.datatypes import Area
from edgemodbus.line import dtu_registry
from edgemodbus.sim import DtuFleet, FleetProcesses, default_register, loopback_sources
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.waiting import wait_for

REFUSALS = ("unknown", "silent", "oversize", "evicted", "refusedPortCap", "refusedSourceCap",
            "refusedNotAllowed", "refusedDtuNotAllowed", "badKey", "duplicateRefused",
            "refusedContested", "contested", "acceptErrors")
"""The listener's counters of connections it turned away (line/dtu_newcomer.py)."""


def test_loopback_sources_cover_the_fleet_and_bad_sources_are_named() -> None:
    assert loopback_sources(1) == ("127.0.0.1",)
    assert loopback_sources(20_000) == ("127.0.0.1",)
    assert loopback_sources(50_000) == ("127.0.0.1", "127.0.0.2", "127.0.0.3")
    with pytest.raises(ValueError, match=r"for 0 DTUs: must be at least 1"):
        loopback_sources(0)
    with pytest.raises(ValueError, match=r"sources: 'lo' is not an IP address"):
        DtuFleet("127.0.0.1", 9, 2, sources=["lo"])
    with pytest.raises(ValueError, match=r"sources: '::1' is IPv6, host '127.0.0.1' IPv4"):
        DtuFleet("127.0.0.1", 9, 2, sources=["::1"])
    with pytest.raises(ValueError, match=r"mark 16: must be a register address 0\.\.15"):
        DtuFleet("127.0.0.1", 9, 2, size=16, mark=16)
    with pytest.raises(ValueError, match=r"processes 0: must be an integer 1\.\.256"):
        FleetProcesses("127.0.0.1", 9, 2, processes=0)
    with pytest.raises(ValueError, match=r"3 DTUs in 4 processes"):
        FleetProcesses("127.0.0.1", 9, 3, processes=4)
    with pytest.raises(ValueError, match=r"registration: a template string"):
        FleetProcesses("127.0.0.1", 9, 3, processes=2, registration=lambda n: b"x")


def test_each_dtu_dials_from_its_source_address_and_holds_its_number() -> None:
    port = free_port()
    cfgs = [dtu_device(port, f"S{k}", 1, addresses=(0, 1)) for k in range(4)]
    fleet = DtuFleet("127.0.0.1", port, 4, registration="S{n}\r\n", size=16,
                     sources=("127.0.0.2", "127.0.0.3"), mark=1)
    with running(*cfgs), fleet:
        for cfg in cfgs:
            wait_for(ok(cfg), what=f"{cfg.organization.device_code} Ok")
        assert [values(cfg) for cfg in cfgs] == [[default_register(1, 0), k] for k in range(4)]
        held = dtu_registry.held()[f"127.0.0.1:{port}"]
        sources = {d["dtuId"]: str(d["peer"]).rsplit(":", 1)[0] for d in held}
        assert sources == {"S0": "127.0.0.2", "S1": "127.0.0.3", "S2": "127.0.0.2",
                           "S3": "127.0.0.3"}
        assert fleet.dtu(2).slave(1).get_registers(Area.HOLDING_REGISTER, 1, 1) == [2]


def test_a_fleet_in_two_processes_answers_for_every_dtu_and_stops_clean() -> None:
    port = free_port()
    cfgs = [dtu_device(port, f"P{k}", 1, addresses=(0, 2)) for k in range(5)]
    with running(*cfgs), FleetProcesses("127.0.0.1", port, 5, processes=2,
                                        registration="P{n}\r\n", size=16, mark=2) as fleet:
        assert fleet.shares == [(0, 3), (3, 2)]
        for cfg in cfgs:
            wait_for(ok(cfg), timeout=60, what=f"{cfg.organization.device_code} Ok")
        assert [values(cfg) for cfg in cfgs] == [[default_register(1, 0), k] for k in range(5)]
        stats = fleet.stats()
        assert stats["dtus"] == stats["connected"] == stats["connections"] == 5
        assert fleet.cpu_seconds() > 0
    # the leak check (tests/conftest.py) finds no child process, fd or thread left


N = 300


def test_the_whole_fleet_redials_at_once_and_every_value_comes_back() -> None:
    """300 DTUs on the loop engine, from two processes and two source addresses; all
    their connections reset at once (RST, as a network outage ends them), the DTUs
    redial within a second: every device reads its own DTU's number again through a
    new link within the deadline, and the listener turns none away."""
    port = free_port()
    cfgs = [dtu_device(port, f"M{k:03d}", 1, addresses=(0, 3), engine="loop",
                       readCycle=1000, readTimeout=1000, registrationTimeout=5000,
                       maxUnregistered=N, maxUnregisteredPerSource=N) for k in range(N)]
    fleet = FleetProcesses("127.0.0.1", port, N, processes=2, registration="M{n:03d}\r\n",
                           size=16, mark=3, reconnect=1.0, reconnect_max=4.0,
                           sources=("127.0.0.1", "127.0.0.2"))
    with running(*cfgs) as drivers, fleet:
        for cfg in cfgs:
            wait_for(ok(cfg), timeout=120, what=f"{cfg.organization.device_code} Ok")
        listener = dtu_registry.listener("127.0.0.1", port)
        assert listener is not None
        assert listener.stats["registered"] == N
        fleet.reset_all()
        reset_at = time.monotonic()
        # a second link for every DTU, then a reply through it
        wait_for(lambda: all(d.stats()["line"]["reconnects"] >= 1 for d in drivers),
                 timeout=60, what="every DTU's line up again")
        answered = [int(d.stats()["responses"]) for d in drivers]
        wait_for(lambda: all(int(d.stats()["responses"]) > n
                             for d, n in zip(drivers, answered, strict=True))
                 and all(ok(cfg)() for cfg in cfgs), timeout=60, what="every value Ok again")
        again = time.monotonic() - reset_at
        wrong = [cfg.organization.device_code for k, cfg in enumerate(cfgs)
                 if values(cfg) != [default_register(1, 0), k]]
        assert wrong == []
        stats = listener.stats
        assert stats["registered"] == stats["accepted"] == 2 * N
        assert {key: stats[key] for key in REFUSALS if stats[key]} == {}
        fleet_stats = fleet.stats()
        assert fleet_stats["connections"] == 2 * N and fleet_stats["dial_failures"] == 0
        print(f"\n{N} DTUs: every value Ok again {again:.1f} s after the reset")
