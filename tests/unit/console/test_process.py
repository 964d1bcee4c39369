"""The console in the gateway service's own process (``python -m edgemodbus.gateway``):
a device saved from the console is started by the service's reload (the SIGHUP path,
run.py's hook), and the console at the fd limit does not spin
(docs/fault-checklist.md, "The web console")."""

from __future__ import annotations

import re
import time
from pathlib import Path

from tests.conftest import SlaveFactory
from tests.console_gateway import Client
from tests.gateway_proc import (
    GatewayProcess,
    cpu_share,
    device_file,
    idle_connections,
    write_json,
)
from tests.waiting import wait_for


def console_port(gw: GatewayProcess) -> int:
    line = gw.wait_log(r"console on http://127\.0\.0\.1:\d+/")
    match = re.search(r":(\d+)/", line)
    assert match is not None
    return int(match.group(1))


def test_a_saved_device_is_started_by_the_service(tmp_path: Path,
                                                  slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp")
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {"console": {"port": 0}})
    with GatewayProcess(conf, tmp_path / "gw.log") as gw:
        client = Client(console_port(gw))
        client.session()
        _, out = client.post("/api/commission/save", {
            "fileName": "dev2.json", "document": device_file(slave.port, 2, "dev2")})
        assert out["ok"] is True, out
        gw.wait_log(r"dev2: started from dev2\.json")
        wait_for(lambda: any(r["code"] == "dev2" and r["cycles"] > 0
                             for r in client.get("/api/overview")[1]["devices"]),
                 timeout=20, what="dev2 polled")
        assert gw.stop() == 0, gw.log


def test_the_console_backs_off_at_the_fd_limit(tmp_path: Path,
                                               slave_factory: SlaveFactory) -> None:
    """100 connections against a gateway allowed 64 fds: the console's thread stays near
    0 % CPU, at most one log line per 10 s about it, and it answers once they close."""
    slave = slave_factory("rtu-over-tcp")
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {"console": {"port": 0, "maxConnections": 1000}})
    with GatewayProcess(conf, tmp_path / "gw.log", nofile=64) as gw:
        port = console_port(gw)
        with idle_connections(port, 100):
            gw.wait_log(r"console: socket\.accept\(\) out of system resource")
            first = gw.usage()
            polled = slave.request_count(1)
            time.sleep(3.0)  # pacing: the window measured (a spinning loop burns it all)
            cpu, busiest = cpu_share(first, gw.usage())
            assert cpu < 0.10 and busiest < 0.05, f"CPU {cpu:.2f}, busiest {busiest:.2f}"
            assert len(gw.lines(r"console: ")) <= 2, gw.log
            assert "Traceback" not in gw.log
            assert slave.request_count(1) - polled >= 5
        wait_for(lambda: Client(port).get("/api/session")[0] == 200, timeout=30,
                 what="the console answers after the flood")
        assert gw.stop() == 0, gw.log
