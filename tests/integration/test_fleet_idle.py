"""An idle fleet instance costs nothing per device file (issue #28, docs/deploy.md "What
the fleet costs"): a gateway with MQTT on, in a fleet, with listen-mode DTU files and no
DTU connected, reads no device's status and asks no DTU slot whether it is held while
nothing happens.  Before, the service's main loop (gateway/run.py ``check_statuses``)
and the MQTT thread (``_check_statuses``) each read every device's status every
``statusCheckInterval``: 2 x 10 reads per file per second at 100 ms here.

The counts are of the per-device functions themselves (the driver's status property and
the DTU registry's ``connected``), over the same window, with 40 and with 400 files:
events (there are none here) would be counted too, per-tick looks would grow tenfold."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.driver import DriverModbusRtu
from edgemodbus.gateway import Gateway, load_gateway_config
from edgemodbus.line.dtu_registry import DtuRegistry
from edgemodbus.northbound.metrics import MetricsExporter
from tests.fleet_gateways import Timing, device
from tests.gateway_proc import write_json
from tests.mosquitto import Mosquitto
from tests.peers import free_port
from tests.waiting import wait_for

TICK = 0.1  # statusCheckInterval: the main loop's and the MQTT thread's period
WINDOW = 1.5  # seconds counted: 15 ticks


class Counts:
    """Calls of the per-device functions, by name (any thread; a GIL-atomic add)."""

    def __init__(self) -> None:
        self.calls: dict[str, int] = {"status": 0, "connected": 0}

    def total(self) -> int:
        return sum(self.calls.values())


@contextmanager
def counting(monkeypatch: pytest.MonkeyPatch) -> Iterator[Counts]:
    counts = Counts()
    status = DriverModbusRtu.device_driver_status
    assert isinstance(status, property) and status.fget is not None
    status_get: Callable[[DriverModbusRtu], Any] = status.fget
    connected = DtuRegistry.connected

    def counted_status(self: DriverModbusRtu) -> Any:
        counts.calls["status"] += 1
        return status_get(self)

    def counted_connected(self: DtuRegistry, host: str, port: int, dtu_id: str) -> bool:
        counts.calls["connected"] += 1
        return connected(self, host, port, dtu_id)

    monkeypatch.setattr(DriverModbusRtu, "device_driver_status", property(counted_status))
    monkeypatch.setattr(DtuRegistry, "connected", counted_connected)
    yield counts


def idle_calls(folder: Path, broker: int, files: int, counts: Counts) -> tuple[int, bytes]:
    """Calls of the per-device functions in WINDOW seconds of an idle instance with
    ``files`` listen-mode DTU files (none connected), its main loop run as run.py runs
    it (check_statuses every tick); and then its metrics text."""
    folder.mkdir()
    listen, timing = free_port(), Timing(files)
    write_json(folder / "gateway.json", {
        "gatewayId": "idle",
        "mqtt": {"port": broker, "reconnectMin": 100, "reconnectMax": 1000,
                 "statusCheckInterval": int(TICK * 1000)},
        "fleet": {"instanceId": "gw-1", "loadBalancers": ["127.0.0.1"]},
        "metrics": {"host": "127.0.0.1", "port": 0},
        "statusCheckInterval": int(TICK * 1000)})
    for n in range(files):
        write_json(folder / f"m{n}.json", device(n, listen, timing))
    gateway_file = folder / "gateway.json"
    gateway = Gateway(folder, load_gateway_config(gateway_file), gateway_file)
    try:
        gateway.start()
        assert len(gateway.devices) == files
        publisher = gateway.publisher
        assert publisher is not None
        wait_for(lambda: getattr(publisher, "connected", False), timeout=30,
                 what="the publisher connected")

        # start-up: each status is looked at once (the new connection); let those end,
        # sampling three ticks at a time for at most 10 s (a per-tick cost never ends:
        # then the window below counts it)
        quiet_until = time.monotonic() + 10
        while time.monotonic() < quiet_until:
            before = counts.total()
            for _ in range(3):
                time.sleep(TICK)  # pacing: run.py's tick
                gateway.check_statuses()
            if counts.total() - before < files:
                break
        before = counts.total()
        end = time.monotonic() + WINDOW
        while time.monotonic() < end:  # run.py's loop: a wait, then check_statuses
            time.sleep(TICK)  # pacing: run.py's tick
            gateway.check_statuses()
        calls = counts.total() - before
        assert gateway.exporter is not None
        return calls, gateway.exporter.render()
    finally:
        gateway.stop()


def test_an_idle_fleet_instance_does_no_work_per_device_file(
        tmp_path: Path, broker: Mosquitto, monkeypatch: pytest.MonkeyPatch) -> None:
    with counting(monkeypatch) as counts:
        few, few_text = idle_calls(tmp_path / "few", broker.port, 40, counts)
        many, many_text = idle_calls(tmp_path / "many", broker.port, 400, counts)
    # per-tick looks: 2 x 15 reads per file in the window (1,200 and 12,000); events:
    # none while idle.  A few stray calls are allowed, none that grow with the files.
    assert many <= few + 40, (few, many)
    assert many < 400, (few, many)
    # a scrape: no series of a device held elsewhere (was ~6 kB a file), the held gauge
    assert len(many_text) <= len(few_text) + 100, (len(few_text), len(many_text))  # counts' digits
    assert b'device="m1"' not in many_text
    assert b'edgemodbus_dtu_held{instance="gw-1"} 0.0' in many_text
    assert b"edgemodbus_dtu_listener_dtus" in many_text


class Source:
    """A driver's face to the exporter (northbound/metrics.py StatsSource)."""

    device_driver_status = DeviceDriverStatus.RUNNING
    data_item_count = 2

    def stats(self) -> dict[str, Any]:
        return {"cycles": 3, "responses": 6}


def test_a_fleet_device_exports_its_series_only_while_held() -> None:
    exporter = MetricsExporter({"port": 0}, gateway_id="gw")
    here = [False]
    exporter.attach(Source(), "held", "dtu", held=lambda: here[0])
    exporter.attach(Source(), "lone", "com1")  # not in a fleet: always exported
    text = exporter.render().decode()
    assert 'device="held"' not in text
    assert 'edgemodbus_items{device="lone",line="com1"} 2.0' in text
    here[0] = True
    text = exporter.render().decode()
    assert 'edgemodbus_items{device="held",line="dtu"} 2.0' in text
    assert 'edgemodbus_device_status{device="held",line="dtu",status="Running"} 1.0' in text
