"""Sparkplug B in a dial-in fleet (docs/deploy.md): each instance is its own edge node
and births a listen-mode device only while it holds its DTU.  Here two publishers
(instances A and B, one gateway id) each run a driver of dev1 polling one pymodbus
slave; which instance holds the device is a flag (in the gateway it is its DTU's
connection, gateway/fleet.py; tests/integration/test_sparkplug_haproxy.py runs real
gateways).  Payloads are read by tests/sparkplug_wire.py (not our encoder)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import ExitStack

import pytest

import edgemodbus as em
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher
from edgemodbus.northbound.sparkplug.settings import node_id_for
from tests.integration.test_metrics import scrape
from tests.integration.test_sparkplug import BASE, G, device, wait_payload
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.sparkplug_wire import encode, encode_metric
from tests.waiting import wait_for


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200) as peer:
        yield peer


class Instance:
    """One fleet instance: a Sparkplug publisher (instance ``name``) and a driver of dev1."""

    def __init__(self, stack: ExitStack, broker: int, port: int, name: str) -> None:
        cfg = device(port)
        self.holds = False
        self.pub = SparkplugPublisher(
            {"mode": "sparkplug", "port": broker, "statusCheckInterval": 100,
             "reconnectMin": 100, "reconnectMax": 400, "sparkplug": {"groupId": G}},
            gateway_id="gw1", instance=name)
        self.drv = em.DriverModbusRtu()
        self.pub.start()
        stack.callback(self.pub.stop)
        self.pub.attach(self.drv, "dev1", held=lambda: self.holds)
        assert self.drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        stack.callback(self.drv.stop_device)
        self.node = self.pub.node_id

    def topic(self, kind: str) -> str:
        return f"{BASE}/{kind}/{self.node}/dev1"

    def stats(self, key: str) -> int:
        return int(self.pub.stats()[key])


def test_node_ids_name_the_instance() -> None:
    assert node_id_for(None, "gw1", "A") == "gw1-A"
    assert node_id_for("edge", "gw1", "A") == "edge-A"
    assert node_id_for("site.{instance}.edge", "gw1", "gw-2") == "site.gw-2.edge"
    assert node_id_for("edge", "gw1", None) == "edge"
    with pytest.raises(ValueError, match=r"mqtt\.sparkplug\.edgeNodeId 'edge-\{instance\}' "
                                         r"names \{instance\}, but this gateway is not in"):
        node_id_for("edge-{instance}", "gw1", None)
    with pytest.raises(ValueError, match="instanceId"):
        SparkplugPublisher({"mode": "sparkplug", "sparkplug": {"groupId": G}},
                           gateway_id="gw1", instance="a/b")


def test_dbirth_on_arrival_ddeath_on_departure_dcmd_only_where_held(
        broker: Mosquitto, slave: PymodbusSlave) -> None:
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port, [f"{BASE}/#"]))
        a = Instance(stack, broker.port, slave.port, "A")
        b = Instance(stack, broker.port, slave.port, "B")
        assert (a.node, b.node) == ("gw1-A", "gw1-B")
        for inst in (a, b):
            probe.wait_for(f"{BASE}/NBIRTH/{inst.node}")
            wait_for(lambda inst=inst: inst.drv.stats().get("cycles", 0) > 0,
                     what="a complete poll cycle")

        # A holds it: DBIRTH from A's node only
        mark = probe.mark()
        a.holds = True
        born = wait_payload(probe, a.topic("DBIRTH"), after=mark)
        sp = born.by_name()["sp"]

        # it leaves A (the DTU hung up) and arrives at B
        mark = probe.mark()
        a.holds = False
        wait_payload(probe, a.topic("DDEATH"), after=mark)
        assert not a.pub.stats()["devices"]["dev1"]["held"]
        b.holds = True
        born_b = wait_payload(probe, b.topic("DBIRTH"), after=mark)
        sp_b = born_b.by_name()["sp"]

        # a DCMD to the node that let it go is ignored and counted ...
        stamp = int(time.time() * 1000)
        probe.publish(f"{BASE}/DCMD/{a.node}/dev1", encode(
            [encode_metric(alias=sp.alias, datatype="UInt16", value=111)], stamp))
        wait_for(lambda: a.stats("commandsNotHeld") == 1, what="A's refusal counted")
        assert a.stats("writes") == 0
        exporter = stack.enter_context(MetricsExporter({"port": 0}))
        exporter.set_publisher(a.pub)
        _, samples = scrape(exporter.port)
        assert samples[("edgemodbus_sparkplug_commands_not_held_total", ())] == 1
        # ... and one to its holder lands on the slave
        probe.publish(f"{BASE}/DCMD/{b.node}/dev1", encode(
            [encode_metric(alias=sp_b.alias, datatype="UInt16", value=777)], stamp))
        wait_for(lambda: slave.registers(1, "hr", 100) == [777], what="B's write")
        assert b.stats("commandsNotHeld") == 0

        # no DBIRTH of a device an instance did not hold; DDATA only from its holder
        order = [m.topic for m in probe.messages()
                 if m.topic.endswith("/dev1") and "/DCMD/" not in m.topic]
        left, arrived = order.index(a.topic("DDEATH")), order.index(b.topic("DBIRTH"))
        assert order[0] == a.topic("DBIRTH"), order
        assert all(t == a.topic("DDATA") for t in order[1:left]), order
        assert all(t == a.topic("DDEATH") for t in order[left:arrived]), order
        assert all(t == b.topic("DDATA") for t in order[arrived + 1:]), order
