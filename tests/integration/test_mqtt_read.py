"""Reads on demand from MQTT (the ``$read`` topic, docs/reporting.md) and period reports
(reportEvery) on the wire: a real mosquitto, a paho subscriber, a pymodbus slave."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.northbound.mqtt import parse_read
from tests.integration.test_mqtt import Gateway
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

P = "edgemodbus"


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200, fill="zero") as peer:
        yield peer


def device(port: int, **comm: Any) -> em.DeviceConfig:
    items: list[dict[str, Any]] = [
        {"name": "p", "address": "hr:0", "deviceDataType": "UInt16"},
        {"name": "d", "address": "hr:40", "deviceDataType": "UInt16", "readCycle": "demand"},
        {"name": "e", "address": "hr:41", "deviceDataType": "UInt16", "readCycle": -1},
    ]
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
        "readCycle": 100, "readTimeout": 300, "reconnectInterval": 300, "byteTimeout": 50,
    }
    base.update(comm)
    return em.load_device_config(
        {"organization": {"deviceCode": "dev1"}, "communication": base, "addressList": items})


def read(probe: MqttProbe, payload: bytes | str, request: Any) -> dict[str, Any]:
    mark = probe.mark()
    probe.publish(f"{P}/dev1/$read", payload)
    msg = probe.wait_for(f"{P}/dev1/$reply", lambda m: m.json()["id"] == request, after=mark,
                         timeout=20)
    body: dict[str, Any] = msg.json()
    return body


def test_a_read_command_publishes_the_fresh_values_per_item(
        broker: Mosquitto, slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 40, [401, 402])
    with MqttProbe(broker.port) as probe, Gateway(broker.port, device(slave.port)) as gw:
        probe.wait_for(f"{P}/dev1/p")
        requests = slave.request_count(1)
        assert probe.on(f"{P}/dev1/d") == []  # never polled
        body = read(probe, json.dumps({"items": ["d"], "id": "r1"}), "r1")
        assert body["ok"] is True and body["error"] is None and body["items"] == ["d"]
        assert body["read"]["d"]["value"] == 401 and body["read"]["d"]["status"] == "Ok"
        assert probe.wait_for(f"{P}/dev1/d").json()["value"] == 401
        # e shares d's request: its first value is news, published as a change
        assert probe.wait_for(f"{P}/dev1/e").json()["value"] == 402
        # the same values again are published again (they answer a request)
        body = read(probe, b"", None)  # the whole device
        assert sorted(body["read"]) == ["d", "e", "p"]
        wait_for(lambda: len(probe.on(f"{P}/dev1/d")) == 2, what="d published again")
        wait_for(lambda: len(probe.on(f"{P}/dev1/e")) == 2, what="e published again")
        wait_for(lambda: len(probe.on(f"{P}/dev1/p")) == 2, what="p published again")
        assert slave.request_count(1) > requests
        assert gw.pub.stats()["commandErrors"] == 0


def test_a_read_command_in_batch_mode_publishes_a_batch(
        broker: Mosquitto, slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 40, [7])
    with MqttProbe(broker.port) as probe, \
            Gateway(broker.port, device(slave.port), mode="batch"):
        probe.wait_for(f"{P}/dev1/$batch")
        mark = probe.mark()
        body = read(probe, '["d"]', None)
        assert body["ok"] is True and body["read"]["d"]["value"] == 7
        batch = probe.wait_for(f"{P}/dev1/$batch", lambda m: "d" in m.json()["values"],
                               after=mark)
        # d asked for, e of the same request read for the first time (news)
        assert batch.json()["values"] == {"d": 7, "e": 0}


def test_bad_read_commands_get_error_replies(broker: Mosquitto, slave: PymodbusSlave,
                                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="edgemodbus.mqtt")
    with MqttProbe(broker.port) as probe, Gateway(broker.port, device(slave.port)) as gw:
        probe.wait_for(f"{P}/dev1/p")
        cases: list[tuple[bytes, Any, str]] = [
            (b'{"items": ["nosuch"], "id": "b1"}', "b1", "no item named 'nosuch'"),
            (b'{"items": 5, "id": "b2"}', "b2", "must be a non-empty list of item names"),
            (b'{"items": [], "id": "b3"}', "b3", "must be a non-empty list"),
            (b'{"itmes": ["d"], "id": "b4"}', "b4", "unknown key 'itmes'"),
            (b"{not json", None, "not JSON"),
            (b"\xff\xfe", None, "not JSON"),
            (b"[" * 30_000 + b"]" * 30_000, None, "nested too deeply"),
            (b'{"items": ["' + b"x" * 70_000 + b'"]}', None, "too large"),
            # a huge or structured id is never echoed: null, and the error says why
            (b'{"id": "' + b"i" * 5000 + b'"}', None, '"id" is a string of 5000 characters'),
            (b'{"id": {"a": [1]}, "items": ["d"]}', None, '"id" must be a number or a string'),
            (b'{"items": [["d"]], "id": "b9"}', "b9", "must be a non-empty list of item names"),
            (b'{"items": ["' + b"y" * 60_000 + b'"], "id": "b10"}', "b10", "no item named"),
        ]
        for payload, request, reason in cases:
            body = read(probe, payload, request)
            assert body["ok"] is False and reason in body["error"], (payload[:40], body)
            assert len(json.dumps(body)) < 1000
        assert gw.pub.stats()["commandErrors"] == len(cases)
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


def test_a_storm_of_reads_is_bounded_and_polling_goes_on(
        broker: Mosquitto, slave: PymodbusSlave) -> None:
    n = 400
    with MqttProbe(broker.port) as probe, Gateway(broker.port, device(slave.port)) as gw:
        probe.wait_for(f"{P}/dev1/p")
        mark = probe.mark()
        for i in range(n):
            probe.publish(f"{P}/dev1/$read", json.dumps({"items": ["d"], "id": i}))
        wait_for(lambda: len(probe.on(f"{P}/dev1/$reply")) >= n, timeout=60,
                 what=f"{n} replies")
        cycles = gw.drv.stats()["cycles"]
        wait_for(lambda: gw.drv.stats()["cycles"] >= cycles + 5, what="polling goes on")
        replies = [m.json() for m in probe.messages()[mark:]
                   if m.topic == f"{P}/dev1/$reply"]
    ok = [r for r in replies if r["ok"]]
    refused = [r for r in replies if not r["ok"]]
    assert len(ok) + len(refused) == n and ok
    # what the line or the command queue could not take was refused at once
    assert all("pending" in r["error"] or "jobs already waiting" in r["error"]
               for r in refused), {r["error"] for r in refused}


def test_parse_read_forms() -> None:
    assert parse_read(b"") == (None, None)
    assert parse_read(b"{}") == (None, None)
    assert parse_read(b'{"id": 3}') == (3, None)
    assert parse_read(b'"a"') == (None, ["a"])
    assert parse_read(b'["a", "b"]') == (None, ["a", "b"])
    assert parse_read(b'{"items": ["a"], "id": "x"}') == ("x", ["a"])
    with pytest.raises(ValueError, match="list of item names"):
        parse_read(b"[1]")


def test_an_item_named_like_the_read_topic_is_refused_and_the_topic_is_checked() -> None:
    from edgemodbus.config import ConfigError
    from edgemodbus.northbound.mqtt import MqttPublisher, MqttSettings

    pub = MqttPublisher({"port": 1}, gateway_id="gw1")
    try:
        with pytest.raises(ValueError, match=r"item '\$read' of device 'dev1'.*read topic"):
            pub.check_item_names("dev1", ["ok", "$read"])
    finally:
        pub.stop()
    with pytest.raises(ConfigError, match=r"readTopic"):
        MqttSettings.load({"readTopic": "{prefix}/#/read"})
    assert MqttSettings.load({"readTopic": "{prefix}/{deviceCode}/get"}).read_topic == (
        "{prefix}/{deviceCode}/get")
