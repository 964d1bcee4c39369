"""Sparkplug B in a dial-in fleet behind HAProxy (issue #28, docs/deploy.md): mosquitto,
three gateway instances in Sparkplug mode (each ``EDGEMODBUS_INSTANCE``, so each its own
edge node ``fleet-<instance>``), HAProxy with the documented config and a few simulated
DTUs (``DtuFleet``), each DTU's slave with a value no other has.  A Sparkplug host probe
(tests/sparkplug_wire.py reads the payloads) checks that each device is born by the one
node holding its DTU, that a kill -9 is seen as that node's NDEATH (its will, with its
NBIRTH's bdSeq) followed by the moved devices' DBIRTHs from the survivors, and that a
DCMD to a moved device reaches its slave.  ``SPARKPLUG_FLEET_DTUS`` sets the size."""

from __future__ import annotations

import os
import signal
import time
from contextlib import ExitStack
from pathlib import Path

from edgemodbus.datatypes import Area
from edgemodbus.sim import DtuFleet
from tests.fleet_gateways import INSTANCES, Fleet, held, paced, value_of
from tests.haproxy import HAProxy, local_config
from tests.mosquitto import Mosquitto, MqttProbe, Received
from tests.peers import free_port
from tests.sparkplug_wire import decode, encode, encode_metric
from tests.waiting import wait_for

DTUS = int(os.environ.get("SPARKPLUG_FLEET_DTUS", "12"))
G = "plant1"
BASE = f"spBv1.0/{G}"
NODES = {f"fleet-{name}": name for name in INSTANCES}  # edge node id -> instance


class Host:
    """What a Sparkplug host makes of the messages so far: the node each device is
    born on now (its DBIRTH not followed by its DDEATH or the node's NDEATH)."""

    def __init__(self, probe: MqttProbe) -> None:
        self.probe = probe

    def born(self, after: int = 0) -> dict[int, tuple[str, int | None]]:
        """Device number -> (node, the value of its ``v`` in that DBIRTH)."""
        where: dict[int, tuple[str, int | None]] = {}
        for m in self.probe.messages()[after:]:
            parts = m.topic.split("/")
            kind, node = parts[2], parts[3]
            if kind == "NDEATH":
                where = {n: b for n, b in where.items() if b[0] != node}
            elif kind in ("DBIRTH", "DDEATH"):
                n = int(parts[4].removeprefix("m"))
                if kind == "DBIRTH":
                    where[n] = (node, decode(m.payload).by_name()["v"].value)
                elif where.get(n, ("",))[0] == node:
                    del where[n]
        return where

    def wrong(self, devices: set[int], nodes: set[str], after: int = 0) -> list[str]:
        """What is not right yet (empty: each device born on one of ``nodes`` with its
        own value)."""
        born = self.born(after)
        return [f"m{n}: {born.get(n)}" for n in sorted(devices)
                if born.get(n, ("", None))[0] not in nodes or born[n][1] != value_of(n)]


def test_sparkplug_nodes_of_a_fleet_behind_haproxy(tmp_path: Path, broker: Mosquitto) -> None:
    fleet = Fleet(tmp_path, broker.port, DTUS,
                  mqtt={"mode": "sparkplug", "sparkplug": {"groupId": G}})
    listen, metrics, frontend = fleet.listen, fleet.metrics, free_port()
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port, topics=(f"{BASE}/#",)))
        host = Host(probe)
        fleet.start(stack, ready=rf"edge node {G}/\S+ connected")
        procs = fleet.procs
        bd_seq = {}
        for node in NODES:
            nbirth = decode(probe.wait_for(f"{BASE}/NBIRTH/{node}", timeout=30).payload)
            bd_seq[node] = nbirth.by_name()["bdSeq"].value
        config = local_config(frontend, [listen[name] for name in INSTANCES])
        stack.enter_context(HAProxy(config, tmp_path / "haproxy.cfg", frontend))
        sim = DtuFleet("127.0.0.1", frontend, DTUS, registration="FL{n:06d}", size=128,
                       reconnect=0.5, reconnect_max=2.0, dial_rate=fleet.timing.dial_rate)
        for dtu in sim.dtus:
            dtu.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [value_of(dtu.number)])
        stack.enter_context(sim)

        # each device born by exactly the node holding its DTU, with its own value
        everyone, dtus = set(NODES), set(range(DTUS))
        wait_for(lambda: not host.wrong(dtus, everyone), timeout=90,
                 what=f"every device born on one node ({host.wrong(dtus, everyone)[:5]})")

        def gauges() -> dict[str, int]:
            return {node: held(metrics[name]) or 0 for node, name in NODES.items()
                    if procs[name].alive()}

        wait_for(paced(lambda: sum(gauges().values()) == DTUS), timeout=30,
                 what=f"edgemodbus_dtu_held summing to {DTUS} ({gauges()})")
        born = host.born()
        per_node = {node: sum(1 for b in born.values() if b[0] == node) for node in NODES}
        assert per_node == gauges(), (per_node, gauges())  # born where held, nowhere else
        births = [m for m in probe.messages() if "/DBIRTH/" in m.topic]
        assert len(births) == DTUS, [m.topic for m in births]  # no device born twice

        # kill -9: the node's will (NDEATH, its bdSeq), then DBIRTHs from the survivors
        victim = max(per_node, key=lambda node: (per_node[node], node))
        moved = {n for n, b in born.items() if b[0] == victim}
        mark = probe.mark()
        killed_at = time.monotonic()
        os.kill(procs[NODES[victim]].pid, signal.SIGKILL)
        procs[NODES[victim]].wait()
        death = probe.wait_for(f"{BASE}/NDEATH/{victim}", timeout=30, after=mark)
        assert decode(death.payload).by_name()["bdSeq"].value == bd_seq[victim]
        survivors = everyone - {victim}
        wait_for(lambda: not host.wrong(moved, survivors, after=mark), timeout=30,
                 what=f"{len(moved)} devices of {victim} born on {sorted(survivors)} "
                      f"({host.wrong(moved, survivors, after=mark)[:5]})")
        took = time.monotonic() - killed_at
        after: list[Received] = probe.messages()[mark:]
        first_birth = next(i for i, m in enumerate(after) if "/DBIRTH/" in m.topic)
        assert after.index(death) < first_birth  # the host sees the node die first
        assert not any(m.topic.split("/")[3] == victim for m in after
                       if "/NDEATH/" not in m.topic), "the killed node spoke after its death"
        wait_for(paced(lambda: sum(gauges().values()) == DTUS), timeout=30,
                 what=f"the survivors holding all {DTUS} ({gauges()})")

        # a DCMD to a moved device, sent to its new node, lands on its slave
        n = min(moved)
        node = host.born()[n][0]
        probe.publish(f"{BASE}/DCMD/{node}/m{n}", encode(
            [encode_metric(name="w", datatype="UInt16", value=4242)],
            int(time.time() * 1000)))
        wait_for(lambda: sim.dtu(n).slave(1).get_registers(
            Area.HOLDING_REGISTER, 100, 1) == [4242], timeout=15, what="the DCMD's write")
        print(f"\n{DTUS} DTUs: spread {per_node}; {len(moved)} moved in {took:.1f} s")
