"""Backup endpoints (line/failover.py, docs/links.md): a line moves to its alternate
after failoverAfter failed connects, or failed cycles of every device, and back to the
primary once a probe of it succeeds; counted in the line's stats.  Real libmodbus,
pymodbus slaves in their own processes as the primary and the alternate."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import edgemodbus as em
from tests.conftest import SlaveFactory
from tests.integration.test_driver import Running
from tests.peers import PtyPair
from tests.waiting import wait_for

PRIMARY, ALTERNATE = 1111, 2222  # what hr:0 holds on each peer: who answered


def config(port: int, alt_port: int, **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
        "alternates": [f"127.0.0.1:{alt_port}"], "failoverAfter": 2,
        "failbackInterval": 300, "readTimeout": 300, "readCycle": 100,
        "reconnectInterval": 100, "maxBackoff": 200, "connectTimeout": 1000,
        "offlineAfterFailedCycles": 1, "retries": 0,
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": "failover"}, "communication": comm,
        "addressList": [{"name": "who", "address": "hr:0", "deviceDataType": "UInt16"}],
    })


def value(drv: em.DriverModbusRtu) -> Any:
    item = drv.address_items[0]
    return item.value if item.status == "Ok" else None


def line_stats(drv: em.DriverModbusRtu) -> dict[str, Any]:
    line: dict[str, Any] = drv.stats()["line"]
    return line


def test_fails_over_after_failed_connects_and_back_after_the_primary_returns(
        slave_factory: SlaveFactory) -> None:
    primary = slave_factory("tcp", units=(1,), initial={1: {"hr": {0: PRIMARY}}})
    alternate = slave_factory("tcp", units=(1,), initial={1: {"hr": {0: ALTERNATE}}})
    with Running(config(primary.port, alternate.port)) as drv:
        wait_for(lambda: value(drv) == PRIMARY, 10, "a value from the primary")
        assert line_stats(drv)["activeEndpoint"] == f"tcp://127.0.0.1:{primary.port}"
        primary.stop()  # the link drops; connects to the primary fail from now on
        wait_for(lambda: value(drv) == ALTERNATE, 15, "a value from the alternate")
        stats = line_stats(drv)
        assert stats["failovers"] == 1 and stats["failbacks"] == 0
        assert stats["activeEndpoint"] == f"tcp://127.0.0.1:{alternate.port}"
        assert stats["connectFailures"] >= 2
        primary.restart()  # the probe (every 300 ms) finds it: back to the primary
        wait_for(lambda: value(drv) == PRIMARY, 15, "a value from the primary again")
        stats = line_stats(drv)
        assert (stats["failovers"], stats["failbacks"]) == (1, 1)
        assert stats["activeEndpoint"] == f"tcp://127.0.0.1:{primary.port}"
    assert not [t for t in threading.enumerate() if t.name.startswith("edgemodbus-failover")]


def test_fails_over_after_failed_cycles_of_every_device(slave_factory: SlaveFactory) -> None:
    """The primary accepts the connection but its slave is silent (a serial server whose
    RS-485 side is cut): after failoverAfter failed cycles the line moves on; the probe
    (a connect) then takes it back, and the failed cycles move it out again."""
    primary = slave_factory("tcp", units=(7,))  # unit 1 is silent there
    alternate = slave_factory("tcp", units=(1,), initial={1: {"hr": {0: ALTERNATE}}})
    with Running(config(primary.port, alternate.port, failbackInterval=0)) as drv:
        wait_for(lambda: value(drv) == ALTERNATE, 15, "a value from the alternate")
        stats = line_stats(drv)
        assert stats["failovers"] == 1 and stats["connectFailures"] == 0
        assert drv.stats()["failedCycles"] >= 2
        assert stats["timeouts"] >= 2


def test_a_dead_alternate_wraps_around_to_the_primary(slave_factory: SlaveFactory,
                                                     free_tcp_port: int) -> None:
    """With the primary down and the alternate refusing too, the line keeps cycling
    through both (each move counted) and takes the primary when it comes back."""
    primary = slave_factory("tcp", units=(1,), initial={1: {"hr": {0: PRIMARY}}})
    port = primary.port
    primary.stop()
    with Running(config(port, free_tcp_port, failoverAfter=1, failbackInterval=0)) as drv:
        wait_for(lambda: line_stats(drv)["failbacks"] >= 1, 15, "a move back to the primary")
        assert line_stats(drv)["failovers"] >= 1
        primary.restart()
        wait_for(lambda: value(drv) == PRIMARY, 15, "a value from the primary")


def test_a_serial_line_fails_over_to_its_second_port(tmp_path: Path,
                                                     slave_factory: SlaveFactory) -> None:
    """The primary serial port is gone (an unplugged adapter): after failoverAfter failed
    opens the line takes the second port (a socat pty pair, a pymodbus slave on its
    other end) with the same settings."""
    with PtyPair(tmp_path / "pty") as pair:
        slave_factory("serial", units=(1,), device=pair.b,
                      initial={1: {"hr": {0: ALTERNATE}}})
        cfg = em.load_device_config({
            "organization": {"deviceCode": "serial-failover"},
            "communication": {"transport": "rtu", "comPort": str(tmp_path / "unplugged"),
                              "baudRate": 19200, "slaveId": 1,
                              "alternates": [str(pair.a)], "failoverAfter": 2,
                              "readCycle": 100, "readTimeout": 500,
                              "reconnectInterval": 100, "maxBackoff": 200},
            "addressList": [{"name": "who", "address": "hr:0", "deviceDataType": "UInt16"}],
        })
        with Running(cfg) as drv:
            wait_for(lambda: value(drv) == ALTERNATE, 15, "a value over the second port")
            stats = line_stats(drv)
            assert stats["failovers"] == 1 and stats["activeEndpoint"].startswith(str(pair.a))
