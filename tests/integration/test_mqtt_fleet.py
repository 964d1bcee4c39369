"""A device in a dial-in fleet (northbound/mqtt/holding.py): two publishers of one
gateway id, instances A and B, each with its own driver of device dev1 (both polling one
pymodbus slave); which instance holds the device is a flag here (in the gateway it is
its DTU's connection, gateway/fleet.py).  Only the holder publishes the device and
takes its commands; the retained status ends up naming the holder whatever the order
of arrival and departure."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.northbound.mqtt import MqttPublisher
from tests.integration.test_mqtt import P, device
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

STATUS = f"{P}/dev1/$status"


class Instance:
    """One fleet instance: a publisher (instance ``name``) and a driver of dev1."""

    def __init__(self, stack: ExitStack, broker: int, port: int, name: str,
                 mode: str = "per-item") -> None:
        cfg = device(port)  # items of its own
        self.name = name
        self._holds = False
        self.pub = MqttPublisher({"port": broker, "reconnectMin": 100, "reconnectMax": 400,
                                  "statusCheckInterval": 100, "mode": mode},
                                 gateway_id="gw1", instance=name)
        self.drv = em.DriverModbusRtu()
        self.pub.start()
        stack.callback(self.pub.stop)
        self.pub.attach(self.drv, "dev1", held=lambda: self._holds)
        assert self.drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        stack.callback(self.drv.stop_device)
        assert self.pub.wait_connected(10)

    @property
    def holds(self) -> bool:
        return self._holds

    @holds.setter
    def holds(self, value: bool) -> None:
        """As the gateway's DTU arrives (its reads report, or held_changed); a departure
        is seen at the publisher's next look at the devices it holds."""
        self._holds = value
        if value:
            self.pub.held_changed(self.drv)

    def stats(self, key: str) -> int:
        return int(self.pub.stats()[key])

    def published(self) -> int:
        return int(self.pub.stats()["devices"]["dev1"]["published"])


def retained(port: int) -> dict[str, Any]:
    """The retained status of dev1, as a subscriber that comes now reads it."""
    with MqttProbe(port, topics=(STATUS,)) as late:
        body: dict[str, Any] = late.wait_for(STATUS).json()
        return body


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200) as peer:
        yield peer


def write(probe: MqttProbe, value: int, request: str) -> dict[str, Any]:
    mark = probe.mark()
    probe.publish(f"{P}/dev1/set/sp", json.dumps({"value": value, "id": request}))
    body: dict[str, Any] = probe.wait_for(f"{P}/dev1/$reply",
                                          lambda m: m.json()["id"] == request,
                                          after=mark).json()
    return body


def test_only_the_holder_publishes_and_takes_commands(broker: Mosquitto,
                                                      slave: PymodbusSlave) -> None:
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port))
        a = Instance(stack, broker.port, slave.port, "A")
        b = Instance(stack, broker.port, slave.port, "B")
        a.holds = True
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "A")
        slave.set_registers(1, "hr", 0, [777])  # both drivers read it; A alone publishes
        probe.wait_for(f"{P}/dev1/t0", lambda m: m.json()["value"] == 777)
        wait_for(lambda: b.drv.snapshot()["items"]["t0"]["value"] == 777, what="B read it")
        assert write(probe, 1234, "w1")["ok"] is True
        assert slave.registers(1, "hr", 100) == [1234]
        assert (a.stats("commands"), b.stats("commands")) == (1, 0)
        assert b.published() == 0 and not any(
            m.json().get("instance") == "B" for m in probe.on(STATUS))

        # the device moves: A notices first, then B registers it
        a.holds = False
        probe.wait_for(STATUS, lambda m: m.json() == {**m.json(), "instance": "A",
                                                      "status": "NotHere"})
        b.holds = True
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "B"
                       and m.json()["status"] != "NotHere")
        assert write(probe, 4321, "w2")["ok"] is True
        assert slave.registers(1, "hr", 100) == [4321]
        assert (a.stats("commands"), b.stats("commands")) == (1, 1)  # the write followed
        assert retained(broker.port)["instance"] == "B"


def test_a_late_departure_never_overwrites_the_new_holder(broker: Mosquitto,
                                                         slave: PymodbusSlave) -> None:
    """B registers the DTU before A notices it left: A stays silent, and the retained
    status names B; when B lets it go too, B's "NotHere" stands."""
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port))
        a = Instance(stack, broker.port, slave.port, "A")
        b = Instance(stack, broker.port, slave.port, "B")
        a.holds = True
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "A")
        assert a.pub.stats()["devices"]["dev1"]["held"] is True
        b.holds = True  # both think they hold it for a moment (A's TCP has not noticed)
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "B")
        # "late": A notices after B's claim reached it (before, A cannot know of B, and
        # its "NotHere" is answered by B: test_a_departure_before_the_new_claim_...)
        wait_for(lambda: a.pub.stats()["devices"]["dev1"]["retainedHolder"] == "B",
                 what="A read back B's status")
        a.holds = False
        wait_for(lambda: a.pub.stats()["devices"]["dev1"]["held"] is False,
                 what="A saw the departure")
        body = retained(broker.port)
        assert (body["instance"], body["status"]) != ("A", "NotHere")
        assert body["instance"] == "B"
        said = [m.json() for m in probe.on(STATUS) if m.json().get("status") == "NotHere"]
        assert not said, said
        b.holds = False
        probe.wait_for(STATUS, lambda m: m.json().get("status") == "NotHere")
        assert retained(broker.port)["instance"] == "B"


def test_a_departure_before_the_new_claim_arrived_is_answered_by_the_holder(
        broker: Mosquitto, slave: PymodbusSlave) -> None:
    """A leaves before B's status reached it (A cannot know of B): A's "NotHere" may go
    out, and B, which holds the device, answers it with its own status (holding.py)."""
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port))
        a = Instance(stack, broker.port, slave.port, "A")
        a.holds = True
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "A")
        b = Instance(stack, broker.port, slave.port, "B")
        b.holds = True
        a.holds = False  # at once: A's look may come before B's status reaches it
        wait_for(lambda: a.pub.stats()["devices"]["dev1"]["held"] is False,
                 what="A saw the departure")
        wait_for(lambda: b.pub.stats()["devices"]["dev1"]["held"] is True,
                 what="B saw the arrival")
        wait_for(lambda: (retained(broker.port)["instance"] == "B"
                          and retained(broker.port)["status"] != "NotHere"),
                 what="the retained status names B, holding it")


def test_batch_mode_publishes_the_held_device_only(broker: Mosquitto,
                                                   slave: PymodbusSlave) -> None:
    with ExitStack() as stack:
        probe = stack.enter_context(MqttProbe(broker.port))
        a = Instance(stack, broker.port, slave.port, "A", mode="batch")
        b = Instance(stack, broker.port, slave.port, "B", mode="batch")
        b.holds = True
        probe.wait_for(STATUS, lambda m: m.json().get("instance") == "B")
        slave.set_registers(1, "hr", 0, [555])
        batch = probe.wait_for(f"{P}/dev1/$batch", lambda m: m.json()["values"]["t0"] == 555)
        assert batch.json()["deviceCode"] == "dev1"
        wait_for(lambda: a.drv.snapshot()["items"]["t0"]["value"] == 555, what="A read it")
        assert a.published() == 0 and b.published() > 0
