"""Cases of `make soak-gateway` for the loop engine (docs/scale.md): the floods of the
line-scheduling row against DTUs that dial in, several DTU lines on one loop thread.
The DTUs are the fleet simulator in a child process (sim/fleet_procs.py), each with
slaves 1 and 2 (7 answers nothing: a dead slave); every DTU's slave 1 is a bystander,
polled every 100 ms; DTU 0's slave 2 is the masters' target, beside its bystander.  The
bystanders' rate is the polls the gateway counts answered (/metrics: the simulator
counts requests per fleet, not per slave)."""

from __future__ import annotations

import os
import sys
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests.peers import free_port
from tools.soak_cases_line import dead_flood, forward_flood, write_flood
from tools.soak_cases_north import dcmd_storm, sparkplug_broker
from tools.soak_gw_base import (
    FLOOD_RATE,
    Case,
    Prep,
    Run,
    answered,
    served_and_scraped,
)

from edgemodbus.line.loop_jobs import JOB_THREADS
from edgemodbus.sim.fleet_procs import FleetProcesses

DTUS = 6
FORWARD_UNIT, WRITE_UNIT, DEAD_UNIT = 20, 21, 22


def dtu_device(port: int, n: int, slave: int, code: str, read_cycle: int,
               **comm: Any) -> dict[str, Any]:
    """Slave ``slave`` behind DTU ``n``, which dials listen port ``port`` (engine auto:
    the loop; one loop thread for every line)."""
    return {
        "organization": {"deviceCode": code},
        "communication": {
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "registration": "text", "dtuId": f"LP{n:06d}",
            "registrationTimeout": 5000, "slaveId": slave, "readCycle": read_cycle,
            "readTimeout": 1000, "reconnectInterval": 500, "loopThreads": 1, **comm},
        "addressList": [{"name": f"t{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"}
                        for i in range(3)],
    }


def loop_prep(prep: Prep) -> None:
    port = free_port()
    for n in range(DTUS):
        prep.devices[f"l{n}"] = dtu_device(port, n, 1, f"l{n}", 100)
    prep.devices["lf"] = dtu_device(port, 0, 2, "lf", 1000)
    prep.devices["ld"] = dtu_device(port, 0, 7, "ld", 1000, readTimeout=700)
    prep.gateway["serve"] = {"units": [
        {"unitId": FORWARD_UNIT, "forward": "lf"}, {"unitId": WRITE_UNIT, "device": "lf"},
        {"unitId": DEAD_UNIT, "forward": "ld", "timeoutMs": 700}]}
    prep.bystanders = tuple(f"l{n}" for n in range(DTUS))
    prep.stack.enter_context(FleetProcesses(
        "127.0.0.1", port, DTUS, processes=1, registration="LP{n:06d}", slaves=(1, 2),
        size=200, reconnect=0.5, reconnect_max=2.0))


def loop_sparkplug_prep(prep: Prep) -> None:
    loop_prep(prep)
    sparkplug_broker(prep, own=False)


def all_polled(run: Run) -> bool:
    """Every bystander DTU answered, and the dead slave is Offline (its probes, not its
    first timeouts, are in the quiet window)."""
    return bool(run.gw.lines(r"ld: \w+ -> Offline")) and all(
        run.gw.lines(rf"l{n}: \w+ -> Running") for n in range(DTUS))


def loop_case(name: str, row: str, attack: Any, prep: Any = loop_prep,
              log_kinds: int = 0) -> Case:
    return Case(name, row, attack, served_and_scraped, prep=prep, ready=all_polled,
                polled=answered, min_rate=FLOOD_RATE, max_thread_cpu=1.0,
                log_kinds=log_kinds, extra_threads=JOB_THREADS)  # a job flood's threads


def loop_cases() -> list[Case]:
    where = f" ({DTUS} DTUs dialled in, one loop thread)"
    return [
        loop_case("loop-forward-loop", "loop engine: two masters forwarding in a closed "
                  "loop to a slave behind a DTU" + where, forward_flood(FORWARD_UNIT)),
        loop_case("loop-fc06-flood", "loop engine: two masters writing FC06 to a served "
                  "unit behind a DTU" + where, write_flood(WRITE_UNIT)),
        loop_case("loop-dead-forward", "loop engine: one master forwarding back-to-back "
                  "to a dead slave behind a DTU (timeout 0.7 s)" + where,
                  dead_flood(DEAD_UNIT)),
        loop_case("loop-dcmd-storm", "loop engine: a Sparkplug DCMD storm to a slave "
                  "behind a DTU" + where, dcmd_storm("lf"), loop_sparkplug_prep,
                  log_kinds=3),  # writes confirmed, refused (line busy), polling delayed
    ]
