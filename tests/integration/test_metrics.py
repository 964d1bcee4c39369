"""Prometheus endpoint: scraped over real HTTP while drivers poll a pymodbus slave."""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.gateway import Gateway, GatewayConfig
from edgemodbus.line.dtu_newcomer import COUNTERS
from edgemodbus.northbound.metrics import DTU_LISTENER_EVENTS, MetricsExporter, MetricsSettings
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.sim import Simulator
from tests.engines import with_engine
from tests.peers import ExceptionRange, PymodbusSlave, free_port
from tests.waiting import wait_for

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    ranges = [ExceptionRange(50, 51, code=4, unit=1)]  # one block answers "device failure"
    with PymodbusSlave("rtu-over-tcp", units=(1, 2), size=200,
                       exception_ranges=ranges) as peer:
        yield peer


def start(port: int, slave_id: int, code: str, **comm: Any) -> em.DriverModbusRtu:
    cfg = em.load_device_config({
        "organization": {"deviceCode": code},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave_id, "readCycle": 50, "readTimeout": 150, "retries": 0,
            "byteTimeout": 50, "maxMergeAddressGap": 0, **comm,
        },
        "addressList": [
            {"name": "a", "address": "hr:0", "deviceDataType": "UInt16"},
            {"name": "b", "address": "hr:50", "deviceDataType": "UInt16"},
        ],
    })
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    return drv


def scrape(port: int) -> tuple[str, Samples]:
    """GET /metrics with a real HTTP client; samples keyed by (name, sorted labels)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        assert resp.status == 200
        assert resp.headers["Content-Type"].startswith("text/plain")
        text = resp.read().decode()
    samples: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return text, samples


def lbl(**labels: str) -> tuple[tuple[str, str], ...]:
    return tuple(sorted(labels.items()))


def test_scrape_reports_device_and_line_counters_from_stats(slave: PymodbusSlave) -> None:
    line = f"rtu-over-tcp://127.0.0.1:{slave.port}"
    ok = start(slave.port, 1, "dev1")
    silent = start(slave.port, 3, "dev3", offlineAfterFailedCycles=1000)  # nobody at 3
    exporter = MetricsExporter({"port": 0})
    publisher = MqttPublisher({"port": free_port()}, gateway_id="gw")  # never started
    try:
        exporter.attach(ok, "dev1", line)
        publisher.attach(ok, "dev1")  # not connected: updates wait in its queue
        exporter.attach(silent, None, line)  # the code comes from the driver
        exporter.set_publisher(publisher)
        port = exporter.start()
        slave.set_registers(1, "hr", 0, [777])  # one update for the publisher's queue
        deadline = time.monotonic() + 10
        while (ok.stats().get("cycles", 0) < 5 or silent.stats().get("timeouts", 0) < 3
               or publisher.stats()["queued"] < 1):
            assert time.monotonic() < deadline, "no progress"
            time.sleep(0.05)  # poll: until every count moved (deadline above)
        _, live = scrape(port)
        assert live[("edgemodbus_device_status", lbl(device="dev1", line=line,
                                                     status="Running"))] == 1
        assert live[("edgemodbus_device_status", lbl(device="dev1", line=line,
                                                     status="Offline"))] == 0
        ok.stop_device()
        silent.stop_device()
        text, samples = scrape(port)  # stopped drivers keep their counters: stable now
    finally:
        ok.stop_device()
        silent.stop_device()
        exporter.stop()
        publisher.stop()
    s1, s3 = ok.stats(), silent.stats()
    d1, d3 = lbl(device="dev1", line=line), lbl(device="dev3", line=line)
    for key, name in (("requests", "requests"), ("responses", "responses"),
                      ("timeouts", "timeouts"), ("cycles", "cycles"),
                      ("crcErrors", "crc_errors"), ("valuesChanged", "values_changed")):
        assert samples[(f"edgemodbus_{name}_total", d1)] == s1[key], name
        assert samples[(f"edgemodbus_{name}_total", d3)] == s3[key], name
    assert s1["requests"] > 0 and s3["timeouts"] > 0 and s3["responses"] == 0
    assert samples[("edgemodbus_exceptions_total", lbl(device="dev1", line=line, code="4"))] \
        == s1["exceptions"][4] > 0
    assert samples[("edgemodbus_device_status", lbl(device="dev1", line=line,
                                                    status="Stopped"))] == 1
    assert samples[("edgemodbus_items", d1)] == 2
    # cycle and round-trip time: exact count and sum
    assert samples[("edgemodbus_cycle_seconds_count", d1)] == s1["cycles"]
    assert samples[("edgemodbus_cycle_seconds_sum", d1)] == pytest.approx(
        s1["avgCycleTime"] * s1["cycles"])
    assert samples[("edgemodbus_round_trip_seconds_count", d1)] == s1["responses"]
    # the line once, with its own counters (both devices' requests)
    line_key = ("edgemodbus_line_requests_total", lbl(line=line))
    assert samples[line_key] == s1["line"]["requests"] >= s1["requests"] + s3["requests"] - 1
    assert samples[("edgemodbus_line_reconnects_total", lbl(line=line))] == \
        s1["line"]["reconnects"]
    assert text.count("edgemodbus_line_requests_total{") == 1
    # the publisher's counters
    mqtt = publisher.stats()
    assert samples[("edgemodbus_mqtt_connected", ())] == 0
    assert samples[("edgemodbus_mqtt_queue_depth", ())] == mqtt["queued"] > 0
    assert samples[("edgemodbus_mqtt_queue_size", ())] == 10_000
    assert samples[("edgemodbus_mqtt_published_total", lbl(device="dev1"))] == 0
    assert samples[("edgemodbus_mqtt_dropped_total", lbl(device="dev1"))] == 0


def test_histogram_buckets_are_used_when_stats_carry_them() -> None:
    class Source:
        device_driver_status = DeviceDriverStatus.RUNNING
        data_item_count = 3

        def stats(self) -> dict[str, Any]:
            return {
                "cycles": 10, "requests": 12, "avgCycleTime": 0.02, "responses": 12,
                "cycleTimeHistogram": {"buckets": [[0.01, 4], [0.05, 9], [float("inf"), 10]],
                                       "sum": 0.2, "count": 10},
                "line": {"requests": 12},
            }

    with MetricsExporter({"port": 0}) as exporter:
        exporter.attach(Source(), "fake", "line0")
        _, samples = scrape(exporter.port)
    base = {"device": "fake", "line": "line0"}
    assert samples[("edgemodbus_cycle_seconds_bucket", lbl(**base, le="0.01"))] == 4
    assert samples[("edgemodbus_cycle_seconds_bucket", lbl(**base, le="0.05"))] == 9
    assert samples[("edgemodbus_cycle_seconds_bucket", lbl(**base, le="+Inf"))] == 10
    assert samples[("edgemodbus_cycle_seconds_sum", lbl(**base))] == 0.2
    assert samples[("edgemodbus_requests_total", lbl(**base))] == 12


def parsed(text: bytes) -> tuple[dict[str, str], Samples]:
    """(family name -> type, samples) of rendered exposition text."""
    types: dict[str, str] = {}
    samples: Samples = {}
    for family in text_string_to_metric_families(text.decode()):
        types[family.name] = family.type
        for s in family.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return types, samples


class FakeListeners:
    """A listener-stats source: what DtuRegistry.stats() gives, or a failure."""

    def __init__(self, stats: dict[str, dict[str, int]]) -> None:
        self.ports = stats
        self.fail = False

    def stats(self) -> dict[str, dict[str, int]]:
        if self.fail:
            raise RuntimeError("listener gone")
        return self.ports


def test_dtu_listener_stats_are_a_counter_family_by_event_and_three_gauges() -> None:
    full = {event: n for n, event in enumerate(DTU_LISTENER_EVENTS, start=1)}
    source = FakeListeners({
        "0.0.0.0:9502": {**full, "unregistered": 7, "dtus": 120, "connected": 98},
        "[::]:9600": {"accepted": 3, "badKey": 2, "connected": 1, "somethingNew": 9},
    })
    exporter = MetricsExporter({"port": 0})
    exporter.set_listener_stats(source)
    types, samples = parsed(exporter.render())
    assert types["edgemodbus_dtu_listener_events"] == "counter"
    for gauge in ("unregistered", "dtus", "connected"):
        assert types[f"edgemodbus_dtu_listener_{gauge}"] == "gauge"
    events = {labels: v for (name, labels), v in samples.items()
              if name == "edgemodbus_dtu_listener_events_total"}
    assert events == {
        **{lbl(port="0.0.0.0:9502", event=e): float(n) for e, n in full.items()},
        lbl(port="[::]:9600", event="accepted"): 3.0,
        lbl(port="[::]:9600", event="badKey"): 2.0,  # the others are missing: not emitted
    }
    assert samples[("edgemodbus_dtu_listener_unregistered", lbl(port="0.0.0.0:9502"))] == 7
    assert samples[("edgemodbus_dtu_listener_dtus", lbl(port="0.0.0.0:9502"))] == 120
    assert samples[("edgemodbus_dtu_listener_connected", lbl(port="0.0.0.0:9502"))] == 98
    assert samples[("edgemodbus_dtu_listener_connected", lbl(port="[::]:9600"))] == 1
    assert ("edgemodbus_dtu_listener_dtus", lbl(port="[::]:9600")) not in samples
    assert not any("somethingNew" in str(k) for k in samples)
    exporter.set_listener_stats(None)
    types, _ = parsed(exporter.render())
    assert not any(name.startswith("edgemodbus_dtu_listener") for name in types)


def test_every_counter_of_the_listener_is_an_event() -> None:
    # the gauges are the other keys of DtuListener.stats (checked live below)
    assert set(DTU_LISTENER_EVENTS) == {*COUNTERS, "logSuppressed"}


@pytest.mark.parametrize("broken", ["raises", "not a number"])
def test_a_failing_listener_source_never_fails_the_scrape(
        broken: str, caplog: pytest.LogCaptureFixture) -> None:
    class Source:
        device_driver_status = DeviceDriverStatus.RUNNING
        data_item_count = 1

        def stats(self) -> dict[str, Any]:
            return {"cycles": 4, "requests": 4}

    source = FakeListeners({"127.0.0.1:9502": {"accepted": 5}})
    if broken == "raises":
        source.fail = True
    else:
        source.ports["127.0.0.1:9502"]["registered"] = "many"  # type: ignore[assignment]
    with MetricsExporter({"port": 0}) as exporter:
        exporter.attach(Source(), "dev", "line0")
        exporter.set_listener_stats(source)
        with caplog.at_level(logging.ERROR, logger="edgemodbus.metrics"):
            _, samples = scrape(exporter.port)  # HTTP 200, the device's families intact
    assert samples[("edgemodbus_requests_total", lbl(device="dev", line="line0"))] == 4
    assert not any(name.startswith("edgemodbus_dtu_listener") for name, _ in samples)
    assert "DTU listener stats() failed" in caplog.text


@pytest.mark.usefixtures("engine")
def test_the_gateway_exports_its_drivers_dtu_listen_ports(tmp_path: Path) -> None:
    listen = free_port()
    (tmp_path / "dtu.json").write_text(json.dumps({
        "organization": {"deviceCode": "dtu1"},
        "communication": with_engine({
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": listen, "dtuId": "A1", "registration": "text",
            "registrationTimeout": 5000, "readCycle": 100}),
        "addressList": [{"name": "a", "address": "hr:0", "deviceDataType": "UInt16"}],
    }), "utf-8")
    gateway = Gateway(tmp_path, GatewayConfig.model_validate({"metrics": {"port": 0}}))
    key = lbl(port=f"127.0.0.1:{listen}", event="accepted")
    try:
        gateway.start()
        assert "dtu.json" in {p.name for p in gateway.devices}
        exporter = gateway.exporter
        assert exporter is not None
        _, samples = scrape(exporter.port)
        assert samples[("edgemodbus_dtu_listener_events_total", key)] == 0
        port = lbl(port=f"127.0.0.1:{listen}")
        assert samples[("edgemodbus_dtu_listener_dtus", port)] == 1
        assert samples[("edgemodbus_dtu_listener_connected", port)] == 0
        assert {labels for name, labels in samples
                if name == "edgemodbus_dtu_listener_events_total"} \
            == {lbl(port=f"127.0.0.1:{listen}", event=e) for e in DTU_LISTENER_EVENTS}
        with socket.create_connection(("127.0.0.1", listen), timeout=5):
            wait_for(lambda: scrape(exporter.port)[1].get(
                ("edgemodbus_dtu_listener_events_total", key)) == 1, what="accepted 1")
            assert scrape(exporter.port)[1][("edgemodbus_dtu_listener_unregistered", port)] \
                == 1
        with Simulator(slaves=[1]) as sim:  # a DTU registers: its line reads through it
            sim.dial("127.0.0.1", listen, registration=b"A1\r\n")
            wait_for(lambda: scrape(exporter.port)[1].get(
                ("edgemodbus_dtu_listener_connected", port)) == 1, what="connected 1")
            driver = gateway.devices[tmp_path / "dtu.json"].driver
            wait_for(lambda: driver.stats()["responses"] >= 1, what="a reply via the DTU")
    finally:
        gateway.stop()


def test_the_gateway_exports_its_modbus_tcp_server(tmp_path: Path) -> None:
    gateway = Gateway(tmp_path, GatewayConfig.model_validate(
        {"metrics": {"port": 0}, "serve": {"listen": "127.0.0.1:0"}}))
    try:
        gateway.start()
        exporter, server = gateway.exporter, gateway.serving.server
        assert exporter is not None and server is not None
        at = lbl(listen=f"127.0.0.1:{server.port}")
        _, samples = scrape(exporter.port)
        assert samples[("edgemodbus_serve_accepted_total", at)] == 0
        assert samples[("edgemodbus_serve_connections", at)] == 0
        with socket.create_connection(("127.0.0.1", server.port), timeout=5):
            wait_for(lambda: scrape(exporter.port)[1].get(
                ("edgemodbus_serve_connections", at)) == 1, what="1 open connection")
            assert scrape(exporter.port)[1][("edgemodbus_serve_accepted_total", at)] == 1
    finally:
        gateway.stop()


def test_bad_metrics_settings_name_the_field() -> None:
    with pytest.raises(ConfigError, match=r"metrics\.port 70000: must be 0\.\.65535"):
        MetricsSettings.load({"port": 70000})


def test_importing_edgemodbus_loads_neither_paho_nor_prometheus() -> None:
    code = (
        "import sys, edgemodbus, edgemodbus.northbound.mqtt, edgemodbus.northbound.metrics, "
        "edgemodbus.gateway\n"
        "bad = [m for m in sys.modules if m.startswith(('paho', 'prometheus_client'))]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
