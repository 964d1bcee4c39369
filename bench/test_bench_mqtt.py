"""Issue 8: what publishing to MQTT costs the gateway.

10,000 UInt16 tags on 10 slaves (1,000 each) of one RTU-over-TCP line, played by our
simulator in its own process; 1% of the values change on every read (a FlipMover on
every 100th tag), checked from ``stats()["valuesChanged"]``.  A real mosquitto (own
process) receives the updates and a subscriber (own process) counts what arrives.

The same drivers run all along (polling as fast as the line allows); a publisher is
attached (MQTT on) and detached (MQTT off) in alternating phases of the same run, and
the client CPU of this process (time.process_time: every thread, the line worker and the
MQTT thread included) per tag read is compared: each on window against the mean of the
off windows before and after its round, the median over the rounds (the machine is
shared: a burst of someone else's load spoils a window, not the figure).  Publishers in
mode "batch" (one message per device and cycle) and "per-item" (one message per update),
each at QoS 0 and QoS 1, all through paho's public publish().  Targets (gated:
bench/gate.py): batch on / off <= 1.2 at QoS 0 and <= 1.5 at QoS 1; per-item QoS 0 keeps
issue 8's target (<= 1.5, not met since the hand-built packets went: its limit is a
regression guard) and per-item QoS 1 is reported.  The benchmark fixture times the line
worker's side of MQTT: the batch callback handing 100 updates over.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from tests.mosquitto import Mosquitto

import edgemodbus as em
from bench import gate
from bench.conftest import QUICK, cpu_seconds, report, scale
from bench.slave_process import SimulatorProcess
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.northbound.mqtt import MqttPublisher

SLAVES = list(range(1, 11))
TAGS = 1000  # per slave
CHANGING_EVERY = 100  # 1%
PHASE_SECONDS = 1.0 if QUICK else 2.5
PHASES = 3 if QUICK else 6  # rounds of off and every on mode, then off once more
Mode = tuple[str, int]  # (mqtt.mode, qos)
ON: list[Mode] = [("batch", 0), ("batch", 1), ("per-item", 0), ("per-item", 1)]

SUBSCRIBER = textwrap.dedent("""
    import sys, threading
    import paho.mqtt.client as paho
    count = 0
    lock = threading.Lock()
    ready = threading.Event()
    def on_message(client, userdata, msg):
        global count
        with lock:
            count += 1
    c = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2)
    c.on_message = on_message
    c.on_subscribe = lambda *a: ready.set()
    c.connect("127.0.0.1", int(sys.argv[1]))
    c.subscribe(sys.argv[2], qos=1)
    c.loop_start()
    ready.wait(10)
    print("ready", flush=True)
    for line in sys.stdin:  # each line asks for the count so far
        with lock:
            print(count, flush=True)
    c.disconnect()
    c.loop_stop()
""")


class Subscriber:
    """A paho subscriber in its own process (its CPU is not ours)."""

    def __init__(self, port: int, topic: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SUBSCRIBER, str(port), topic],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
        )
        assert self.proc.stdout is not None
        assert self.proc.stdout.readline().strip() == "ready"

    def count(self) -> int:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write("?\n")
        self.proc.stdin.flush()
        return int(self.proc.stdout.readline())

    def close(self) -> None:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


class Captured:
    """A driver as the publisher sees it, keeping the listener the publisher subscribes
    (so the bench times that listener's hand-off alone, through the public protocol)."""

    def __init__(self, driver: em.DriverModbusRtu) -> None:
        self.driver = driver
        self.listener: em.Listener[em.DriverModbusRtu] | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.driver, name)

    def subscribe(self, listener: em.Listener[em.DriverModbusRtu]) -> None:
        self.listener = listener

    def unsubscribe(self, listener: em.Listener[em.DriverModbusRtu]) -> None:
        self.listener = None


def device(port: int, slave: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": f"bench{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave, "readCycle": 10, "readTimeout": 1000, "byteTimeout": 200,
            "maxBlockReadRegisterCount": 120,
        },
        "addressList": [{"name": f"t{k}", "address": f"3:{k}", "deviceDataType": "UInt16"}
                        for k in range(TAGS)],
    })


@pytest.fixture(scope="module")
def setup() -> Iterator[tuple[SimulatorProcess, Mosquitto]]:
    # a subscriber may lag behind thousands of updates a second: let mosquitto queue them
    # all for it (its default drops QoS 1 messages beyond 1000 queued per client)
    unlimited = ["max_queued_messages 0"]
    with tempfile.TemporaryDirectory() as tmp, \
            Mosquitto(Path(tmp), extra_config=unlimited) as broker, \
            SimulatorProcess(SLAVES, size=TAGS + 10) as sim:
        flips = sim.flip([(s, Area.HOLDING_REGISTER, k, 1)
                          for s in SLAVES for k in range(0, TAGS, CHANGING_EVERY)])
        assert flips == len(SLAVES) * TAGS // CHANGING_EVERY
        yield sim, broker


def _totals(drivers: list[em.DriverModbusRtu]) -> tuple[int, int]:
    """(tag reads, values changed) so far over every driver."""
    reads = changed = 0
    for drv in drivers:
        s = drv.stats()
        reads += s["cycles"] * drv.data_item_count
        changed += s["valuesChanged"]
    return reads, changed


def test_cpu_per_tag_read_mqtt_on_vs_off(setup: tuple[SimulatorProcess, Mosquitto],
                                         benchmark: Any) -> None:
    sim, broker = setup
    configs = [device(sim.port, s) for s in SLAVES]
    publishers = {(mode, qos): MqttPublisher({"port": broker.port, "qos": qos, "mode": mode},
                                             gateway_id=f"bench-{mode}-q{qos}").start()
                  for mode, qos in ON}
    subscriber = Subscriber(broker.port, "edgemodbus/+/+")
    drivers: list[em.DriverModbusRtu] = []
    modes: list[Mode | None] = [None, *ON]  # MQTT off, then each way of publishing
    results: dict[Mode | None, list[float]] = {m: [0.0, 0.0, 0.0] for m in modes}
    windows: dict[Mode | None, list[float]] = {m: [] for m in modes}  # CPU per read
    try:
        for pub in publishers.values():
            assert pub.wait_connected(10)
        for cfg in configs:
            drv = em.DriverModbusRtu()
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
        deadline = time.monotonic() + 60
        while not all(it.status is ItemStatus.OK for c in configs for it in c.address_list):
            assert time.monotonic() < deadline, "tags not all read"
            time.sleep(0.1)  # poll: until all Ok (deadline above)
        time.sleep(1.0)  # pacing: warm up

        for last in [False] * PHASES + [True]:
            for mode in modes[:1] if last else modes:
                pub = publishers[mode] if mode is not None else None
                if pub is not None:
                    for drv, cfg in zip(drivers, configs, strict=True):
                        pub.attach(drv, cfg.organization.device_code)
                time.sleep(0.3)  # pacing: let the switch settle
                reads0, changed0 = _totals(drivers)
                cpu0 = cpu_seconds()
                time.sleep(PHASE_SECONDS)  # pacing: the phase measured
                cpu1 = cpu_seconds()
                reads1, changed1 = _totals(drivers)
                acc = results[mode]
                acc[0] += cpu1 - cpu0
                acc[1] += reads1 - reads0
                acc[2] += changed1 - changed0
                windows[mode].append((cpu1 - cpu0) / (reads1 - reads0))
                if pub is not None:
                    for drv in drivers:
                        pub.detach(drv)
                    # what it still holds is sent before the next window, not in it
                    deadline = time.monotonic() + 10
                    while pub.stats()["queued"] and time.monotonic() < deadline:
                        time.sleep(0.05)  # poll: until sent (deadline above)
        stats = {mode: pub.stats() for mode, pub in publishers.items()}
        # messages: an update each (per-item), a device's cycle each (batch)
        published = sum(st["batchesPublished"] if mode[0] == "batch" else st["published"]
                        for mode, st in stats.items())
        # every published message reached the subscriber
        deadline = time.monotonic() + 15
        while subscriber.count() < published:
            assert time.monotonic() < deadline, (subscriber.count(), published)
            time.sleep(0.1)  # poll: until all received (deadline above)
        received = subscriber.count()

        # the worker's side: the publisher's listener taking 100 updates
        drv = drivers[0]
        captured = Captured(drv)
        publishers["batch", 0].attach(captured, "bench1")  # type: ignore[arg-type]
        listener = captured.listener
        assert listener is not None
        batch = configs[0].address_list[:100]
        benchmark.pedantic(lambda: listener.on_changes(drv, batch),
                           rounds=scale(2000, 200), iterations=1)
        publishers["batch", 0].detach(captured)  # type: ignore[arg-type]
    finally:
        for drv in drivers:
            drv.stop_device()
        for pub in publishers.values():
            pub.stop()
        subscriber.close()

    seconds = PHASES * PHASE_SECONDS  # of each on mode (off has one window more)
    off_cpu, off_reads, off_changed = results[None]
    per_off = off_cpu / off_reads
    offs = windows[None]  # PHASES + 1: before and after each round
    rows: list[tuple[str, float, str]] = [("MQTT off: CPU per tag read", per_off * 1e9, "ns")]
    ratios: dict[Mode, float] = {}
    for mode, qos in ON:
        cpu, reads, changed = results[mode, qos]
        rounds = [on / ((offs[r] + offs[r + 1]) / 2) for r, on in enumerate(windows[mode, qos])]
        ratios[mode, qos] = statistics.median(rounds)
        st = stats[mode, qos]
        name = f"MQTT {mode} QoS {qos}"
        rows += [
            (f"{name}: CPU per tag read", cpu / reads * 1e9, "ns"),
            (f"{name}: ratio to off (median of rounds)", ratios[mode, qos], "x"),
            (f"{name}: ratio to off (all windows)", (cpu / reads) / per_off, "x"),
            (f"{name}: ratio to off (lowest round)", min(rounds), "x"),
            (f"{name}: ratio to off (highest round)", max(rounds), "x"),
            (f"{name}: updates published per second", changed / seconds, "/s"),
            (f"{name}: CPU, % of one core", 100 * cpu / seconds, "%"),
            (f"{name}: values changed per read", 100 * changed / reads, "%"),
            (f"{name}: updates dropped (queue full)", float(st["dropped"]), ""),
        ]
        if mode == "batch":
            rows.append((f"{name}: updates per message",
                         st["published"] / max(1, st["batchesPublished"]), ""))
    rows += [
        ("MQTT off: values changed per read", 100 * off_changed / off_reads, "%"),
        ("MQTT off: tag reads per second", off_reads / (seconds + PHASE_SECONDS), "/s"),
        ("MQTT off: CPU, % of one core", 100 * off_cpu / (seconds + PHASE_SECONDS), "%"),
    ]
    benchmark.extra_info.update(
        ns_per_tag_read_off=per_off * 1e9, published=published, received=received,
        **{f"ratio_{mode}_qos{qos}": ratio for (mode, qos), ratio in ratios.items()},
    )
    report("CPU per tag read, 10,000 tags, 1% changing per read, MQTT to mosquitto", rows)
    for mode in modes:
        cpu, reads, changed = results[mode]
        assert 0.9 <= 100 * changed / reads <= 1.1, f"the 1% change did not happen ({mode})"
    assert received >= published > 0
    # a valid run only: nothing dropped where a figure is gated (a dropped update is work
    # not done, which would flatter the ratio)
    for key in (("batch", 0), ("batch", 1), ("per-item", 0)):
        assert stats[key]["dropped"] == 0, (key, stats[key]["dropped"])
    gate.record("mqtt.batch_qos0_on_vs_off", ratios["batch", 0])
    gate.record("mqtt.batch_qos1_on_vs_off", ratios["batch", 1])
    gate.record("mqtt.qos0_on_vs_off", ratios["per-item", 0])
