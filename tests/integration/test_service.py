"""The gateway service as users run it: ``python -m edgemodbus.gateway`` in its own process,
a config folder, a real mosquitto, a pymodbus slave, signals."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.gateway import load_gateway_config
from tests.gateway_proc import GatewayProcess, scrape, write_json
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, default_register, free_port

P = "edgemodbus"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2, 3), size=200) as peer:
        yield peer


def device_file(port: int, unit: int, tags: int = 3, code: str | None = None,
                **comm: Any) -> dict[str, Any]:
    org: dict[str, Any] = {"deviceCode": code} if code else {}
    return {
        "organization": org,
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": unit, "readCycle": 100, "readTimeout": 1000, "byteTimeout": 50,
            "retries": 0, "offlineAfterFailedCycles": 1, **comm,
        },
        "addressList": [
            {"name": f"t{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"}
            for i in range(tags)
        ],
    }


Service = GatewayProcess  # python -m edgemodbus.gateway in a child process, reaped


def gateway_file(conf: Path, broker: Mosquitto, **mqtt: Any) -> None:
    write_json(conf / "gateway.json", {
        "gatewayId": "gw-test",
        "mqtt": {"port": broker.port, "reconnectMin": 100, "reconnectMax": 500,
                 "statusCheckInterval": 100, **mqtt},
        "metrics": {"port": 0},
        "statusCheckInterval": 100,
    })


def test_service_polls_publishes_reloads_and_stops_cleanly(
    tmp_path: Path, broker: Mosquitto, slave: PymodbusSlave
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    gateway_file(conf, broker)
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    write_json(conf / "boiler.json", device_file(slave.port, 2))  # named after the file
    with MqttProbe(broker.port) as probe, Service(conf, tmp_path / "service.log") as svc:
        for code, unit in (("dev1", 1), ("boiler", 2)):
            for i in range(3):
                msg = probe.wait_for(f"{P}/{code}/t{i}", timeout=20)
                assert msg.json()["value"] == default_register(unit, "hr", i)
        assert probe.wait_for(f"{P}/$gateway/gw-test").json()["status"] == "online"
        port = int(svc.wait_log(r"metrics on http://127\.0\.0\.1:(\d+)/metrics").rsplit(":", 1)[1]
                   .split("/")[0])
        text = scrape(port)
        assert re.search(r'edgemodbus_cycles_total\{device="dev1",line="rtu-over-tcp://'
                         r'127\.0\.0\.1:\d+"\} [1-9]', text)
        assert "edgemodbus_mqtt_connected 1.0" in text

        # SIGHUP 1: dev1 gains an item (update_addresses, no restart); boiler's cycle
        # changes (restart of boiler alone); dev3 appears; a broken file is reported
        dev1 = device_file(slave.port, 1, tags=4, code="dev1")
        write_json(conf / "dev1.json", dev1)
        write_json(conf / "boiler.json", device_file(slave.port, 2, readCycle=150))
        write_json(conf / "dev3.json", device_file(slave.port, 3, code="dev3"))
        (conf / "broken.json").write_text('{"communication": {"slaveId": 999}}')
        svc.signal(signal.SIGHUP)
        svc.wait_log(r"dev1: address list updated from dev1\.json \(4 items, 0 actions\)")
        svc.wait_log(r"boiler: restarted from boiler\.json")
        svc.wait_log(r"dev3: started from dev3\.json")
        svc.wait_log(r"broken\.json: invalid, not started")
        assert "slaveId 999" in svc.log
        assert probe.wait_for(f"{P}/dev1/t3").json()["value"] == default_register(1, "hr", 3)
        assert probe.wait_for(f"{P}/dev3/t2").json()["value"] == default_register(3, "hr", 2)
        assert not svc.lines(r"dev1: (stopped|restarted|started)")[1:]  # started once only

        # one log line per status change, none per value
        mark = len(svc.log.splitlines())
        slave.set_offline(3)
        svc.wait_log(r"dev3: Running -> Offline")
        for n in range(5):
            slave.set_registers(1, "hr", 0, [100 + n])
            probe.wait_for(f"{P}/dev1/t0", lambda m, n=n: m.json()["value"] == 100 + n)
        slave.set_offline(3, False)
        svc.wait_log(r"dev3: Offline -> Running")
        new = svc.log.splitlines()[mark:]
        assert len([ln for ln in new if "dev3: Running -> Offline" in ln]) == 1
        assert not [ln for ln in new if "dev1" in ln], new

        # SIGHUP 2: dev3's file removed: stopped, its last status retained
        (conf / "dev3.json").unlink()
        svc.signal(signal.SIGHUP)
        svc.wait_log(r"dev3: stopped \(dev3\.json removed\)")
        probe.wait_for(f"{P}/dev3/$status", lambda m: m.json()["status"] == "Stopped")

        # SIGTERM while a request is in flight: stop within the response timeout (1 s)
        slave.set_response_delay(0.6)
        time.sleep(0.3)  # pacing: a request in flight (0.6 s delay)
        sent = time.monotonic()
        svc.signal(signal.SIGTERM)
        assert svc.wait(15) == 0
        exited = time.monotonic() - sent
        stopped_ms = int(svc.wait_log(r"stopped in (\d+) ms").rsplit(" ", 2)[-2])
        assert stopped_ms <= 1000 + 200, svc.log
        assert exited < 5.0
        offline = probe.wait_for(f"{P}/$gateway/gw-test",
                                 lambda m: m.json()["status"] == "offline")
        assert offline.json()["reason"] == "shutdown"
        for code in ("dev1", "boiler"):
            probe.wait_for(f"{P}/{code}/$status", lambda m: m.json()["status"] == "Stopped")
    with MqttProbe(broker.port) as late:  # what a dashboard connecting now is told
        msg = late.wait_for(f"{P}/$gateway/gw-test")
        assert msg.retain and msg.json()["status"] == "offline"
        assert late.wait_for(f"{P}/dev1/$status").json()["status"] == "Stopped"
    print(f"SIGTERM: service stopped in {stopped_ms} ms, process gone after {exited:.2f} s")


def test_killed_gateway_is_marked_offline_by_its_last_will(
    tmp_path: Path, broker: Mosquitto, slave: PymodbusSlave
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    gateway_file(conf, broker)
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    with MqttProbe(broker.port) as probe, Service(conf, tmp_path / "service.log") as svc:
        probe.wait_for(f"{P}/$gateway/gw-test", lambda m: m.json()["status"] == "online",
                       timeout=20)
        probe.wait_for(f"{P}/dev1/t0")
        mark = probe.mark()
        svc.signal(signal.SIGKILL)
        svc.wait()
        will = probe.wait_for(f"{P}/$gateway/gw-test", after=mark, timeout=10)
        assert will.json() == {"gatewayId": "gw-test", "status": "offline", "reason": "lost"}
    with MqttProbe(broker.port) as late:  # retained for whoever comes later
        msg = late.wait_for(f"{P}/$gateway/gw-test")
        assert msg.retain and msg.json()["status"] == "offline"


def test_example_gateway_file_loads() -> None:
    cfg = load_gateway_config(REPO / "examples" / "gateway.json")  # TLS files checked too
    assert cfg.gateway_id == "gw-line3" and cfg.mqtt is not None and cfg.metrics is not None
    assert cfg.mqtt.qos == 0 and cfg.metrics.port == 9108
    # TLS is shown but off: the example runs against a local plain broker as shipped
    assert cfg.mqtt.tls is not None and not cfg.mqtt.tls.enabled
    assert (cfg.mqtt.host, cfg.mqtt.port) == ("127.0.0.1", 1883)


def test_shipped_example_gateway_file_works_against_a_plain_broker(
    tmp_path: Path, broker: Mosquitto, slave: PymodbusSlave
) -> None:
    """examples/gateway.json with only the ports changed (tests use free ports)."""
    conf = tmp_path / "conf"
    conf.mkdir()
    example = json.loads((REPO / "examples" / "gateway.json").read_text())
    example["mqtt"]["port"] = broker.port
    example["metrics"].update(host="127.0.0.1", port=0)
    write_json(conf / "gateway.json", example)
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    with MqttProbe(broker.port) as probe, Service(conf, tmp_path / "service.log") as svc:
        msg = probe.wait_for("plant1/$gateway/gw-line3", timeout=20)
        assert msg.json()["status"] == "online"
        probe.wait_for("plant1/dev1/t0")
        svc.signal(signal.SIGTERM)
        assert svc.wait() == 0
    assert "ERROR" not in svc.log and "connection failed" not in svc.log, svc.log


@pytest.mark.parametrize("field, value, problem", [
    ("caFile", "/nonexistent/ca.pem", "'/nonexistent/ca.pem': no such file"),
    ("caFile", "ca.pem", "'{conf}/ca.pem': no such file"),  # relative: from the file's folder
    ("caFile", ".", "'{conf}': is a directory, not a file"),
    ("certFile", "client.pem", "'{conf}/client.pem': no such file"),
    ("keyFile", "key.pem", "'{conf}/key.pem': no such file"),
])
def test_tls_file_problems_stop_the_service_before_it_connects(
    tmp_path: Path, field: str, value: str, problem: str
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "gateway.json", {"gatewayId": "gw", "mqtt": {
        "port": free_port(), "tls": {field: value}}})
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.gateway", "--config-dir", str(conf)],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert result.returncode == 2
    expected = problem.format(conf=str(conf).rstrip("/"))
    assert f"{conf / 'gateway.json'}: mqtt.tls.{field} {expected}" in result.stderr, (
        result.stderr)
    assert "Errno" not in result.stderr and "connect" not in result.stderr


@pytest.mark.parametrize("command", [
    ["edgemodbus.cli", "-v", "run"],  # edgemodbus run --config-dir DIR --seconds N
    ["edgemodbus.gateway"],
])
def test_config_dir_service_stops_by_itself_after_seconds(
    tmp_path: Path, slave: PymodbusSlave, command: list[str]
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", *command, "--config-dir", str(conf), "--seconds", "1"],
        capture_output=True, text=True, timeout=20, cwd=REPO,
    )
    took = time.monotonic() - started
    assert result.returncode == 0, result.stderr
    assert "dev1: started from dev1.json" in result.stderr
    assert "1 s elapsed (--seconds)" in result.stderr and "stopped in" in result.stderr
    assert 1.0 <= took < 15.0
    assert slave.request_count(1) > 0  # it did poll meanwhile
    result = subprocess.run(
        [sys.executable, "-m", *command, "--config-dir", str(conf), "--seconds", "-1"],
        capture_output=True, text=True, timeout=20, cwd=REPO,
    )
    assert result.returncode == 2
    assert "--seconds -1.0: must be >= 0 (0: run until a signal)" in result.stderr


def test_sighup_reports_a_broken_gateway_file_and_applies_a_valid_change(
    tmp_path: Path, broker: Mosquitto, slave: PymodbusSlave
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    gateway_file(conf, broker)
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    with MqttProbe(broker.port) as probe, Service(conf, tmp_path / "service.log") as svc:
        probe.wait_for(f"{P}/dev1/t0", timeout=20)
        port = metrics_port(svc.wait_log(r"metrics on http://"))
        gw = str(conf / "gateway.json")

        # broken: reported with file and field, the running settings kept
        write_json(conf / "gateway.json", {"gatewayId": "gw-test", "mqtt": {"qos": 7}})
        svc.signal(signal.SIGHUP)
        svc.wait_log(rf"{re.escape(gw)}: invalid, keeping the running gateway settings")
        svc.wait_log(r"^mqtt\.qos 7: must be 0 or 1 or 2")
        # a TLS file that is not there: the same
        gateway_file(conf, broker, tls={"caFile": "missing.pem"})
        svc.signal(signal.SIGHUP)
        svc.wait_log(rf"mqtt\.tls\.caFile '{re.escape(str(conf))}/missing\.pem': no such file")
        # ...and the device kept polling and publishing where it did, metrics where they were
        slave.set_registers(1, "hr", 0, [111])
        probe.wait_for(f"{P}/dev1/t0", lambda m: m.json()["value"] == 111)
        assert "edgemodbus_mqtt_connected 1.0" in scrape(port)

        # valid change: MQTT (prefix, gateway id) and metrics port applied live
        new_port = free_port()
        mark = probe.mark()
        mqtt = {"port": broker.port, "topicPrefix": "plant2", "reconnectMin": 100,
                "statusCheckInterval": 100}
        write_json(conf / "gateway.json", {
            "gatewayId": "gw-two", "mqtt": mqtt, "metrics": {"port": new_port},
        })
        svc.signal(signal.SIGHUP)
        applied = svc.wait_log(r"gateway settings applied: ")
        assert f"metrics on http://127.0.0.1:{new_port}/metrics" in applied
        assert "MQTT publisher restarted" in applied and "gateway gw-two" in applied
        old = probe.wait_for(f"{P}/$gateway/gw-test", after=mark,
                             match=lambda m: m.json()["status"] == "offline")
        assert old.json()["reason"] == "reconfigure"
        probe.wait_for("plant2/$gateway/gw-two", lambda m: m.json()["status"] == "online")
        probe.wait_for("plant2/dev1/$status", lambda m: m.json()["status"] == "Running")
        slave.set_registers(1, "hr", 0, [222])
        probe.wait_for("plant2/dev1/t0", lambda m: m.json()["value"] == 222)
        text = scrape(new_port)
        assert re.search(r'edgemodbus_cycles_total\{device="dev1"', text)
        assert "edgemodbus_mqtt_connected 1.0" in text
        with pytest.raises(OSError):
            scrape(port)

        # mqtt.snapshotInterval: the devices that take theirs from it restart
        write_json(conf / "gateway.json", {
            "gatewayId": "gw-two", "mqtt": {**mqtt, "snapshotInterval": 200},
            "metrics": {"port": new_port},
        })
        svc.signal(signal.SIGHUP)
        svc.wait_log(r"gateway settings applied: snapshotInterval 200 ms: 1 devices restarted")
        probe.wait_for("/real/dev1", lambda m: m.json()["gatewayId"] == "gw-two")
        assert len(svc.lines(r"dev1: restarted")) == 1  # only now, not before
        assert not svc.lines(r"ERROR (?!edgemodbus\.service: \S+/gateway\.json: invalid, "
                             r"keeping the running gateway settings:$)")
        svc.signal(signal.SIGTERM)
        assert svc.wait() == 0


def test_sighup_applies_a_gateway_file_that_appeared_and_reports_a_busy_metrics_port(
    tmp_path: Path, slave: PymodbusSlave
) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, code="dev1"))
    with Service(conf, tmp_path / "service.log") as svc:
        svc.wait_log(r"dev1: started from dev1\.json")
        # no gateway file at start; one appears: the gateway's, not a device file
        write_json(conf / "gateway.json", {"gatewayId": "gw", "metrics": {"port": 0}})
        svc.signal(signal.SIGHUP)
        port = metrics_port(svc.wait_log(r"gateway settings applied: metrics on http://"))
        assert 'device="dev1"' in scrape(port)
        # a port that is taken: reported, the running exporter kept
        with socket.create_server(("127.0.0.1", 0)) as taken:
            busy = taken.getsockname()[1]
            write_json(conf / "gateway.json", {"gatewayId": "gw", "metrics": {"port": busy}})
            svc.signal(signal.SIGHUP)
            svc.wait_log(rf"gateway\.json: not applied, keeping the running gateway settings: "
                         rf"metrics: cannot listen on 127\.0\.0\.1:{busy}: ")
        port = metrics_port(svc.lines(r"metrics on http://")[-1])
        assert 'device="dev1"' in scrape(port)
        assert not svc.lines(r"gateway\.json: invalid|dev1: (stopped|restarted)")
        svc.signal(signal.SIGTERM)
        assert svc.wait() == 0


def metrics_port(line: str) -> int:
    found = re.search(r"metrics on http://[\d.]+:(\d+)/metrics", line)
    assert found, line
    return int(found.group(1))


def test_bad_gateway_file_is_refused_with_the_field_named(tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "gateway.json", {"gatewayId": "gw", "mqtt": {"qos": 5}})
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.gateway", "--config-dir", str(conf)],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert result.returncode == 2
    assert "mqtt.qos 5: must be 0 or 1 or 2" in result.stderr
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.gateway", "--config-dir", str(tmp_path / "nope")],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert result.returncode == 2 and "not a directory" in result.stderr


def test_the_old_module_name_still_runs_the_service_and_says_it_is_deprecated() -> None:
    """Installed systemd units name ``python -m edgemodbus.service``: it must keep working."""
    out = subprocess.run(
        [sys.executable, "-m", "edgemodbus.service", "--help"],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "--config-dir" in out.stdout
    assert "deprecated: use python -m edgemodbus.gateway" in out.stderr
