"""Issue #25, through the gateway's CLI in a child process (tests/gateway_proc.py):

* the Modbus TCP server at the open-files limit: accept4 fails with EMFILE; the C loop
  pauses accepting instead of spinning, logs once per interval, and serves a new master
  once fds are free;
* the metrics exporter against connections that never finish their request headers: one
  thread, a bounded number of fds, scrapes still answered, fds released after the header
  deadline;
* a deeply nested file: SIGHUP keeps the running gateway and its configuration; at start
  it is one line and exit status 2, no traceback.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.gateway_proc import (
    REPO,
    GatewayProcess,
    cpu_share,
    device_file,
    idle_connections,
    nested_json,
    scrape,
    served,
    write_json,
)
from tests.peers import PymodbusSlave, free_port
from tests.waiting import wait_for

SLOW_HEADERS = b"GET /metrics HTTP/1.1\r\nHost: x\r\n"  # and never the blank line


def has_dev1(port: int) -> bool:
    """A scrape answered, with dev1's counters (False when it failed: retried)."""
    try:
        return 'edgemodbus_requests_total{device="dev1"' in scrape(port)
    except OSError:
        return False


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2), size=200) as peer:
        yield peer


def test_the_modbus_tcp_server_backs_off_at_the_fd_limit(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    """Row 1: 100 masters against a gateway allowed 64 fds (maxConnections 1024): the
    server thread stays near 0 % CPU (it spun at 60-98 %), logs at most a line per
    10 s, the bystander device is still polled, and a master is served afterwards."""
    port = free_port()
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {
        "metrics": {"enabled": False},
        "serve": {"listen": f"127.0.0.1:{port}", "maxConnections": 1024,
                  "idleTimeoutS": 600, "units": [{"unitId": 1, "device": "dev1"}]}})
    with GatewayProcess(conf, tmp_path / "gw.log", nofile=64) as gw:
        gw.wait_log(r"Modbus TCP server on")
        wait_for(lambda: served(port), timeout=20, what="unit 1 served")
        with idle_connections(port, 100):
            gw.wait_log(r"serve :\d+: accept failed \d+ times \(EMFILE")
            first = gw.usage()
            polled = slave.request_count(1)
            time.sleep(3.0)  # pacing: the window measured (a spinning loop burns it all)
            last = gw.usage()
            cpu, busiest = cpu_share(first, last)
            # (the server's thread spun at 0.8 CPU; polling costs the gateway ~0.005)
            assert cpu < 0.10 and busiest < 0.05, f"CPU {cpu:.2f}, busiest thread {busiest:.2f}"
            assert len(gw.lines(r"accept failed")) <= 2, gw.log
            assert slave.request_count(1) - polled >= 5  # readCycle 100 ms: ~30
        wait_for(lambda: served(port), timeout=20, what="a master served after the flood")
        assert gw.stop() == 0, gw.log


def test_the_metrics_exporter_bounds_slow_header_connections(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    """Row 2: 1,024 connections that never finish their request headers, against a
    gateway allowed 256 fds: no thread per connection (1,019 before), at most 64 of
    them held, a scrape still answered, and their fds closed by the header deadline."""
    port = free_port()
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {"metrics": {"port": port}})
    with GatewayProcess(conf, tmp_path / "gw.log", nofile=256) as gw:
        gw.wait_log(r"metrics on http://")
        wait_for(lambda: has_dev1(port),
                 timeout=20, what="dev1 in a scrape")
        before = gw.usage()
        with idle_connections(port, 1024, send=SLOW_HEADERS):
            started = time.monotonic()
            text = scrape(port)
            took = time.monotonic() - started
            during = gw.usage()
            assert 'edgemodbus_requests_total{device="dev1"' in text
            assert took < 5.0, f"the scrape took {took:.1f} s"
            assert during.threads <= before.threads + 1, (before, during)
            assert during.fds <= before.fds + 64 + 2, (before, during)
            # the header deadline (5 s) closes what is left: back to where it was
            wait_for(lambda: gw.usage().fds <= before.fds + 1, timeout=60,
                     what="the exporter's fds released")
        assert 'edgemodbus_requests_total{device="dev1"' in scrape(port)
        assert gw.stop() == 0, gw.log


def test_the_metrics_exporter_backs_off_at_the_fd_limit(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    """The exporter's accept at EMFILE (1,024 slow connections, 64 fds: fewer than its
    connection cap): the oldest waiting connection makes room, or accepting pauses; no
    spin, a line per kind and 10 s, scrapes answered during the flood and after."""
    port = free_port()
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {"metrics": {"port": port}})
    with GatewayProcess(conf, tmp_path / "gw.log", nofile=64) as gw:
        gw.wait_log(r"metrics on http://")
        wait_for(lambda: has_dev1(port),
                 timeout=20, what="dev1 in a scrape")
        with idle_connections(port, 1024, send=SLOW_HEADERS, patience=2.0):
            gw.wait_log(r"metrics: (no room for a connection \(Too many open files\)|"
                        r"accept failed \(Too many open files\); pausing)")
            first = gw.usage()
            time.sleep(3.0)  # pacing: the window measured
            cpu, busiest = cpu_share(first, gw.usage())
            assert cpu < 0.10 and busiest < 0.05, f"CPU {cpu:.2f}, busiest thread {busiest:.2f}"
            assert has_dev1(port)
            assert len(gw.lines(r"metrics: ")) <= 4, gw.log
        wait_for(lambda: has_dev1(port),
                 timeout=20, what="a scrape after the flood")
        assert gw.stop() == 0, gw.log


def test_sighup_with_deeply_nested_files_keeps_the_running_gateway(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    """Row 3: a device file and the gateway file nested 100,000 deep, then SIGHUP: one
    line each, the gateway keeps running with what it had (RecursionError ended it with
    status 1 before); a valid change on the next SIGHUP is still applied."""
    conf = tmp_path / "conf"
    conf.mkdir()
    metrics = free_port()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    write_json(conf / "gateway.json", {"metrics": {"port": metrics}})
    with GatewayProcess(conf, tmp_path / "gw.log") as gw:
        gw.wait_log(r"dev1: started from dev1.json")
        write_json(conf / "dev1.json", nested_json())
        write_json(conf / "gateway.json", nested_json())
        gw.signal(signal.SIGHUP)
        gw.wait_log(r"dev1\.json: (cannot load|invalid).*keeping the running version")
        gw.wait_log(r"gateway\.json: (cannot load|invalid).*keeping the running gateway")
        assert "Traceback" not in gw.log
        polled = slave.request_count(1)
        wait_for(lambda: slave.request_count(1) >= polled + 3, timeout=10,
                 what="dev1 still polled")
        assert 'edgemodbus_requests_total{device="dev1"' in scrape(metrics)
        write_json(conf / "dev2.json", device_file(slave.port, 2, "dev2"))
        gw.signal(signal.SIGHUP)
        gw.wait_log(r"dev2: started from dev2.json")
        assert gw.alive()
        assert gw.stop() == 0, gw.log


def test_a_deeply_nested_gateway_file_at_start_is_one_line_and_status_2(
        tmp_path: Path) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    (conf / "gateway.json").write_text(nested_json())
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.gateway", "--config-dir", str(conf)],
        capture_output=True, text=True, timeout=60, cwd=REPO)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "gateway.json" in lines[0], lines
    assert len(lines[0]) < 600


def test_a_deeply_nested_device_file_at_start_is_reported_and_the_others_run(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "dev1.json", device_file(slave.port, 1, "dev1"))
    (conf / "bad.json").write_text(nested_json())
    result = subprocess.run(
        [sys.executable, "-m", "edgemodbus.gateway", "--config-dir", str(conf),
         "--seconds", "1"], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    # one ERROR record: the file "invalid, not started", then its one problem (the depth)
    bad = [ln for ln in result.stderr.splitlines() if "bad.json" in ln]
    assert len(bad) == 2 and "not started" in bad[0], result.stderr
    assert "nested more than 32 levels" in bad[1], result.stderr
    assert "dev1: started from dev1.json" in result.stderr
