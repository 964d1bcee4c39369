"""Store-and-forward in the sender (store_forward.py), without a broker: the stand-in
paho client of tests/unit/test_mqtt_sender.py, a real spool file.  An outage goes to the
spool; the replay is in order with retain off; QoS 1 stays in the spool until
acknowledged; a device with a backlog queues its live messages behind it while other
devices publish directly."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.northbound.mqtt.devices import AttachedDevice
from edgemodbus.northbound.mqtt.outbox import Outbox
from edgemodbus.northbound.mqtt.sender import Sender
from tests.unit.test_mqtt_sender import Client, items, make


def spooled(tmp_path: Path, mode: str = "per-item", **settings: Any
            ) -> tuple[Sender, Outbox, AttachedDevice]:
    sender, outbox, dev = make(mode, storeAndForward={"path": str(tmp_path / "s.db"),
                                                      "replayRatePerS": 1000}, **settings)
    sender.open_spool()
    return sender, outbox, dev


def topic(template: str, code: str, item: str = "") -> str:
    return template.format(prefix="p", deviceCode=code, itemName=item, gatewayId="g")


def values(client: Client, start: int = 0) -> list[Any]:
    return [json.loads(p)["value"] for _, p, _, _ in client.sent[start:]]


def test_an_outage_goes_to_the_spool_and_is_replayed_in_order_with_its_retain_flag(
        tmp_path: Path) -> None:
    """Replayed with the retain flag it was kept with: the device's live messages queue
    behind its backlog, so its last replayed message per topic is the newest (before:
    retain off, and the broker kept the value from before the outage, issue #24)."""
    sender, outbox, dev = spooled(tmp_path, qos=1, retain=True, queueSize=2)
    assert sender.forwarder is not None
    try:
        sender._connected.clear()
        outbox.set_outage(True)
        for _ in range(3):  # 12 updates, beyond queueSize: none dropped
            outbox.offer_items(dev, items(4))
            sender.spool_outage()
        assert outbox.counts["dropped"] == 0 and outbox.queued == 0
        assert sender.forwarder.stats()["pending"] == 12
        sender._connected.set()
        client = Client()
        sender.pump(client)  # type: ignore[arg-type]
        assert values(client) == [0, 1, 2, 3] * 3
        assert {(qos, retain) for _, _, qos, retain in client.sent} == {(1, True)}
        stats = sender.forwarder.stats()
        assert stats["inflight"] == 12 and stats["replayed"] == 12
        for info in client.infos[:5]:
            info.done = True
        sender.pump(client)  # type: ignore[arg-type]
        assert sender.forwarder.stats()["stored"] == 7  # acked ones deleted
    finally:
        sender.close_spool()
        outbox.close()


def test_live_qos1_is_in_the_spool_until_acknowledged_and_survives_a_restart(
        tmp_path: Path) -> None:
    sender, outbox, dev = spooled(tmp_path, qos=1)
    assert sender.forwarder is not None
    outbox.offer_items(dev, items(3))
    client = Client()
    sender.pump(client)  # type: ignore[arg-type]
    assert values(client) == [0, 1, 2]
    assert sender.forwarder.stats()["inflight"] == 3
    client.infos[0].done = True
    sender.pump(client)  # type: ignore[arg-type]
    sender.close_spool()  # the process ends with two unacknowledged
    outbox.close()
    again, outbox, _ = spooled(tmp_path, qos=1)
    try:
        client = Client()
        again.pump(client)  # type: ignore[arg-type]
        assert values(client) == [1, 2]  # replayed; 0 was acknowledged
    finally:
        again.close_spool()
        outbox.close()


def test_a_device_with_a_backlog_queues_behind_it_and_others_publish_directly(
        tmp_path: Path) -> None:
    sender, outbox, dev = spooled(tmp_path, qos=0)
    assert sender.forwarder is not None
    try:
        other = AttachedDevice(sender.settings, topic, em.DriverModbusRtu(), "dev2")
        sender._connected.clear()
        outbox.offer_items(dev, items(2))
        sender.spool_outage()
        sender._connected.set()
        sender.forwarder.pacer.spend(sender.forwarder.pacer.budget())  # no replay yet
        outbox.offer_items(dev, items(3)[2:])  # dev1: behind its backlog
        outbox.offer_items(other, items(1))  # dev2: no backlog, at once, not spooled
        client = Client()
        sender.pump(client)  # type: ignore[arg-type]
        # the pacer is empty, but dev1's live message queued behind its backlog: one
        # more message of the backlog goes (live traffic is not held back by the rate)
        assert [t for t, _, _, _ in client.sent] == ["p/dev2/t0", "p/dev1/t0"]
        assert sender.forwarder.stats()["pending"] == 2
        sender.forwarder.pacer = type(sender.forwarder.pacer)(1000)  # replay allowed again
        sender.pump(client)  # type: ignore[arg-type]
        assert [t for t, _, _, _ in client.sent[2:]] == ["p/dev1/t1", "p/dev1/t2"]
        for info in client.infos:
            info.done = True
        sender.pump(client)  # type: ignore[arg-type]
        assert sender.forwarder.stats()["stored"] == 0
        assert not sender.forwarder.backlogged("dev1")
        outbox.offer_items(dev, items(1))  # no backlog any more: direct
        sender.pump(client)  # type: ignore[arg-type]
        assert client.sent[-1][0] == "p/dev1/t0"
        assert sender.forwarder.stats()["appended"] == 3  # QoS 0 live is not spooled
    finally:
        sender.close_spool()
        outbox.close()


def test_refused_and_lost_messages_go_back_to_the_spool(tmp_path: Path) -> None:
    sender, outbox, dev = spooled(tmp_path, "batch", qos=0)
    assert sender.forwarder is not None
    try:
        for _ in range(3):
            outbox.offer_items(dev, items(2))
        client = Client(refuse_after=1)
        sender.pump(client)  # type: ignore[arg-type]
        assert len(client.sent) == 1 and sender.forwarder.stats()["pending"] == 2
        sender.reconnected()  # the first was never written: lost, not spooled (QoS 0)
        client.refuse_after = 10
        sender.pump(client)  # type: ignore[arg-type]
        assert len(client.sent) == 3
        sender.reconnected()  # the two replayed were not written: pending again
        assert sender.forwarder.stats()["pending"] == 2
        sender.pump(client)  # type: ignore[arg-type]
        for info in client.infos:
            info.done = True
        sender.pump(client)  # type: ignore[arg-type]
        assert len(client.sent) == 5 and sender.forwarder.stats()["stored"] == 0
    finally:
        sender.close_spool()
        outbox.close()


def test_a_spool_in_use_by_another_publisher_is_a_config_error_naming_the_path(
        tmp_path: Path) -> None:
    settings = {"storeAndForward": {"path": str(tmp_path / "s.db")}}
    first = MqttPublisher(settings, gateway_id="g1")
    first._sender.open_spool()
    second = MqttPublisher(settings, gateway_id="g2")
    try:
        with pytest.raises(ConfigError, match=r"mqtt.storeAndForward.path '.*s.db': spool "
                                              r"'.*s.db': in use by another process"):
            second.start()
    finally:
        second.stop()
        first.stop()


def test_an_outage_queue_has_the_memory_queue_as_margin_before_it_drops(
        tmp_path: Path) -> None:
    """Issue #24's flaky test: during an outage the line workers queue reports faster
    than a stalled MQTT thread (a slow checkpoint, a loaded machine) moves them to the
    spool; the outbox then dropped 10 past queueSize + one report per device.  Now
    memoryQueueSize more may wait (the memory store-and-forward may use anyway)."""
    sender, outbox, dev = spooled(tmp_path, queueSize=10, qos=1)
    assert sender.forwarder is not None
    s = sender.settings.store_and_forward
    assert s is not None and s.memory_queue_size == 10_000
    try:
        sender._connected.clear()
        outbox.set_outage(True)
        outbox.offer_items(dev, items(20))  # the largest report: the burst
        for _ in range(500):  # 10,000 more, the MQTT thread kept from running
            outbox.offer_items(dev, items(20))
        assert outbox.counts["dropped"] == 0 and outbox.queued == 10_020
        outbox.offer_items(dev, items(20))
        assert outbox.counts["dropped"] == 10  # the bound still holds, counted
        sender.spool_outage()
        assert sender.forwarder.stats()["stored"] == 10_030
    finally:
        sender.close_spool()
        outbox.close()


def test_a_damaged_spool_does_not_stop_the_publisher(tmp_path: Path) -> None:
    """Before: ConfigError at start(), so the gateway exited 2 (no polling, no server;
    under systemd a restart loop).  Now the file is moved aside and a new one used."""
    spool = tmp_path / "s.db"
    spool.write_bytes(b"\x00garbage" * 1000)
    pub = MqttPublisher({"port": 1, "storeAndForward": {"path": str(spool)}},
                        gateway_id="g1")
    try:
        pub.start()
        aside = [p.name for p in tmp_path.iterdir() if ".corrupt-" in p.name]
        assert len(aside) == 1 and aside[0].startswith("s.db.corrupt-")
        assert pub.stats()["spool"]["stored"] == 0
    finally:
        pub.stop(timeout=0)
