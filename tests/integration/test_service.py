"""The gateway service as users run it: ``python -m edgemodbus.service`` in its own process,
a config folder, a real mosquitto, a pymodbus slave, signals."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.service import load_gateway_config
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, default_register

P = "edgemodbus"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    with Mosquitto(tmp_path / "broker") as peer:
        yield peer


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


def write_json(path: Path, data: Any) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)  # atomic, as an editor or config tool should do it


class Service:
    """``python -m edgemodbus.service`` in a child process; always reaped."""

    def __init__(self, config_dir: Path, log_path: Path) -> None:
        self.config_dir = config_dir
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Service:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("JOURNAL_STREAM", None)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "edgemodbus.service", "--config-dir",
                 str(self.config_dir)],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log, cwd=REPO, env=env,
            )
        return self

    def __exit__(self, *exc: object) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait()

    @property
    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def lines(self, pattern: str) -> list[str]:
        return [ln for ln in self.log.splitlines() if re.search(pattern, ln)]

    def wait_log(self, pattern: str, timeout: float = 15.0, count: int = 1) -> str:
        deadline = time.monotonic() + timeout
        while True:
            found = self.lines(pattern)
            if len(found) >= count:
                return found[count - 1]
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"service exited ({self.proc.returncode}):\n{self.log}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no log line /{pattern}/ x{count}; log:\n{self.log}")
            time.sleep(0.05)

    def signal(self, signum: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(signum)

    def wait(self, timeout: float = 15.0) -> int:
        assert self.proc is not None
        return self.proc.wait(timeout)


def scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        return str(resp.read().decode())


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
        svc.wait_log(r"dev1: address list updated from dev1\.json \(4 items\)")
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
        time.sleep(0.3)
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
    cfg = load_gateway_config(REPO / "examples" / "gateway.json")
    assert cfg.gateway_id == "gw-line3" and cfg.mqtt is not None and cfg.metrics is not None
    assert cfg.mqtt.tls is not None and cfg.mqtt.qos == 0 and cfg.metrics.port == 9108


def test_bad_gateway_file_is_refused_with_the_field_named(tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "gateway.json", {"gatewayId": "gw", "mqtt": {"qos": 5}})
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.service", "--config-dir", str(conf)],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert result.returncode == 2
    assert "mqtt.qos 5: must be 0 or 1 or 2" in result.stderr
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.service", "--config-dir", str(tmp_path / "nope")],
        capture_output=True, text=True, timeout=60, cwd=REPO,
    )
    assert result.returncode == 2 and "not a directory" in result.stderr
