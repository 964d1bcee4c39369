"""What the web console costs the polling: CPU per tag read with the console enabled
and idle (listening, nobody looking) over the console disabled, in the same run.

2,000 UInt16 tags on 4 slaves (500 each) of one RTU-over-TCP line, played by our
simulator in its own process, polled as fast as the line allows (readCycle 10 ms), 1% of
the values changing on every read.  A gateway (gateway/service.py) runs the devices all
along; its console (console/server.py) is started for the "on" windows and stopped for
the "off" ones, alternately; the CPU of this process (every thread) per tag read of each
on window is compared with the mean of the off windows around it, the median over the
rounds (the machine is shared).  Gated (bench/gate.py ``console.idle_vs_off``): an idle
console subscribes nothing (console/feed.py) and its thread sleeps in epoll, so the
target is 1.0 with a 5 % allowance and a margin for noise.  Reported, not gated: the
same with one browser watching a device (a live stream open, its feed subscribed).  The
benchmark fixture times the line worker's side of a watched device: the feed's
on_changes for a batch of 100 items (a wake-up of the loop already pending).
"""

from __future__ import annotations

import itertools
import json
import socket
import statistics
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from bench import gate
from bench.conftest import QUICK, cpu_seconds, report
from bench.slave_process import SimulatorProcess
from edgemodbus.console import ConsoleSettings
from edgemodbus.console.feed import DeviceFeed
from edgemodbus.console.server import ConsoleServer
from edgemodbus.datatypes import Area
from edgemodbus.gateway import Gateway, load_gateway_config

SLAVES = [1, 2, 3, 4]
TAGS = 500  # per slave
CHANGING_EVERY = 100  # 1%
WINDOW = 1.0 if QUICK else 2.5  # seconds
ROUNDS = 3 if QUICK else 6


def device_file(port: int, slave: int) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": f"bench{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave, "readCycle": 10, "readTimeout": 1000, "byteTimeout": 200,
            "maxBlockReadRegisterCount": 120},
        "addressList": [{"name": f"t{k}", "address": f"3:{k}", "deviceDataType": "UInt16"}
                        for k in range(TAGS)],
    }


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    folder = tmp_path_factory.mktemp("console-bench")
    with SimulatorProcess(SLAVES, size=TAGS + 10) as sim:
        sim.flip([(s, Area.HOLDING_REGISTER, k, 1)
                  for s in SLAVES for k in range(0, TAGS, CHANGING_EVERY)])
        for slave in SLAVES:
            (folder / f"bench{slave}.json").write_text(json.dumps(device_file(sim.port, slave)))
        (folder / "gateway.json").write_text("{}")
        gw = Gateway(folder, load_gateway_config(folder / "gateway.json"),
                     folder / "gateway.json")
        gw.start()
        try:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not all(
                    d.driver.stats().get("cycles", 0) > 5 for d in gw.devices.values()):
                time.sleep(0.05)  # poll: until five cycles (deadline above)
            yield gw
        finally:
            gw.stop()


def reads(gw: Gateway) -> int:
    return sum(d.driver.stats()["cycles"] * d.driver.data_item_count
               for d in gw.devices.values())


def window(gw: Gateway) -> float:
    """CPU seconds per tag read over one window."""
    cpu0, reads0 = cpu_seconds(), reads(gw)
    time.sleep(WINDOW)  # pacing: the window measured
    return (cpu_seconds() - cpu0) / max(1, reads(gw) - reads0)


class Watcher:
    """One browser watching a device: a live stream read on a thread of its own."""

    def __init__(self, port: int, code: str) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.sock.sendall(f"GET /api/devices/{code}/events HTTP/1.1\r\n"
                          f"Host: 127.0.0.1:{port}\r\n\r\n".encode())
        self.bytes = 0
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            while chunk := self.sock.recv(65536):
                self.bytes += len(chunk)
        except OSError:
            pass

    def close(self) -> None:
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self.thread.join(10)


def test_console_idle_vs_off(gateway: Gateway, benchmark: Any) -> None:
    offs: list[float] = []
    idles: list[float] = []
    watched: list[float] = []
    settings = ConsoleSettings(port=0)
    offs.append(window(gateway))
    streamed = 0
    for _ in range(ROUNDS):
        console = ConsoleServer(settings, gateway).start()
        try:
            idles.append(window(gateway))
            watcher = Watcher(console.port, "bench1")
            try:
                watched.append(window(gateway))
            finally:
                watcher.close()
                streamed += watcher.bytes
        finally:
            console.stop()
        offs.append(window(gateway))
    around = [(a + b) / 2 for a, b in itertools.pairwise(offs)]  # the off before and after
    idle = statistics.median(i / off for i, off in zip(idles, around, strict=True))
    watch = statistics.median(w / off for w, off in zip(watched, around, strict=True))
    assert streamed > 0  # the watched windows did stream values
    report("console: CPU per tag read (same run, median of rounds)", [
        ("console off (us/tag read)", 1e6 * statistics.median(offs), "us"),
        ("console on, idle / off", idle, "x"),
        ("console on, one stream / off", watch, "x"),
    ])
    gate.record("console.idle_vs_off", idle)

    dev = next(d for d in gateway.devices.values() if d.code == "bench1")
    feed = DeviceFeed(dev.driver, _Loop())
    batch = dev.driver.address_items[:100]
    benchmark.pedantic(lambda: feed.on_changes(dev.driver, batch), rounds=200, iterations=10)
    benchmark.extra_info.update({"idle_vs_off": idle, "watched_vs_off": watch})


class _Loop:
    """A stand-in for the console's loop: the feed posts its wake-up here (dropped)."""

    def call_soon_threadsafe(self, callback: Any) -> None:
        return None
