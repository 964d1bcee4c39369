"""MQTT mode "batch" and the queue's limits, end to end: a real mosquitto (own process), a
real paho subscriber, our driver polling a pymodbus slave (own process)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.northbound.mqtt import MqttPublisher
from tests.integration.test_mqtt import Gateway, P, device
from tests.mosquitto import Mosquitto, MqttProbe, Received
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for

GATEWAY_DOC = Path(__file__).resolve().parents[2] / "docs" / "gateway.md"
NAMES = [f"t{i}" for i in range(8)] + ["sp", "sp2", "ro"]  # device(tags=8): 11 items


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200) as peer:
        yield peer


def expected(name: str) -> Any:
    """The value of an item of tests.integration.test_mqtt.device at the slave's start."""
    if name == "ro":
        return default_register(1, "ir", 5)
    if name == "sp":
        return default_register(1, "hr", 100)
    if name == "sp2":  # Int16 x 0.1
        raw = default_register(1, "hr", 101)
        return pytest.approx((raw - 0x10000 if raw >= 0x8000 else raw) * 0.1)
    return default_register(1, "hr", int(name[1:]))


def readme_batch_example() -> dict[str, Any]:
    """The batch message docs/gateway.md shows (the json block after 'is published on')."""
    text = GATEWAY_DOC.read_text()
    found = re.search(r"is published on `[^`]+` as:\n\n```json\n(.*?)```", text, re.S)
    assert found, "docs/gateway.md: the batch mode example is missing"
    example: dict[str, Any] = json.loads(found.group(1))
    return example


def batches(probe: MqttProbe, code: str = "dev1") -> list[dict[str, Any]]:
    bodies: list[dict[str, Any]] = [m.json() for m in probe.on(f"{P}/{code}/$batch")]
    return bodies


@pytest.mark.parametrize("mode", ["per-item", "batch"])
def test_a_start_up_burst_is_kept_while_connected_and_an_outage_keeps_queue_size(
    broker: Mosquitto, slave: PymodbusSlave, mode: str
) -> None:
    """queueSize 5 and 11 items: every first read arrives while the broker is up (six
    were dropped when queueSize bounded normal running too); during an outage the queue
    holds 5, the oldest dropped, and those 5 arrive after the broker is back (retained,
    so that the probe sees them however its subscription and our reconnect interleave)."""
    cfg = device(slave.port, tags=8)
    probe = MqttProbe(broker.port).start()
    with Gateway(broker.port, cfg, queueSize=5, mode=mode, qos=1, retain=True) as gw:
        try:
            if mode == "per-item":
                for name in NAMES:
                    assert probe.wait_for(f"{P}/dev1/{name}").json()["value"] == expected(
                        name), name
            else:
                first = probe.wait_for(f"{P}/dev1/$batch").json()
                assert first["values"] == {name: expected(name) for name in NAMES}
        finally:
            probe.stop()
        stats = gw.pub.stats()
        assert stats["dropped"] == 0 and stats["published"] == len(NAMES), stats
        assert stats["queueLimit"] == 5 + len(NAMES)  # queueSize + the device's burst

        broker.stop()
        wait_for(lambda: not gw.pub.connected, what="publisher sees the broker go")
        wait_for(lambda: gw.pub.stats()["queueLimit"] == 5, what="the outage's limit")
        slave.set_registers(1, "hr", 0, [40_000 + i for i in range(8)])  # 8 updates
        wait_for(lambda: gw.pub.stats()["dropped"] >= 3, what="the queue overflowing")
        stats = gw.pub.stats()
        assert stats["queued"] == 5 and stats["dropped"] == 3, stats

        broker.restart()
        with MqttProbe(broker.port) as probe:
            assert gw.pub.wait_connected(10)
            wait_for(lambda: gw.pub.stats()["published"] == len(NAMES) + 5,
                     what="the 5 queued updates published")
            # the newest 5 survived the outage: t3..t7 (the restarted broker had nothing)
            if mode == "per-item":
                for i in range(3, 8):
                    assert probe.wait_for(f"{P}/dev1/t{i}").json()["value"] == 40_000 + i
                assert not [m for m in probe.received
                            if m.topic in (f"{P}/dev1/t0", f"{P}/dev1/t1", f"{P}/dev1/t2")]
            else:
                assert probe.wait_for(f"{P}/dev1/$batch").json()["values"] == {
                    f"t{i}": 40_000 + i for i in range(3, 8)}
        assert gw.pub.stats()["dropped"] == 3


def test_batch_mode_sends_one_message_per_device_and_cycle_as_the_readme_shows(
    broker: Mosquitto, slave: PymodbusSlave
) -> None:
    example = readme_batch_example()
    cfg = device(slave.port, tags=8, offlineAfterFailedCycles=1, retries=0, readTimeout=200)
    with MqttProbe(broker.port) as probe, \
            Gateway(broker.port, cfg, mode="batch", qos=1, statusCheckInterval=100) as gw:
        first: Received = probe.wait_for(f"{P}/dev1/$batch")
        body = first.json()
        assert first.qos == 1 and not first.retain
        # docs/gateway.md's schema: the same keys, each of the same JSON type
        assert list(body) == list(example)
        for key in ("values", "status", "errors"):
            assert isinstance(body[key], dict) and isinstance(example[key], dict), key
        assert isinstance(body["ts"], str) and isinstance(example["ts"], str)
        assert body["deviceCode"] == "dev1"
        assert datetime.fromisoformat(body["ts"]).tzinfo is not None
        assert datetime.fromisoformat(example["ts"]).tzinfo is not None
        assert body["values"] == {name: expected(name) for name in NAMES}
        assert body["status"] == dict.fromkeys(NAMES, "Ok") and body["errors"] == {}
        newest = max(it.update_ts for it in cfg.address_list if it.update_ts is not None)
        assert datetime.fromisoformat(body["ts"]) <= newest

        # a change: the next message carries that item alone
        mark = probe.mark()
        slave.set_registers(1, "hr", 100, [4321])
        changed = probe.wait_for(f"{P}/dev1/$batch", after=mark).json()
        assert changed["values"] == {"sp": 4321} and changed["status"] == {"sp": "Ok"}
        assert changed["errors"] == {}

        # the slave stops answering: every item Invalid with its reason, values kept
        mark = probe.mark()
        slave.set_offline(1)
        invalid = probe.wait_for(f"{P}/dev1/$batch", after=mark).json()
        assert set(invalid["status"].values()) == {"Invalid"}
        assert set(invalid["errors"]) == set(invalid["status"])
        assert all("not responding" in reason for reason in invalid["errors"].values())
        assert invalid["values"]["sp"] == 4321
        slave.set_offline(1, False)
        probe.wait_for(f"{P}/dev1/$batch",
                       lambda m: set(m.json()["status"].values()) == {"Ok"}, after=mark)

        # no item topics in this mode
        assert not [m for m in probe.received if m.topic.startswith(f"{P}/dev1/t")]
        # every batch published reaches the probe (the counter moves before delivery)
        wait_for(lambda: gw.pub.stats()["batchesPublished"]
                 == len(probe.on(f"{P}/dev1/$batch")), what="every batch at the probe")
        assert gw.pub.stats()["dropped"] == 0


def test_a_batch_topic_that_is_a_command_topic_is_refused() -> None:
    pub = MqttPublisher({"mode": "batch", "batchTopic": "{prefix}/{deviceCode}/set"},
                        gateway_id="gw1")
    try:
        with pytest.raises(ValueError, match=r"device 'dev1': its batch topic "
                                             r"'edgemodbus/dev1/set' is the device's command"):
            pub.check_item_names("dev1", ["a+b"])
    finally:
        pub.stop()
    pub = MqttPublisher({"mode": "batch"}, gateway_id="gw1")
    try:  # item names are JSON keys in this mode: no topic rules for them
        pub.check_item_names("dev1", ["a+b", "set", "$status"])
    finally:
        pub.stop()
    with pytest.raises(ValueError, match=r"mqtt.mode 'bulk': must be 'per-item', 'batch' or "
                                         r"'sparkplug'"):
        MqttPublisher({"mode": "bulk"})
