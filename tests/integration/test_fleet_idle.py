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

from edgemodbus.driver import DriverModbusRtu
from edgemodbus.gateway import Gateway, load_gateway_config
from edgemodbus.line.dtu_registry import DtuRegistry
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


def idle_calls(folder: Path, broker: int, files: int, counts: Counts) -> int:
    """Calls of the per-device functions in WINDOW seconds of an idle instance with
    ``files`` listen-mode DTU files (none connected), its main loop run as run.py runs
    it (check_statuses every tick)."""
    folder.mkdir()
    listen, timing = free_port(), Timing(files)
    write_json(folder / "gateway.json", {
        "gatewayId": "idle",
        "mqtt": {"port": broker, "reconnectMin": 100, "reconnectMax": 1000,
                 "statusCheckInterval": int(TICK * 1000)},
        "fleet": {"instanceId": "gw-1", "loadBalancers": ["127.0.0.1"]},
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
                time.sleep(TICK)
                gateway.check_statuses()
            if counts.total() - before < files:
                break
        before = counts.total()
        end = time.monotonic() + WINDOW
        while time.monotonic() < end:  # run.py's loop: a wait, then check_statuses
            time.sleep(TICK)
            gateway.check_statuses()
        return counts.total() - before
    finally:
        gateway.stop()


def test_an_idle_fleet_instance_does_no_work_per_device_file(
        tmp_path: Path, broker: Mosquitto, monkeypatch: pytest.MonkeyPatch) -> None:
    with counting(monkeypatch) as counts:
        few = idle_calls(tmp_path / "few", broker.port, 40, counts)
        many = idle_calls(tmp_path / "many", broker.port, 400, counts)
    # per-tick looks: 2 x 15 reads per file in the window (1,200 and 12,000); events:
    # none while idle.  A few stray calls are allowed, none that grow with the files.
    assert many <= few + 40, (few, many)
    assert many < 400, (few, many)
