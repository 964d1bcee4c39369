"""Store-and-forward (``mqtt.storeAndForward``) end to end: a real mosquitto (own process),
our driver polling our simulator (10,000 tags on 5 slaves, 1% of them changing on every
read), a subscriber whose session the broker keeps across its restart (persistence on,
clean_session off: it misses nothing the broker accepted).

A 10-minute outage compressed in time: the drivers poll every ``CYCLE_MS`` ms instead of
every second, and the broker stays away for ``OUTAGE_CYCLES`` cycles of every device.
What the subscriber receives is checked against what the drivers reported (a recorder
chained to each driver's batch callback): every report arrives once (QoS 1 duplicates
aside), in order per device, with the values the driver read; beyond ``maxBytes`` the
oldest are dropped and counted, and so are those older than ``maxAgeS``.  Then the same
with the gateway service in its own process, killed with SIGKILL in the middle of the
outage and started again on the same spool file."""

from __future__ import annotations

import json
import logging
import signal
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import DeviceAddressItem
from edgemodbus.datatypes import Area
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.sim import CounterMover, Simulator
from tests.gateway_proc import GatewayProcess as Service
from tests.gateway_proc import scrape, write_json
from tests.mosquitto import Mosquitto, MqttProbe
from tests.tmpfs import small_tmpfs
from tests.waiting import wait_for

SLAVES = [1, 2, 3, 4, 5]
TAGS = 2000  # per slave: 10,000 in all
CHANGING_EVERY = 100  # 1%
CYCLE_MS = 20  # one simulated second
OUTAGE_CYCLES = 600  # ten simulated minutes
P = "edgemodbus"


@pytest.fixture
def sim() -> Iterator[int]:
    with Simulator(SLAVES, size=TAGS + 10) as peer:
        for sid in SLAVES:
            for k in range(0, TAGS, CHANGING_EVERY):  # changes on every read (1 ms ticks)
                peer.slave(sid).add_mover(CounterMover(Area.HOLDING_REGISTER, k, 1,
                                                       interval_ms=1, start=k))
        yield peer.serve_tcp("127.0.0.1", 0)


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    folder = tmp_path / "broker"
    keep = ["persistence true", f"persistence_location {folder}/", "autosave_interval 0",
            "max_queued_messages 0"]  # the subscriber's session survives the restart
    with Mosquitto(folder, extra_config=keep) as peer:
        yield peer


def device_file(port: int, slave: int, cycle_ms: int = CYCLE_MS) -> dict[str, Any]:
    return {
        "organization": {"deviceCode": f"dev{slave}"},
        "communication": {
            "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": slave, "readCycle": cycle_ms, "readTimeout": 1000,
            "byteTimeout": 200, "maxBlockReadRegisterCount": 100,
        },
        "addressList": [{"name": f"t{k}", "address": f"hr:{k}", "deviceDataType": "UInt16"}
                        for k in range(TAGS)],
    }


def received_data(probe: MqttProbe) -> dict[str, list[dict[str, Any]]]:
    """Per device, the messages in arrival order as ``{"values": {name: value}, "ts"}``
    (a batch, or in mode "per-item" one item), a redelivered one (same topic and
    payload: it carries its read's timestamp) counted once."""
    seen: set[tuple[str, bytes]] = set()
    out: dict[str, list[dict[str, Any]]] = {}
    for m in probe.messages():
        if not is_data(m.topic) or (m.topic, m.payload) in seen:
            continue
        seen.add((m.topic, m.payload))
        body = json.loads(m.payload)
        _, code, leaf = m.topic.split("/")
        if leaf != "$batch":
            body = {"values": {leaf: body["value"]}, "ts": body["updateTs"]}
        out.setdefault(code, []).append(body)
    return out


def is_data(topic: str) -> bool:
    """A batch or an item update (not a status, not the gateway's topic)."""
    _, code, leaf = topic.split("/")
    return not code.startswith("$") and (leaf == "$batch" or not leaf.startswith("$"))


def duplicates(probe: MqttProbe) -> int:
    """Messages our publisher sent twice.  A copy the broker redelivered to the probe's
    own session (DUP set, MQTT 3.1.1, 3.3.1.1: a slow probe had not acknowledged it
    before the broker went down) is not one: the broker forwards a publisher's resend
    as a new PUBLISH, DUP clear."""
    messages = [(m.topic, m.payload) for m in probe.messages()
                if is_data(m.topic) and not m.dup]
    return len(messages) - len(set(messages))


def check_in_order(got: list[dict[str, Any]], want: list[dict[str, Any]]) -> list[int]:
    """``got`` is ``want`` in order with a contiguous run left out (or none); the indexes
    of ``want`` left out."""
    head = 0
    while head < min(len(got), len(want)) and got[head]["values"] == want[head]["values"]:
        head += 1
    tail = len(want) - (len(got) - head)
    assert tail >= head, (len(got), len(want), head)
    assert [b["values"] for b in got[head:]] == [b["values"] for b in want[tail:]], \
        f"not in order, or lost in the middle (first {head} in order)"
    stamps = [b["ts"] for b in got]
    assert stamps == sorted(stamps)
    return list(range(head, tail))


class Recorder:
    """What a driver reported, chained before the publisher's callback."""

    def __init__(self, per_item: bool) -> None:
        self.per_item = per_item
        self.reports: list[dict[str, Any]] = []  # one a message

    def __call__(self, items: list[DeviceAddressItem]) -> None:
        if self.per_item:
            self.reports += [{"values": {it.name: it.value}} for it in items]
        else:
            self.reports.append({"values": {it.name: it.value for it in items}})


@pytest.mark.parametrize(("mode", "bound"), [("batch", "fits"), ("batch", "overflows"),
                                             ("batch", "expires"), ("per-item", "fits")])
def test_an_outage_is_kept_on_disk_and_replayed_in_order_per_device(
        sim: int, broker: Mosquitto, tmp_path: Path, mode: str, bound: str) -> None:
    max_bytes = 400_000 if bound == "overflows" else 1_000_000_000
    max_age_s = 3 if bound == "expires" else 3600  # of a 12 s outage
    settings = {"port": broker.port, "mode": mode, "qos": 1, "reconnectMin": 100,
                "reconnectMax": 400, "queueSize": 10,
                "storeAndForward": {"path": str(tmp_path / "spool.db"), "maxBytes": max_bytes,
                                    "maxAgeS": max_age_s,
                                    "replayRatePerS": 2000 if mode == "batch" else 20_000}}
    # per item: 100 messages per simulated second instead of 5; compressed 5x, not 50x
    cycle_ms, cycles = (CYCLE_MS, OUTAGE_CYCLES) if mode == "batch" else (100, 120)
    configs = [em.load_device_config(device_file(sim, s, cycle_ms)) for s in SLAVES]
    recorders = {str(c.organization.device_code): Recorder(mode == "per-item")
                 for c in configs}
    probe = MqttProbe(broker.port, [f"{P}/+/+"], client_id="sf-probe",
                      clean_session=False).start()
    pub = MqttPublisher(settings, gateway_id="gw1").start()
    drivers: list[em.DriverModbusRtu] = []
    try:
        assert pub.wait_connected(10)
        for cfg in configs:
            drv = em.DriverModbusRtu()
            drv.addresses_updated_callback = recorders[str(cfg.organization.device_code)]
            pub.attach(drv, cfg.organization.device_code)
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            drivers.append(drv)
        wait_for(lambda: len(received_data(probe)) == len(SLAVES), timeout=30,
                 what="every device published")

        broker.stop()
        wait_for(lambda: not pub.connected, what="the publisher sees the broker go")
        # QoS 1 messages paho holds unacknowledged: it sends them again on reconnect,
        # even if the spool drops their rows meanwhile (counted as dropped all the same)
        held = pub.stats()["spool"]["inflight"]
        start = [d.stats()["cycles"] for d in drivers]
        wait_for(lambda: all(d.stats()["cycles"] - s >= cycles
                             for d, s in zip(drivers, start, strict=True)),
                 timeout=240, what=f"{cycles} cycles of outage")
        during = pub.stats()
        spooled = during["spool"]["stored"]
        per_cycle = 1 if mode == "batch" else TAGS // CHANGING_EVERY
        assert spooled >= cycles * len(SLAVES) * per_cycle * 0.9 or bound != "fits", during
        assert during["dropped"] == 0  # queueSize 10 no longer bounds an outage

        broker.restart()
        assert pub.wait_connected(10)
        wait_for(lambda: pub.stats()["spool"]["pending"] == 0, timeout=120,
                 what="the backlog replayed")
        for drv in drivers:  # live data flowed meanwhile; stop it to compare
            drv.stop_device()
        total = sum(len(r.reports) for r in recorders.values())
        stats = pub.stats()
        lost = stats["spool"]["droppedSize"] + stats["spool"]["droppedAge"]
        wait_for(lambda: sum(len(v) for v in received_data(probe).values()) >= total - lost,
                 timeout=60, what="every kept message received")
        wait_for(lambda: pub.stats()["spool"]["stored"] == 0, timeout=10,
                 what="every message acknowledged")
        count = -1
        while count != len(probe.received):  # acknowledged is not delivered yet: settle
            count = len(probe.received)
            time.sleep(0.3)  # pacing: settled: nothing new for 0.3 s
        got = received_data(probe)
        missing = 0
        for code, rec in recorders.items():
            missing += len(check_in_order(got[code], rec.reports))
        stats = pub.stats()
        spool = stats["spool"]
        print(f"\n{mode} {bound}: {total} reports, {spooled} spooled during the outage, {missing} "
              f"dropped, {duplicates(probe)} redelivered; {stats}")
        # a row dropped while paho held it (in flight at the outage, or replayed when
        # live rows pushed the oldest out) still arrives: at most paho's window more
        window = pub.settings.max_inflight * 4
        dropped = spool["droppedSize"] + spool["droppedAge"]
        assert missing <= dropped <= missing + held + window, (missing, spool)
        assert stats["dropped"] == 0 and spool["errors"] == 0
        assert duplicates(probe) <= held  # only what paho held unacknowledged, sent again
        if bound == "fits":
            assert missing == dropped == 0
        else:  # the bound held: most of the outage dropped, counted by its bound
            assert missing > cycles
            assert spool["droppedAge" if bound == "overflows" else "droppedSize"] == 0
        assert spool["replayed"] >= spooled - missing
        text = prometheus_text(pub)
        assert f"edgemodbus_mqtt_spool_dropped_size_total {float(spool['droppedSize'])}" in text
        assert f"edgemodbus_mqtt_spool_dropped_age_total {float(spool['droppedAge'])}" in text
        assert "edgemodbus_mqtt_spool_messages 0.0" in text
    finally:
        for drv in drivers:
            drv.stop_device()
        pub.stop()
        probe.stop()


def prometheus_text(pub: MqttPublisher) -> str:
    exporter = MetricsExporter()
    exporter.set_publisher(pub)
    return exporter.render().decode()


def test_a_kill_9_in_the_middle_of_an_outage_loses_nothing_sqlite_acknowledged(
        sim: int, broker: Mosquitto, tmp_path: Path) -> None:
    """The gateway service polls and publishes; the broker goes away; SIGKILL in the
    middle of the outage; the service starts again on the same spool file (the outage
    goes on), then the broker comes back.  Every message the spool file held at the kill
    arrives; a message arrives twice only if it was in flight (sent, not yet
    acknowledged) when the broker went away; per device in order."""
    conf = tmp_path / "conf"
    conf.mkdir()
    write_json(conf / "gateway.json", {
        "gatewayId": "gw-sf", "statusCheckInterval": 100,
        "metrics": {"host": "127.0.0.1", "port": 0},
        "mqtt": {"port": broker.port, "mode": "batch", "qos": 1, "reconnectMin": 100,
                 "reconnectMax": 400, "queueSize": 10,
                 "storeAndForward": {"path": "spool.db", "replayRatePerS": 2000}}})
    for s in SLAVES:
        write_json(conf / f"dev{s}.json", device_file(sim, s))
    probe = MqttProbe(broker.port, [f"{P}/+/$batch"], client_id="sf-kill-probe",
                      clean_session=False).start()
    try:
        with Service(conf, tmp_path / "first.log") as first:
            wait_for(lambda: len(received_data(probe)) == len(SLAVES), timeout=30,
                     what="every device published")
            broker.stop()
            before = len(probe.received)  # what arrived before the outage
            time.sleep(OUTAGE_CYCLES * CYCLE_MS / 1000 / 2)  # pacing: half the outage
            first.signal(signal.SIGKILL)
            first.wait()
        kept = spool_rows(conf / "spool.db")  # what SQLite acknowledged
        # batches of the first half: at least ten cycles of every device (a slow machine
        # polls fewer cycles in that time than OUTAGE_CYCLES)
        assert len(kept) > 10 * len(SLAVES), len(kept)
        with Service(conf, tmp_path / "second.log") as second:
            second.wait_log(r"messages \(\d+ bytes\) kept from before, replayed first")
            time.sleep(OUTAGE_CYCLES * CYCLE_MS / 1000 / 2)  # pacing: the second half
            broker.restart()

            def arrived() -> set[bytes]:
                return {m.payload for m in probe.messages()}

            wait_for(lambda: kept <= arrived(), timeout=120,
                     what="every message kept at the kill received")
            found = second.wait_log(r"metrics on http://127\.0\.0\.1:(\d+)/metrics")
            port = int(found.rsplit(":", 1)[1].split("/")[0])
            wait_for(lambda: "edgemodbus_mqtt_spool_pending 0.0" in scrape(port),
                     timeout=60, what="the second half of the outage replayed")
            text = scrape(port)
            assert "edgemodbus_mqtt_spool_dropped_size_total 0.0" in text
            replayed = metric(text, "edgemodbus_mqtt_spool_replayed_total")
            assert replayed >= len(kept), (replayed, len(kept))
        received = probe.messages()
        counts: dict[bytes, int] = {}
        for m in received:
            if m.dup:  # the broker's redelivery to the probe, not our publisher's
                continue
            counts[m.payload] = counts.get(m.payload, 0) + 1
        twice = {p for p, n in counts.items() if n > 1}
        early = {m.payload for m in received[:before]}
        assert twice <= early, f"{len(twice - early)} published twice, not in flight"
        for code, bodies in received_data(probe).items():
            stamps = [b["ts"] for b in bodies]
            assert stamps == sorted(stamps), f"{code}: out of order"
        print(f"\nkill -9: {len(kept)} messages in the spool at the kill, all received; "
              f"{len(received)} received in all, {len(twice)} twice")
    finally:
        probe.stop()


def metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not exported")


def spool_rows(path: Path) -> set[bytes]:
    """The payloads a (dead) gateway's spool file holds, read with plain sqlite3."""
    db = sqlite3.connect(path)
    try:
        return {bytes(row[0]) for row in db.execute("SELECT payload FROM messages")}
    finally:
        db.close()


@pytest.mark.parametrize("mode", ["per-item", "batch"])
def test_after_a_replay_the_retained_value_is_the_current_one(
        broker: Mosquitto, tmp_path: Path, mode: str) -> None:
    """Issue #24: values change during an outage, then stop changing (the driver stops
    before the broker is back, so nothing live follows the replay).  A subscriber that
    arrives after the replay gets, retained, the last value the driver read.  Before:
    the replay went out with retain off and the broker kept the value from before the
    outage."""
    with Simulator([1], size=10) as peer:
        mover = CounterMover(Area.HOLDING_REGISTER, 0, 1, interval_ms=30, start=2100)
        peer.slave(1).add_mover(mover)
        port = peer.serve_tcp("127.0.0.1", 0)
        file = device_file(port, 1, cycle_ms=50)
        file["addressList"] = file["addressList"][:3]
        cfg = em.load_device_config(file)
        recorder = Recorder(per_item=True)
        settings = {"port": broker.port, "mode": mode, "qos": 1, "retain": True,
                    "reconnectMin": 100, "reconnectMax": 400,
                    "storeAndForward": {"path": str(tmp_path / "spool.db")}}
        pub = MqttPublisher(settings, gateway_id="gw-retain").start()
        drv = em.DriverModbusRtu()
        try:
            assert pub.wait_connected(10)
            drv.addresses_updated_callback = recorder
            pub.attach(drv, "dev1")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            wait_for(lambda: pub.stats()["published"] > 0, timeout=30,
                     what="the first values published")
            broker.stop()
            wait_for(lambda: not pub.connected, what="the publisher sees the broker go")
            spooled = pub.stats()["spool"]["appended"]
            wait_for(lambda: pub.stats()["spool"]["appended"] >= spooled + 10, timeout=60,
                     what="changes spooled during the outage")
            drv.stop_device()  # the last value read stays the device's value
            last = {}
            for report in recorder.reports:
                last.update(report["values"])
            broker.restart()
            assert pub.wait_connected(10)
            wait_for(lambda: pub.stats()["spool"]["stored"] == 0, timeout=60,
                     what="the backlog replayed and acknowledged")
            with MqttProbe(broker.port, [f"{P}/dev1/+"]) as late:
                leaf = "$batch" if mode == "batch" else "t0"
                got = late.wait_for(f"{P}/dev1/{leaf}", lambda m: m.retain)
                body = got.json()
                value = body["values"]["t0"] if mode == "batch" else body["value"]
                assert value == last["t0"], (value, last["t0"])
        finally:
            drv.stop_device()
            pub.stop()


def test_an_outage_that_fills_the_spools_disk_loses_nothing_within_the_memory_bound(
        sim: int, broker: Mosquitto, tmp_path: Path, caplog: pytest.LogCaptureFixture
        ) -> None:
    """Issue #25: the spool on a 2 MB tmpfs (maxBytes 100 MB, the default) and a 15 s
    outage of 10,000 tags that writes more than the disk holds.  Before: every message
    after the disk filled was lost (7,439), acks failed so the spool never shrank, live
    data was lost after the broker came back, ~90 ERROR lines a second.  Now the file
    stops growing while its disk has room for acknowledgements, the rest waits in
    memory, and everything arrives in order once the broker is back."""
    with small_tmpfs(tmp_path) as disk:
        caplog.set_level(logging.WARNING, "edgemodbus.mqtt")
        settings = {"port": broker.port, "mode": "batch", "qos": 1, "reconnectMin": 100,
                    "reconnectMax": 400, "storeAndForward": {
                        "path": str(disk / "spool.db"), "replayRatePerS": 2000}}
        configs = [em.load_device_config(device_file(sim, s)) for s in SLAVES]
        recorders = {str(c.organization.device_code): Recorder(False) for c in configs}
        probe = MqttProbe(broker.port, [f"{P}/+/$batch"], client_id="sf-full-probe",
                          clean_session=False).start()
        pub = MqttPublisher(settings, gateway_id="gw-full").start()
        drivers: list[em.DriverModbusRtu] = []
        try:
            assert pub.wait_connected(10)
            for cfg in configs:
                drv = em.DriverModbusRtu()
                drv.addresses_updated_callback = recorders[str(cfg.organization.device_code)]
                pub.attach(drv, cfg.organization.device_code)
                assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
                drivers.append(drv)
            wait_for(lambda: len(received_data(probe)) == len(SLAVES), timeout=30,
                     what="every device published")
            broker.stop()
            wait_for(lambda: not pub.connected, what="the publisher sees the broker go")
            started = time.monotonic()
            largest = 0

            def disk_full_for_a_while() -> bool:
                nonlocal largest
                spool = pub.stats()["spool"]
                largest = max(largest, spool["fileBytes"])
                return bool(spool["memory"] >= 200)
            wait_for(disk_full_for_a_while, timeout=120, what="the disk full, memory used")
            outage = time.monotonic() - started
            broker.restart()
            assert pub.wait_connected(10)
            wait_for(lambda: pub.stats()["spool"]["pending"] == 0
                     and pub.stats()["spool"]["memory"] == 0, timeout=120,
                     what="the spool and the memory queue replayed")
            live = sum(len(r.reports) for r in recorders.values())
            wait_for(lambda: sum(len(r.reports) for r in recorders.values()) > live + 50,
                     timeout=30, what="live data after the replay")
            for drv in drivers:
                drv.stop_device()
            total = sum(len(r.reports) for r in recorders.values())
            wait_for(lambda: sum(len(v) for v in received_data(probe).values()) >= total,
                     timeout=60, what="every report received")
            wait_for(lambda: pub.stats()["spool"]["stored"] == 0, timeout=30,
                     what="every message acknowledged: the spool shrank")
            got = received_data(probe)
            missing = sum(len(check_in_order(got[code], rec.reports))
                          for code, rec in recorders.items())
            errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
            stats = pub.stats()
            print(f"\nfull disk: {total} reports, {missing} lost, outage {outage:.1f} s, "
                  f"largest file {largest} bytes on a 2 MiB disk, {len(errors)} ERROR "
                  f"lines ({len(errors) / outage:.1f}/s); spool {stats['spool']}")
            assert missing == 0 and stats["dropped"] == 0
            assert stats["spool"]["memoryDropped"] == 0 and stats["spool"]["errors"] > 0
            assert largest <= 2 * 1024 * 1024
            assert len(errors) <= 3 * (outage / 10 + 2)  # 3 lines per kind and 10 s
        finally:
            for drv in drivers:
                drv.stop_device()
            pub.stop()
            probe.stop()


def test_the_gateway_starts_on_a_damaged_spool_and_polls(
        sim: int, broker: Mosquitto, tmp_path: Path) -> None:
    """Issue #25: the spool file overwritten with garbage between runs.  Before: the
    gateway exited 2 at start (no polling, no server; a restart loop under systemd).
    Now the file is moved aside, reported, and the gateway polls and publishes."""
    conf = tmp_path / "conf"
    conf.mkdir()
    (conf / "spool.db").write_bytes(b"\x13garbage from a bad shutdown" * 500)
    write_json(conf / "gateway.json", {
        "gatewayId": "gw-damaged", "statusCheckInterval": 100,
        "mqtt": {"port": broker.port, "mode": "batch", "qos": 1,
                 "storeAndForward": {"path": "spool.db"}}})
    write_json(conf / "dev1.json", device_file(sim, 1, cycle_ms=200))
    with MqttProbe(broker.port, [f"{P}/dev1/$batch"]) as probe, \
            Service(conf, tmp_path / "gateway.log") as service:
        service.wait_log(r"spool .*spool\.db: unreadable, not an SQLite file .* moved "
                         r"aside to .*spool\.db\.corrupt-\d{8}T\d{6}Z")
        probe.wait_for(f"{P}/dev1/$batch", timeout=30)
    aside = [p for p in conf.iterdir() if p.name.startswith("spool.db.corrupt-")]
    assert len(aside) == 1 and aside[0].read_bytes().startswith(b"\x13garbage")
