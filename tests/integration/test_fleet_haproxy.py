"""A dial-in fleet behind HAProxy (docs/deploy.md): mosquitto, three gateway instances
(tests/fleet_gateways.py: ``python -m edgemodbus.gateway``, each ``EDGEMODBUS_INSTANCE``),
HAProxy with the config docs/deploy.md documents, and a fleet of simulated DTUs
(``DtuFleet``, the simulator behind ``edgemodbus simulate --dial ... --dtus N``), each
DTU's slave with a register value no other DTU has.  The instances publish per item at
QoS 1 with store-and-forward, as docs/deploy.md advises for a fleet.  ``FLEET_DTUS`` sets
the size (default 300; ``make soak-fleet``: 3,000), ``FLEET_ENGINE`` the listen-mode
engine (default: the gateway's)."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from edgemodbus.datatypes import Area
from edgemodbus.sim import DtuFleet
from tests.fleet_gateways import INSTANCES, Fleet, fleet_engine, metric, paced, value_of
from tests.gateway_proc import scrape
from tests.haproxy import HAProxy, local_config
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import free_port
from tests.waiting import wait_for

DTUS = int(os.environ.get("FLEET_DTUS", "300"))
P = "edgemodbus"
ITEM_TOPIC = re.compile(rf"{P}/m(\d+)/([a-z]\w*)")  # an item's update (not $status, set/)
FAILOVER_S = 30  # the bound: the killed instance's DTUs Ok elsewhere within it


def settle(cond: Callable[[], object], timeout: float, what: Callable[[], str]) -> None:
    """wait_for, ``cond`` tried twice a second (it reads every message so far, or the
    instances' /metrics: the test process also runs the simulated fleet), saying at the
    deadline what is still wrong *then* (``what`` is called at the end)."""
    try:
        wait_for(paced(cond), timeout=timeout)
    except AssertionError:
        raise AssertionError(f"timed out after {timeout:.0f} s: {what()}") from None


class View:
    """What one subscriber saw: every device's latest status and value, who published
    its statuses, and how many item updates arrived per device."""

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

    def report(self, devices: set[int], owners: set[str], after: int = 0) -> str:
        wrong = self.settled(devices, owners, after)
        return f"{len(wrong)} of {len(devices)} not Ok on {sorted(owners)}: {wrong[:5]}"

    def holders(self, after: int = 0) -> dict[int, set[str]]:
        """Every instance that published a status of each device."""
        seen: dict[int, set[str]] = {}
        for m in self.probe.messages()[after:]:
            found = re.fullmatch(rf"{P}/m(\d+)/\$status", m.topic)
            if found and m.payload:
                seen.setdefault(int(found.group(1)), set()).add(m.json().get("instance", ""))
        return seen

    def updates(self, after: int = 0) -> Counter[int]:
        """Item updates that arrived per device."""
        counts: Counter[int] = Counter()
        for m in self.probe.messages()[after:]:
            found = ITEM_TOPIC.fullmatch(m.topic)
            if found:
                counts[int(found.group(1))] += 1
        return counts


def published(port: int) -> dict[str, float]:
    """An instance's MQTT counters: ``published`` per device code, and its spool's."""
    text = scrape(port, timeout=10)
    out = {f"m{code}": float(v) for code, v in re.findall(
        r'^edgemodbus_mqtt_published_total\{device="m(\d+)"\} (\S+)$', text, re.M)}
    for key in ("mqtt_spool_inflight", "mqtt_spool_pending", "mqtt_spool_acked_total",
                "mqtt_connects_total"):
        out[key] = metric(text, f"edgemodbus_{key}") or 0.0
    return out


@contextmanager
def ticking(sim: DtuFleet, dtus: list[int], period: float = 0.25) -> Iterator[None]:
    """Item ``c`` (hr:1) of ``dtus`` counts up every ``period`` while inside, so their
    holders publish all along (a stream to lose or not)."""
    stop = threading.Event()

    def run() -> None:
        tick = 0
        while not stop.wait(period):
            tick += 1
            for n in dtus:
                sim.dtu(n).slave(1).set_registers(Area.HOLDING_REGISTER, 1, [tick & 0xFFFF])

    thread = threading.Thread(target=run, name="ticker", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(10)


def lost_acknowledged(view: View, fleet: Fleet, survivors: set[str], moved: set[int],
                      mark: int) -> list[str]:
    """The survivors' acknowledged item updates that did not reach the subscriber
    (empty: none).  A survivor's update of a device counts as acknowledged once its
    spool has nothing pending or in flight (each QoS 1 update is spooled before paho
    takes it and deleted at its PUBACK: docs/gateway.md, "Store and forward").  Each
    device is attributed to the one survivor that published its statuses: a device it
    held from the start has all its updates from it; a moved one, its updates since the
    kill (``mark``; the killed instance's last ones may arrive after it, so at least)."""
    counters = {name: published(fleet.metrics[name]) for name in survivors}
    wrong = [f"{name}: spool {c['mqtt_spool_pending']:.0f} pending, "
             f"{c['mqtt_spool_inflight']:.0f} in flight"
             for name, c in counters.items()
             if c["mqtt_spool_pending"] or c["mqtt_spool_inflight"]]
    total, since = view.updates(), view.updates(mark)
    for n, owners in sorted(view.holders().items()):
        holder = owners & survivors
        if len(holder) != 1:
            continue  # held by the killed instance only (none left) or checked elsewhere
        name = holder.pop()
        sent = counters[name].get(f"m{n}", 0.0)
        if n in moved:
            got = since[n]
            if got < sent:
                wrong.append(f"m{n} (moved to {name}): {name} published {sent:.0f} "
                             f"since, {got} arrived")
        else:
            got = total[n]
            reconnected = counters[name]["mqtt_connects_total"] > 1
            if got < sent or (got != sent and not reconnected):  # duplicates: only resent
                wrong.append(f"m{n} ({name} only): {name} published {sent:.0f}, "
                             f"{got} arrived")
    return wrong


def test_three_instances_behind_haproxy_and_the_failover_of_one(
        tmp_path: Path, broker: Mosquitto) -> None:
    fleet = Fleet(tmp_path, broker.port, DTUS, extra_items=1, engine=fleet_engine(),
                  mqtt={"qos": 1, "storeAndForward": {"path": "spool.db"}})
    timing = fleet.timing
    frontend = free_port()
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port, topics=(f"{P}/#",)))
        view = View(probe)
        started = time.monotonic()
        fleet.start(stack)
        loaded_s = time.monotonic() - started
        config = local_config(frontend, [fleet.listen[name] for name in INSTANCES])
        stack.enter_context(HAProxy(config, tmp_path / "haproxy.cfg", frontend))
        sim = DtuFleet("127.0.0.1", frontend, DTUS, registration="FL{n:06d}", size=128,
                       reconnect=0.5, reconnect_max=2.0, dial_rate=timing.dial_rate)
        for dtu in sim.dtus:
            dtu.slave(1).set_registers(Area.HOLDING_REGISTER, 0, [value_of(dtu.number)])
        dialled = time.monotonic()
        stack.enter_context(sim)

        # every DTU held by exactly one instance, every value Ok and exact
        everyone, dtus = set(INSTANCES), set(range(DTUS))
        settle(lambda: not view.settled(dtus, everyone), timing.settle_timeout,
               lambda: view.report(dtus, everyone))
        settled_s = time.monotonic() - dialled
        settle(lambda: sum(fleet.held_by().values()) == DTUS, 30,
               lambda: f"edgemodbus_dtu_held summing to {DTUS} ({fleet.held_by()})")
        counts = fleet.held_by()
        statuses, _ = view.latest()
        named = {name: sum(1 for s in statuses.values() if s["instance"] == name)
                 for name in INSTANCES}
        assert named == counts, (named, counts)  # the statuses agree with the gauges
        assert all(len(owners) == 1 for owners in view.holders().values()), \
            "a DTU held by two instances"
        even = DTUS / len(INSTANCES)
        assert all(abs(c - even) <= 0.2 * even for c in counts.values()), counts
        assert sim.stats()["connected"] == DTUS

        # kill -9 of one instance: its DTUs redial and are Ok on the other two, while
        # the counter items of 30 DTUs spread over the fleet make their holders publish
        victim = max(counts, key=lambda name: counts[name])
        moved = {n for n, s in statuses.items() if s["instance"] == victim}
        survivors = everyone - {victim}
        ticked = sorted(range(0, DTUS, max(1, DTUS // 30)))
        with ticking(sim, ticked):
            wait_for(lambda: view.updates().keys() >= set(ticked), timeout=30,
                     what="the ticking devices' first updates")
            mark = probe.mark()
            killed_at = time.monotonic()
            os.kill(fleet.procs[victim].pid, signal.SIGKILL)
            fleet.procs[victim].wait()
            settle(lambda: not view.settled(moved, survivors, after=mark), FAILOVER_S,
                   lambda: view.report(moved, survivors, after=mark))
            took = time.monotonic() - killed_at
            settle(lambda: sum(fleet.held_by().values()) == DTUS, 30,
                   lambda: f"the survivors holding all {DTUS} ({fleet.held_by()})")
            during = view.updates(mark)
        assert all(during[n] > 0 for n in ticked), "a ticking device fell silent"
        _, values = view.latest(mark)
        assert all(v["value"] == value_of(n) for n, v in values.items() if "value" in v)
        latest, _ = view.latest()
        assert all(latest[n]["instance"] in survivors for n in moved)  # retained: holders
        assert all(len(owners - {victim}) == 1 for owners in view.holders().values()), \
            "a DTU held by two survivors"

        # the survivors lost no acknowledged update (QoS 1 through the spool)
        settle(lambda: not lost_acknowledged(view, fleet, survivors, moved, mark), 60,
               lambda: "; ".join(lost_acknowledged(view, fleet, survivors, moved,
                                                   mark)[:8]))

        # a per-item write to a moved DTU reaches its slave through its new holder
        n = min(moved)
        reply_mark = probe.mark()
        probe.publish(f"{P}/m{n}/set/w", json.dumps({"value": 4242, "id": "moved"}))
        reply = probe.wait_for(f"{P}/m{n}/$reply", lambda m: m.json()["id"] == "moved",
                               timeout=15, after=reply_mark).json()
        assert reply["ok"] is True, reply
        assert sim.dtu(n).slave(1).get_registers(Area.HOLDING_REGISTER, 100, 1) == [4242]
        print(f"\n{DTUS} DTUs: instances loaded in {loaded_s:.0f} s, all Ok "
              f"{settled_s:.0f} s after the first dial; spread {counts}; {len(moved)} "
              f"moved, Ok on the others {took:.1f} s after the kill -9; "
              f"{sum(during.values())} updates during the failover")
