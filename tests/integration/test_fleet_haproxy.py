"""A dial-in fleet behind HAProxy (issue #28, docs/deploy.md): mosquitto, three gateway
instances (``python -m edgemodbus.gateway``, each ``EDGEMODBUS_INSTANCE``), HAProxy with
the config docs/deploy.md documents, and a fleet of simulated DTUs (``DtuFleet``, the
simulator behind ``edgemodbus simulate --dial ... --dtus N``), each DTU's slave with a
register value no other DTU has.  ``FLEET_DTUS`` sets the size (default 300).

On one machine every instance has its own folder, the same device files but for
``listenPort`` (on separate hosts the folder is one)."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.datatypes import Area
from edgemodbus.sim import DtuFleet
from tests.gateway_proc import GatewayProcess, scrape, write_json
from tests.haproxy import HAProxy, local_config
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import free_port
from tests.waiting import wait_for

DTUS = int(os.environ.get("FLEET_DTUS", "300"))
INSTANCES = ("gw-1", "gw-2", "gw-3")
P = "edgemodbus"
BASE = 1000  # DTU n's hr:0 holds BASE + n: a value from the wrong DTU shows


def dtu_id(n: int) -> str:
    return f"FL{n:06d}"  # 8 bytes: the documented hash of the first 8 bytes


def value_of(n: int) -> int:
    return (BASE + n) & 0xFFFF


def device(n: int, port: int) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": f"m{n}"},
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "registration": "text", "dtuId": dtu_id(n),
                          "registrationTimeout": 5000, "slaveId": 1, "readCycle": 1000,
                          "readTimeout": 1000, "reconnectInterval": 500},
        "addressList": [{"name": "v", "address": "hr:0", "deviceDataType": "UInt16"},
                        {"name": "w", "address": "hr:100", "deviceDataType": "UInt16"}],
    }


class Fleet:
    """The instances' folders, ports and processes."""

    def __init__(self, tmp: Path, broker: int) -> None:
        self.listen = {name: free_port() for name in INSTANCES}
        self.metrics = {name: free_port() for name in INSTANCES}
        self.dirs: dict[str, Path] = {}
        for name in INSTANCES:
            folder = tmp / name
            folder.mkdir()
            write_json(folder / "gateway.json", {
                "gatewayId": "fleet",
                "mqtt": {"port": broker, "reconnectMin": 100, "reconnectMax": 1000,
                         "statusCheckInterval": 200},
                "metrics": {"host": "127.0.0.1", "port": self.metrics[name]},
                "fleet": {"loadBalancers": ["127.0.0.1"]}})
            for n in range(DTUS):
                write_json(folder / f"m{n}.json", device(n, self.listen[name]))
            self.dirs[name] = folder
        self.procs: dict[str, GatewayProcess] = {}

    def start(self, stack: ExitStack, monkeypatch: pytest.MonkeyPatch) -> None:
        for name in INSTANCES:
            monkeypatch.setenv("EDGEMODBUS_INSTANCE", name)  # as the systemd unit's %i
            proc = GatewayProcess(self.dirs[name], self.dirs[name] / "gateway.log",
                                  nofile=4 * DTUS + 256)
            self.procs[name] = stack.enter_context(proc)
        monkeypatch.delenv("EDGEMODBUS_INSTANCE")
        for name, proc in self.procs.items():
            proc.wait_log(r"MQTT connected", timeout=60)
            wait_for(lambda name=name: held(self.metrics[name]) is not None, timeout=30,
                     what=f"{name}'s /metrics")

    def held_by(self) -> dict[str, int]:
        """edgemodbus_dtu_held of each live instance."""
        return {name: held(self.metrics[name]) or 0 for name, proc in self.procs.items()
                if proc.proc is not None and proc.proc.poll() is None}


def held(port: int) -> int | None:
    """The instance's edgemodbus_dtu_held, or None when /metrics does not answer."""
    try:
        text = scrape(port, timeout=5)
    except OSError:
        return None
    found = re.search(r'^edgemodbus_dtu_held\{instance="([^"]+)"\} (\S+)$', text, re.M)
    return int(float(found.group(2))) if found else None


class View:
    """The latest retained status and value of every device, from one subscriber."""

    def __init__(self, probe: MqttProbe) -> None:
        self.probe = probe

    def latest(self, after: int = 0) -> tuple[dict[int, dict[str, Any]],
                                              dict[int, dict[str, Any]]]:
        statuses: dict[int, dict[str, Any]] = {}
        values: dict[int, dict[str, Any]] = {}
        for m in self.probe.messages()[after:]:
            found = re.fullmatch(rf"{P}/m(\d+)/(\$status|v)", m.topic)
            if found:
                n = int(found.group(1))
                (statuses if found.group(2) == "$status" else values)[n] = m.json()
        return statuses, values

    def settled(self, devices: set[int], owners: set[str], after: int = 0) -> list[str]:
        """What is not right yet for ``devices`` (empty: every one is Running on one of
        ``owners`` with its exact value Ok)."""
        statuses, values = self.latest(after)
        wrong = []
        for n in sorted(devices):
            status, value = statuses.get(n, {}), values.get(n, {})
            if status.get("instance") not in owners or status.get("status") != "Running":
                wrong.append(f"m{n} status {status}")
            elif value.get("status") != "Ok" or value.get("value") != value_of(n):
                wrong.append(f"m{n} value {value}")
        return wrong


@pytest.fixture
def dtus() -> Iterator[list[int]]:
    yield list(range(DTUS))


def test_three_instances_behind_haproxy_and_the_failover_of_one(
        tmp_path: Path, broker: Mosquitto, monkeypatch: pytest.MonkeyPatch,
        dtus: list[int]) -> None:
    fleet = Fleet(tmp_path, broker.port)
    frontend = free_port()
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port, topics=(f"{P}/#",)))
        view = View(probe)
        fleet.start(stack, monkeypatch)
        config = local_config(frontend, [fleet.listen[name] for name in INSTANCES])
        stack.enter_context(HAProxy(config, tmp_path / "haproxy.cfg", frontend))
        sim = DtuFleet("127.0.0.1", frontend, DTUS, registration="FL{n:06d}", size=128,
                       reconnect=0.5, reconnect_max=2.0, dial_rate=100.0)
        for dtu in sim.dtus:
            dtu.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [value_of(dtu.number)])
        stack.enter_context(sim)

        # every DTU held by exactly one instance, every value Ok and exact
        everyone = set(INSTANCES)
        wait_for(lambda: not view.settled(set(dtus), everyone), timeout=90,
                 what=f"all {DTUS} DTUs Running with their values "
                      f"({view.settled(set(dtus), everyone)[:5]})")
        wait_for(lambda: sum(fleet.held_by().values()) == DTUS, timeout=30,
                 what=f"edgemodbus_dtu_held summing to {DTUS} ({fleet.held_by()})")
        counts = fleet.held_by()
        statuses, _ = view.latest()
        named = {name: sum(1 for s in statuses.values() if s["instance"] == name)
                 for name in INSTANCES}
        assert named == counts, (named, counts)  # the statuses agree with the gauges
        even = DTUS / len(INSTANCES)
        assert all(abs(c - even) <= 0.2 * even for c in counts.values()), counts
        assert sim.stats()["connected"] == DTUS

        # kill -9 of one instance: its DTUs redial and are Ok on the other two
        victim = max(counts, key=lambda name: counts[name])
        moved = {n for n, s in statuses.items() if s["instance"] == victim}
        mark = probe.mark()
        killed_at = time.monotonic()
        os.kill(fleet.procs[victim].pid, signal.SIGKILL)
        fleet.procs[victim].proc.wait()  # type: ignore[union-attr]
        survivors = everyone - {victim}
        wait_for(lambda: not view.settled(moved, survivors, after=mark), timeout=30,
                 what=f"{len(moved)} DTUs of {victim} Ok on {sorted(survivors)} "
                      f"({view.settled(moved, survivors, after=mark)[:5]})")
        took = time.monotonic() - killed_at
        wait_for(lambda: sum(fleet.held_by().values()) == DTUS, timeout=30,
                 what=f"the survivors holding all {DTUS} ({fleet.held_by()})")
        _, values = view.latest(mark)
        assert all(v["value"] == value_of(n) for n, v in values.items() if "value" in v)
        latest, _ = view.latest()
        assert all(latest[n]["instance"] in survivors for n in moved)  # retained: holders

        # a per-item write to a moved DTU reaches its slave through its new holder
        n = min(moved)
        reply_mark = probe.mark()
        probe.publish(f"{P}/m{n}/set/w", json.dumps({"value": 4242, "id": "moved"}))
        reply = probe.wait_for(f"{P}/m{n}/$reply", lambda m: m.json()["id"] == "moved",
                               timeout=15, after=reply_mark).json()
        assert reply["ok"] is True, reply
        assert sim.dtu(n).slave(1).get_registers(Area.HOLDING_REGISTER, 100, 1) == [4242]
        print(f"\n{DTUS} DTUs: spread {counts}; {len(moved)} moved in {took:.1f} s")
