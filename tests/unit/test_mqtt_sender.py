"""The sender's seam, without a broker: every message reaches paho through hand_over
(client.publish), and its completion is seen in settle (the MQTTMessageInfo that publish
returned); a reconnect forgets the QoS 0 messages paho dropped with the old connection.
A stand-in client plays paho's publish() and its MQTTMessageInfo."""

from __future__ import annotations

import threading
from typing import Any

import paho.mqtt.client as paho

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from edgemodbus.northbound.mqtt import MqttSettings
from edgemodbus.northbound.mqtt.devices import AttachedDevice
from edgemodbus.northbound.mqtt.outbox import Message, Outbox
from edgemodbus.northbound.mqtt.sender import Sender


class Info:
    """What publish() returns: rc, mid, is_published()."""

    def __init__(self, mid: int, rc: int = 0) -> None:
        self.mid, self.rc, self.done = mid, rc, False

    def is_published(self) -> bool:
        return self.done


class Client:
    """paho's publish(), recorded; refuses once ``refuse_after`` messages were taken."""

    def __init__(self, refuse_after: int = 1_000_000) -> None:
        self.sent: list[tuple[str, bytes, int, bool]] = []
        self.infos: list[Info] = []
        self.refuse_after = refuse_after

    def publish(self, topic: str, payload: bytes, qos: int = 0,
                retain: bool = False) -> Info:
        if len(self.sent) >= self.refuse_after:
            return Info(0, int(paho.MQTT_ERR_QUEUE_SIZE))
        self.sent.append((topic, payload, qos, retain))
        self.infos.append(Info(len(self.infos) + 1))
        return self.infos[-1]


def make(mode: str, **settings: Any) -> tuple[Sender, Outbox, AttachedDevice]:
    s = MqttSettings.load({"mode": mode, **settings})
    outbox = Outbox(s.queue_size)
    connected = threading.Event()
    connected.set()

    def topic(template: str, code: str, item: str = "") -> str:
        return template.format(prefix="p", deviceCode=code, itemName=item, gatewayId="g")

    sender = Sender(outbox, s, paho, "g", lambda c, i: topic(s.item_topic, c, i), connected)
    return sender, outbox, AttachedDevice(s, topic, em.DriverModbusRtu(), "dev1")


def items(n: int) -> list[em.DeviceAddressItem]:
    made = []
    for k in range(n):
        item = em.DeviceAddressItem.model_validate(
            {"name": f"t{k}", "address": f"hr:{k}", "deviceDataType": "UInt16"})
        item.value, item.status = k, ItemStatus.OK
        made.append(item)
    return made


def test_batch_mode_hands_one_message_per_report_and_settles_in_order() -> None:
    sender, outbox, dev = make("batch", qos=1)
    outbox.offer_items(dev, items(3))
    outbox.offer_items(dev, items(2))
    client = Client()
    sender.pump(client)  # type: ignore[arg-type]
    assert [(t, q) for t, _, q, _ in client.sent] == [("p/dev1/$batch", 1)] * 2
    assert outbox.counts["published"] == 5 and outbox.counts["batchesPublished"] == 2
    assert dev.published == 5 and outbox.queued == 0
    assert len(sender.window) == 2 and sender.busy()
    client.infos[1].done = True  # the second acknowledged first: settle waits for order
    sender.settle()
    assert len(sender.window) == 2
    client.infos[0].done = True
    assert not sender.busy() and outbox.counts["acknowledged"] == 2


def test_a_message_paho_refuses_goes_back_to_the_front() -> None:
    sender, outbox, dev = make("per-item")
    outbox.offer_items(dev, items(4))
    client = Client(refuse_after=3)
    sender.pump(client)  # type: ignore[arg-type]
    assert [t for t, _, _, _ in client.sent] == ["p/dev1/t0", "p/dev1/t1", "p/dev1/t2"]
    assert outbox.counts["publishErrors"] == 1 and outbox.counts["published"] == 3
    assert [row[0] for r in outbox.reports for row in r.rows] == ["t3"]
    client.refuse_after = 10
    sender.pump(client)  # type: ignore[arg-type]
    assert client.sent[-1][0] == "p/dev1/t3" and outbox.queued == 0


def test_the_window_bounds_what_paho_holds_and_a_reconnect_forgets_lost_qos0() -> None:
    sender, outbox, dev = make("per-item", maxInflight=1)  # a window of 4
    outbox.push_control(Message("dev1", "p/dev1/$status", b"{}", 1, True))
    outbox.offer_items(dev, items(6))
    client = Client()
    sender.pump(client)  # type: ignore[arg-type]
    assert [t for t, _, _, _ in client.sent] == [
        "p/dev1/$status", "p/dev1/t0", "p/dev1/t1", "p/dev1/t2"]  # control first
    assert outbox.queued == 3
    client.infos[2].done = True  # t1 written, behind the unconfirmed status message
    sender.reconnected()  # t0 and t2 were never written: lost with the connection
    assert outbox.counts["lostOnDisconnect"] == 2
    assert [m.topic for _, m, _ in sender.window] == ["p/dev1/$status"]  # paho resends it
    sender.pump(client)  # type: ignore[arg-type]
    assert [t for t, _, _, _ in client.sent[4:]] == ["p/dev1/t3", "p/dev1/t4", "p/dev1/t5"]
