"""MQTT publisher end to end: a real mosquitto (own process), a real paho subscriber, our
driver polling a pymodbus slave (own process)."""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import time
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.datatypes import DeviceDriverStatus, ItemStatus
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.northbound.mqtt import (
    MqttPublisher,
    MqttSettings,
    TlsSettings,
    encode_item,
    jsonable,
    parse_command,
)
from tests.fake_brokers import FakeBroker, self_signed_cert
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, default_register, free_port
from tests.waiting import wait_for

P = "edgemodbus"


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200) as peer:
        yield peer


def device(port: int, code: str = "dev1", tags: int = 5, **comm: Any) -> em.DeviceConfig:
    items: list[dict[str, Any]] = [
        {"name": f"t{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"} for i in range(tags)
    ]
    items += [
        {"name": "sp", "address": "hr:100", "deviceDataType": "UInt16"},
        {"name": "sp2", "address": "hr:101", "deviceDataType": "Int16", "dataMultiplier": 0.1},
        {"name": "ro", "address": "ir:5", "deviceDataType": "UInt16"},
    ]
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
        "readCycle": 100, "readTimeout": 300, "reconnectInterval": 300, "byteTimeout": 50,
    }
    base.update(comm)
    return em.load_device_config(
        {"organization": {"deviceCode": code}, "communication": base, "addressList": items}
    )


class Gateway:
    """A publisher plus one driver: started on enter, stopped on exit."""

    def __init__(self, broker_port: int, cfg: em.DeviceConfig, **settings: Any) -> None:
        settings.setdefault("port", broker_port)
        settings.setdefault("reconnectMin", 100)
        settings.setdefault("reconnectMax", 400)
        self.cfg = cfg
        self.pub = MqttPublisher(settings, gateway_id="gw1")
        self.drv = em.DriverModbusRtu()

    def __enter__(self) -> Gateway:
        self.pub.start()
        self.pub.attach(self.drv, self.cfg.organization.device_code)
        assert self.drv.start_device(self.cfg.organization, self.cfg.communication,
                                     self.cfg.address_list)
        return self

    def __exit__(self, *exc: object) -> None:
        self.drv.stop_device()
        self.pub.stop()


@pytest.mark.parametrize("qos", [0, 1])
def test_item_updates_status_and_snapshot_reach_a_subscriber(
    broker: Mosquitto, slave: PymodbusSlave, qos: int
) -> None:
    cfg = device(slave.port, snapshotInterval=200)
    with MqttProbe(broker.port) as probe, Gateway(broker.port, cfg, qos=qos) as gw:
        for i in range(5):
            msg = probe.wait_for(f"{P}/dev1/t{i}")
            body = msg.json()
            assert body["value"] == default_register(1, "hr", i)
            assert body["status"] == "Ok" and body["errorReason"] is None
            assert datetime.fromisoformat(body["updateTs"]).tzinfo is not None
            assert msg.qos == qos and not msg.retain
        probe.wait_for(f"{P}/dev1/$status", lambda m: m.json()["status"] == "Running")
        snap = probe.wait_for("/real/dev1", lambda m: m.json()["items"]["t2"]["status"] == "Ok")
        assert snap.json()["deviceCode"] == "dev1" and snap.json()["gatewayId"] == "gw1"
        assert snap.json()["items"]["t2"]["value"] == default_register(1, "hr", 2)

        # report mode "change": an unchanged value is not published again...
        cycles = gw.drv.stats()["cycles"]
        wait_for(lambda: gw.drv.stats()["cycles"] >= cycles + 5, what="5 more cycles")
        assert len(probe.on(f"{P}/dev1/t0")) == 1
        # ...a changed one is, with its new value
        slave.set_registers(1, "hr", 0, [4242])
        assert probe.wait_for(f"{P}/dev1/t0", lambda m: m.json()["value"] == 4242)

        # a subscriber that comes later gets the retained status, gateway and snapshot
        with MqttProbe(broker.port) as late:
            status = late.wait_for(f"{P}/dev1/$status")
            assert status.retain and status.json()["status"] == "Running"
            gateway = late.wait_for(f"{P}/$gateway/gw1")
            assert gateway.retain and gateway.json()["status"] == "online"
            assert late.wait_for("/real/dev1").retain
        stats = gw.pub.stats()
        assert stats["connected"] and stats["dropped"] == 0
        assert stats["devices"]["dev1"]["published"] >= 9  # 8 items + the change
    # a clean stop says so, retained
    with MqttProbe(broker.port) as late:
        offline = late.wait_for(f"{P}/$gateway/gw1")
        assert offline.retain and offline.json()["status"] == "offline"
        assert offline.json()["reason"] == "shutdown"
        status = late.wait_for(f"{P}/dev1/$status")
        assert status.retain and status.json()["status"] == "Stopped"


def test_status_change_is_published_retained(broker: Mosquitto, slave: PymodbusSlave) -> None:
    cfg = device(slave.port, offlineAfterFailedCycles=1, retries=0, readTimeout=200)
    with MqttProbe(broker.port) as probe, Gateway(broker.port, cfg, statusCheckInterval=100):
        probe.wait_for(f"{P}/dev1/$status", lambda m: m.json()["status"] == "Running")
        mark = probe.mark()
        slave.set_offline(1)
        probe.wait_for(f"{P}/dev1/$status", lambda m: m.json()["status"] == "Offline",
                       after=mark)
        invalid = probe.wait_for(f"{P}/dev1/t1", lambda m: m.json()["status"] == "Invalid")
        assert "not responding" in invalid.json()["errorReason"]
        slave.set_offline(1, False)
        probe.wait_for(f"{P}/dev1/$status", lambda m: m.json()["status"] == "Running",
                       after=mark)
        # each status published once per change, not once per check
        statuses = [m.json()["status"] for m in probe.on(f"{P}/dev1/$status")[-2:]]
        assert statuses == ["Offline", "Running"]


def test_writes_from_mqtt_reach_the_slave_and_bad_payloads_get_error_replies(
    broker: Mosquitto, slave: PymodbusSlave
) -> None:
    cfg = device(slave.port)
    with MqttProbe(broker.port) as probe, Gateway(broker.port, cfg) as gw:
        probe.wait_for(f"{P}/dev1/sp")
        reply = f"{P}/dev1/$reply"

        def command(topic: str, payload: bytes | str, request: str | None) -> dict[str, Any]:
            mark = probe.mark()
            probe.publish(topic, payload)
            msg = probe.wait_for(reply, lambda m: m.json()["id"] == request, after=mark)
            body: dict[str, Any] = msg.json()
            return body

        ok = command(f"{P}/dev1/set/sp", '{"value": 1234, "id": "a1"}', "a1")
        assert ok["ok"] is True and ok["error"] is None and ok["items"] == ["sp"]
        assert slave.registers(1, "hr", 100) == [1234]
        assert probe.wait_for(f"{P}/dev1/sp", lambda m: m.json()["value"] == 1234)

        ok = command(f"{P}/dev1/set", json.dumps({"items": {"sp": 7, "sp2": -1.5}, "id": 9}), 9)
        assert ok["ok"] is True, ok
        assert slave.registers(1, "hr", 100, 2) == [7, (-15) & 0xFFFF]
        ok = command(f"{P}/dev1/set", json.dumps([["sp", 8], {"name": "sp2", "value": 2}]),
                     None)
        assert ok["ok"] is True and slave.registers(1, "hr", 100, 2) == [8, 20]
        ok = command(f"{P}/dev1/set/sp", "99", None)  # a bare JSON value
        assert ok["ok"] is True and slave.registers(1, "hr", 100) == [99]

        bad = [
            (f"{P}/dev1/set/nosuch", '{"value": 1, "id": "b1"}', "b1", "nosuch"),
            (f"{P}/dev1/set/sp", '{"value": 70000, "id": "b2"}', "b2", "sp"),
            (f"{P}/dev1/set/sp", '{"value": "abc", "id": "b3"}', "b3", "sp"),
            (f"{P}/dev1/set/ro", '{"value": 1, "id": "b4"}', "b4", "read-only"),
            (f"{P}/dev1/set/sp", '{"id": "b5"}', "b5", '"value"'),
            (f"{P}/dev1/set", '{"id": "b6", "items": 5}', "b6", "items"),
            (f"{P}/dev1/set", "{not json", None, "not JSON"),
            (f"{P}/dev1/set", b"\xff\xfe\x00", None, "UTF-8"),
            (f"{P}/dev1/set", '{"items": {}, "id": "b9"}', "b9", "no items"),
        ]
        for topic, payload, request, reason in bad:
            body = command(topic, payload, request)
            assert body["ok"] is False and reason in body["error"], (payload, body)
        assert slave.registers(1, "hr", 100) == [99]  # none of them wrote anything
        ok = command(f"{P}/dev1/set/sp", '{"value": 5, "id": "after"}', "after")
        assert ok["ok"] is True and slave.registers(1, "hr", 100) == [5]
        stats = gw.pub.stats()
        assert stats["commands"] == 5 + len(bad)
        assert stats["commandErrors"] == len(bad)
        assert gw.drv.device_driver_status is DeviceDriverStatus.RUNNING


def test_hostile_commands_get_short_error_replies_without_tracebacks(
    broker: Mosquitto, slave: PymodbusSlave, caplog: pytest.LogCaptureFixture
) -> None:
    """The issue's cases: nested JSON made a traceback per message; a 5 MB "id" was echoed
    back in the reply (the payload over the 64 KB cap was parsed for its id anyway).
    Now: an error reply each, counted, no traceback, no echo of the oversized field."""
    caplog.set_level(logging.DEBUG, logger="edgemodbus.mqtt")
    cfg = device(slave.port)
    with MqttProbe(broker.port) as probe, Gateway(broker.port, cfg) as gw:
        probe.wait_for(f"{P}/dev1/sp")
        reply = f"{P}/dev1/$reply"
        cases: list[tuple[str, bytes, str]] = [
            (f"{P}/dev1/set/sp", b"[" * 100_000 + b"]" * 100_000, "too large"),
            (f"{P}/dev1/set/sp", b"[" * 30_000 + b"]" * 30_000, "nested too deeply"),
            (f"{P}/dev1/set", b'{"items": ' + b"[" * 30_000 + b"]" * 30_000 + b"}",
             "nested too deeply"),
            (f"{P}/dev1/$action", b'{"action": ' + b"[" * 30_000 + b"]" * 30_000 + b"}",
             "nested too deeply"),
            (f"{P}/dev1/set/sp", json.dumps({"value": 1, "id": "i" * 5_000_000}).encode(),
             "too large"),
            (f"{P}/dev1/set/sp", json.dumps({"value": 1, "id": "i" * 1000}).encode(),
             '"id" is a string of 1000 characters (at most 128)'),
            (f"{P}/dev1/set", json.dumps({"items": {"sp": 1}, "id": {"a": [1]}}).encode(),
             '"id" must be a number or a string'),
            (f"{P}/dev1/set", json.dumps({"items": [["x" * 60_000]]}).encode(),
             "items[0] \"['" + "x" * 30 + "\"... (60004 chars): use"),
        ]
        for topic, payload, reason in cases:
            mark = probe.mark()
            probe.publish(topic, payload)
            msg = probe.wait_for(reply, after=mark, timeout=20)
            assert len(msg.payload) < 1000, (reason, msg.payload[:200])
            body = msg.json()
            assert body["ok"] is False and body["id"] is None, body
            assert reason in body["error"], (reason, body["error"])
        assert slave.registers(1, "hr", 100) == [default_register(1, "hr", 100)]
        assert gw.pub.stats()["commandErrors"] == len(cases)
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


def test_broker_restart_coalesces_snapshots_drops_updates_and_recovers(
    broker: Mosquitto, slave: PymodbusSlave
) -> None:
    cfg = device(slave.port, tags=20, snapshotInterval=100)
    probe = MqttProbe(broker.port).start()
    with Gateway(broker.port, cfg, queueSize=5) as gw:
        try:
            probe.wait_for(f"{P}/dev1/t19")
        finally:
            probe.stop()
        assert gw.pub.wait_connected(5)
        broker.stop()
        wait_for(lambda: not gw.pub.connected, what="publisher sees the broker go")
        cycles = gw.drv.stats()["cycles"]
        slave.set_registers(1, "hr", 0, [50_000 + i for i in range(20)])  # 20 updates
        wait_for(lambda: gw.pub.stats()["dropped"] >= 15, what="queue overflow")
        wait_for(lambda: gw.pub.stats()["snapshotsCoalesced"] >= 2, what="coalescing")
        stats = gw.pub.stats()
        assert stats["queued"] == 5 and stats["pendingSnapshots"] == 1
        assert stats["devices"]["dev1"]["dropped"] == stats["dropped"]
        # polling went on at full speed while the broker was away
        wait_for(lambda: gw.drv.stats()["cycles"] >= cycles + 10, timeout=20,
                   what="polling while the broker is down")
        assert gw.drv.stats()["overruns"] == 0

        broker.restart()  # no persistence: retained messages are gone
        assert gw.pub.wait_connected(10)
        with MqttProbe(broker.port) as probe:
            # the new broker knew nothing: all of this was republished on reconnect (live
            # or retained, depending on whether it came before our subscription)
            assert probe.wait_for(f"{P}/$gateway/gw1").json()["status"] == "online"
            assert probe.wait_for(f"{P}/dev1/$status").json()["status"] == "Running"
            probe.wait_for("/real/dev1", lambda m: m.json()["items"]["t0"]["value"] == 50_000)
            slave.set_registers(1, "hr", 3, [7])
            assert probe.wait_for(f"{P}/dev1/t3", lambda m: m.json()["value"] == 7)
        assert gw.pub.stats()["connects"] == 2


def test_unreachable_broker_never_blocks_polling_or_stop(slave: PymodbusSlave) -> None:
    cfg = device(slave.port)
    gw = Gateway(free_port(), cfg, reconnectMin=50, reconnectMax=200)
    with gw:
        wait_for(lambda: gw.drv.stats().get("cycles", 0) >= 5, what="polling")
        wait_for(lambda: gw.pub.stats()["connectFailures"] >= 2, what="retries")
        started = time.monotonic()
    assert time.monotonic() - started < 1.5
    assert not gw.pub.connected


def test_item_names_that_collide_with_command_topics_are_refused(broker: Mosquitto) -> None:
    pub = MqttPublisher({"port": broker.port}, gateway_id="gw1")
    try:
        with pytest.raises(ValueError, match=r"item 'set' of device 'dev1'.*command topic"):
            pub.check_item_names("dev1", ["ok", "set"])
        with pytest.raises(ValueError, match=r"'\$status'.*status topic"):
            pub.check_item_names("dev1", ["$status"])
        with pytest.raises(ValueError, match=r"'a\+b'.*'\+', '#'"):
            pub.check_item_names("dev1", ["a+b"])
        with pytest.raises(ValueError, match="deviceCode 'a/b'"):
            pub.check_item_names("a/b", ["x"])
        pub.check_item_names("dev1", ["status", "reply", "settings"])
    finally:
        pub.stop()


def test_settings_errors_name_the_field_the_value_and_what_is_allowed() -> None:
    with pytest.raises(ConfigError) as err:
        MqttSettings.load({"itemTopic": "{prefix}/{device}/{itemName}"})
    assert str(err.value).startswith("mqtt.itemTopic '{prefix}/{device}/{itemName}': ")
    assert "unknown placeholder {device}" in str(err.value)
    assert "{deviceCode}" in str(err.value)
    with pytest.raises(ConfigError, match=r"reconnectMax 100 must be >= reconnectMin"):
        MqttSettings.load({"reconnectMin": 500, "reconnectMax": 100})
    with pytest.raises(ValueError, match=r"qos.*3.*0 or 1 or 2"):
        MqttPublisher({"qos": 3})
    with pytest.raises(ValueError, match=r"commandTopic.*must end with /\{itemName\}"):
        MqttPublisher({"commandTopic": "{prefix}/{itemName}/set"})
    with pytest.raises(ValueError, match=r"topicPrefix 'a/#'.*wildcards"):
        MqttPublisher({"topicPrefix": "a/#"})


def test_item_payload_is_the_json_of_its_fields() -> None:
    ts = datetime(2026, 1, 2, 3, 4, 5, 678000, tzinfo=timezone.utc)
    for value in (0, -7, 2**70, 1.5, -0.0, 1e300, float("nan"), float("-inf"), True, False,
                  None, "héllo \"x\"\n", b"\x01\xff", ts, [1, 2]):
        for status, error in ((ItemStatus.OK, None), (ItemStatus.INVALID, 'bad "x"')):
            body = json.loads(encode_item(value, status, ts, error))
            assert body == {"value": jsonable(value), "status": status.value,
                            "updateTs": ts.isoformat(), "errorReason": error}, value
    assert json.loads(encode_item(1, ItemStatus.UNKNOWN, None, None))["updateTs"] is None


def test_parse_command_forms() -> None:
    assert parse_command("sp", b"12.5") == (None, [("sp", 12.5)])
    assert parse_command("sp", b"true") == (None, [("sp", True)])
    assert parse_command("name", b"hello world") == (None, [("name", "hello world")])
    assert parse_command("sp", b'{"value": [1], "id": 3}') == (3, [("sp", [1])])
    assert parse_command(None, b'{"a": 1, "b": false}') == (None, [("a", 1), ("b", False)])
    assert parse_command(None, b'{"items": [["a", 1]], "id": "x"}') == ("x", [("a", 1)])
    with pytest.raises(ValueError, match=r"items\[1\]"):
        parse_command(None, b'[["a", 1], 7]')
    with pytest.raises(ValueError, match="too large"):
        parse_command("sp", b"1" * 70_000)


# -- failed connections: reason in the log, counted, rate-limited ----------------------
@pytest.fixture
def tls_broker(tmp_path: Path) -> Iterator[tuple[Mosquitto, int, Path]]:
    """mosquitto with its plain listener and a TLS-only one: (broker, tls port, CA)."""
    cert, key = self_signed_cert(tmp_path / "tls")
    tls_port = free_port()
    extra = [f"listener {tls_port} 127.0.0.1", f"certfile {cert}", f"keyfile {key}"]
    with Mosquitto(tmp_path / "broker", extra_config=extra) as peer:
        yield peer, tls_port, cert


def failures(caplog: pytest.LogCaptureFixture, level: int = logging.WARNING) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "edgemodbus.mqtt" and r.levelno == level
            and ("connection failed" in r.getMessage() or "still failing" in r.getMessage()
                 or "attempt" in r.getMessage())]


def assert_failures_reported(pub: MqttPublisher, caplog: pytest.LogCaptureFixture,
                             reason: str) -> None:
    """Three failed attempts counted, exported, and the first logged with ``reason``."""
    wait_for(lambda: pub.stats()["connectFailures"] >= 3, what="3 failed connects")
    lines = failures(caplog)
    assert lines, "no warning for a failed connect"
    assert re.search(reason, lines[0]), lines[0]
    assert lines[0].startswith(f"MQTT broker 127.0.0.1:{pub.settings.port}: connection "
                               "failed: ")
    exporter = MetricsExporter({"port": 0})
    exporter.set_publisher(pub)
    found = re.search(r"^edgemodbus_mqtt_connect_failures_total (\S+)$",
                      exporter.render().decode(), re.M)
    assert found and float(found.group(1)) >= 3
    stats = pub.stats()
    assert stats["connects"] == 0 and not stats["connected"]


@pytest.mark.parametrize("mode, reason", [
    ("close", r"closed before the broker answered CONNECT; is the port TLS-only"),
    ("silent", r"no CONNACK within 200 ms \(connectTimeout\)"),
])
def test_a_peer_that_hangs_up_or_never_answers_is_a_failed_connect(
    caplog: pytest.LogCaptureFixture, mode: Literal["close", "silent"], reason: str
) -> None:
    caplog.set_level(logging.DEBUG, logger="edgemodbus.mqtt")
    with FakeBroker(mode) as peer:
        pub = MqttPublisher({"port": peer.port, "reconnectMin": 20, "reconnectMax": 50,
                             "connectTimeout": 200}, gateway_id="gw1")
        with pub:
            assert_failures_reported(pub, caplog, reason)
        assert peer.accepted >= 3  # the TCP connections did succeed
    # every attempt is in the debug log, numbered
    assert len(failures(caplog, logging.DEBUG)) == pub.stats()["connectFailures"]


def test_refused_port_is_a_failed_connect(
    caplog: pytest.LogCaptureFixture, free_tcp_port: int
) -> None:
    with MqttPublisher({"port": free_tcp_port, "reconnectMin": 20, "reconnectMax": 50},
                       gateway_id="gw1") as pub:
        assert_failures_reported(pub, caplog, r"connection refused")


def test_a_broker_that_refuses_us_is_a_failed_connect_logged_once(
    caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    with Mosquitto(tmp_path / "broker", extra_config=["allow_anonymous false"]) as broker, \
            MqttPublisher({"port": broker.port, "reconnectMin": 20, "reconnectMax": 50},
                          gateway_id="gw1") as pub:
        assert_failures_reported(pub, caplog, r"the broker refused the connection: "
                                               r"Not authorized")
        wait_for(lambda: pub.stats()["connectFailures"] >= 10, what="10 refusals")
        assert len(failures(caplog)) == 1  # not one error per attempt
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_plain_client_on_a_tls_port_and_tls_client_on_a_plain_port_are_reported(
    caplog: pytest.LogCaptureFixture, tls_broker: tuple[Mosquitto, int, Path]
) -> None:
    broker, tls_port, ca = tls_broker
    with MqttPublisher({"port": tls_port, "reconnectMin": 20, "reconnectMax": 50},
                       gateway_id="gw1") as pub:
        assert_failures_reported(pub, caplog, r"closed before the broker answered CONNECT; "
                                               r"is the port TLS-only \(set mqtt.tls\)\?")
    caplog.clear()
    tls = {"caFile": str(ca)}
    with MqttPublisher({"port": broker.port, "tls": tls, "reconnectMin": 20,
                        "reconnectMax": 50}, gateway_id="gw1") as pub:
        assert_failures_reported(pub, caplog, r"(TLS handshake failed|connection reset).* "
                                               r"\(mqtt.tls is on: does this port speak TLS\?\)")
    caplog.clear()
    with MqttPublisher({"port": tls_port, "tls": {}, "reconnectMin": 20, "reconnectMax": 50},
                       gateway_id="gw1") as pub:  # the system's CAs: ours is self-signed
        assert_failures_reported(pub, caplog, r"TLS certificate check failed: self[- ]signed "
                                               r"certificate; retrying")
    # and TLS where TLS is spoken connects
    with MqttPublisher({"port": tls_port, "tls": tls}, gateway_id="gw1") as pub:
        assert pub.wait_connected(10), broker.log_text
        assert pub.stats()["connectFailures"] == 0


def test_connect_failures_are_logged_at_most_once_per_interval_with_counts(
    caplog: pytest.LogCaptureFixture, broker: Mosquitto
) -> None:
    caplog.set_level(logging.INFO, logger="edgemodbus.mqtt")
    broker.stop()  # its port now refuses
    settings = {"port": broker.port, "reconnectMin": 20, "reconnectMax": 20,
                "failureLogInterval": 1000}
    with MqttPublisher(settings, gateway_id="gw1") as pub:
        started = time.monotonic()
        wait_for(lambda: len(failures(caplog)) >= 3, timeout=10, what="3 warnings")
        elapsed = time.monotonic() - started
        lines = failures(caplog)
        total = pub.stats()["connectFailures"]
        assert total >= 20, total  # ~50 attempts a second, far fewer lines
        assert len(lines) <= 2 + elapsed / 1.0, lines
        assert "connection failed: connection refused" in lines[0]
        reported = 1
        for line in lines[1:]:
            found = re.search(r"still failing: connection refused \((\d+) failed attempts "
                              r"since the last report, (\d+) in all\)", line)
            assert found, line
            reported += int(found.group(1))
            assert int(found.group(2)) == reported
        assert reported <= total
        broker.restart()
        assert pub.wait_connected(10)
        done = pub.stats()["connectFailures"]
        wait_for(lambda: any(f"after {done} failed attempts" in r.getMessage()
                             for r in caplog.records), what="the connected line")


@pytest.mark.parametrize("field", ["caFile", "certFile", "keyFile"])
def test_tls_file_problems_name_the_field_the_path_and_what_is_wrong(
    tmp_path: Path, field: str
) -> None:
    cert, key = self_signed_cert(tmp_path / "tls")
    good = {"caFile": str(cert), "certFile": str(cert), "keyFile": str(key)}
    (tmp_path / "dir.pem").mkdir()
    (tmp_path / "text.pem").write_text("not PEM at all\n")
    cases = {
        str(tmp_path / "missing.pem"): "no such file",
        str(tmp_path / "dir.pem"): "is a directory, not a file",
        str(tmp_path / "text.pem"): "no PEM (certificate|private key) in it",
    }
    for path, problem in cases.items():
        tls = TlsSettings.model_validate({**good, field: path})
        found = [str(p) for p in tls.problems()]
        assert len(found) == 1 and re.fullmatch(
            rf"mqtt\.tls\.{field} '{re.escape(path)}': {problem}", found[0]), found
        # the publisher refuses to start with them, naming the field
        pub = MqttPublisher({"tls": {**good, field: path}}, gateway_id="gw1")
        with pytest.raises(ConfigError, match=rf"mqtt\.tls\.{field} "):
            pub.start()
        pub.stop()
    assert TlsSettings.model_validate(good).problems() == []
    assert TlsSettings.model_validate({field: str(tmp_path / "missing.pem"),
                                       "enabled": False}).problems() == []


def test_tls_key_problems_are_named(tmp_path: Path) -> None:
    cert, key = self_signed_cert(tmp_path / "a")
    _, other_key = self_signed_cert(tmp_path / "b")
    found = [str(p) for p in TlsSettings.model_validate({"keyFile": str(key)}).problems()]
    assert found == [f"mqtt.tls.keyFile '{key}': needs certFile (the client certificate "
                     "of this key)"]
    found = [str(p) for p in TlsSettings.model_validate(
        {"certFile": str(cert), "keyFile": str(other_key)}).problems()]
    assert found == [f"mqtt.tls.certFile/keyFile '{cert}, {other_key}': the key does not "
                     "belong to the certificate"]
    found = [str(p) for p in TlsSettings.model_validate({"certFile": str(cert)}).problems()]
    assert found == [f"mqtt.tls.certFile '{cert}': no PEM private key in it (keyFile is not "
                     "set, so the key must be in certFile)"]
    if os.geteuid() != 0:  # root reads any file: no permission error to see
        key.chmod(0)
        found = [str(p) for p in TlsSettings.model_validate(
            {"certFile": str(cert), "keyFile": str(key)}).problems()]
        assert found and "not readable by this process" in found[0], found


def test_a_password_protected_broker_takes_our_credentials_and_never_sees_them_shown(
    tmp_path: Path, slave: PymodbusSlave, caplog: pytest.LogCaptureFixture
) -> None:
    """mosquitto with a password file and no anonymous access: the right password
    connects and publishes; a wrong one is a failed connect; neither password shows in
    a log line, the settings' repr or their to_dict()."""
    caplog.set_level(logging.DEBUG, logger="edgemodbus")
    secret, wrong = "s3cret-Passw0rd", "guessed-Passw0rd"
    pw_file = tmp_path / "passwords"
    subprocess.run(["mosquitto_passwd", "-c", "-b", str(pw_file), "gw", secret], check=True,
                   capture_output=True)
    pw_file.chmod(0o600)
    extra = ["allow_anonymous false", f"password_file {pw_file}"]
    with Mosquitto(tmp_path / "broker", extra_config=extra) as broker:
        cfg = device(slave.port)
        with Gateway(broker.port, cfg, username="gw", password=secret) as gw:
            wait_for(lambda: gw.pub.stats()["connected"]
                     and gw.pub.stats()["devices"]["dev1"]["published"] >= 8,
                     what="connected with the password, item updates published")
            settings = gw.pub.settings
            assert secret not in repr(settings) and secret not in json.dumps(settings.to_dict())
            assert settings.to_dict(secrets=True)["password"] == secret
        with Gateway(broker.port, device(slave.port, code="dev2"), username="gw",
                     password=wrong) as gw:
            wait_for(lambda: gw.pub.stats()["connectFailures"] >= 1, what="a failed connect")
            assert not gw.pub.stats()["connected"]
    logged = "\n".join(r.getMessage() for r in caplog.records)
    assert secret not in logged and wrong not in logged
    assert MqttSettings.load({"password": None}).password is None  # as examples/ writes it
