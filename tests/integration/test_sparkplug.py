"""Sparkplug B edge node end to end: a real mosquitto, a real paho subscriber, our driver
polling a pymodbus slave (own process); every payload is read by tests/sparkplug_wire.py,
a protobuf reader written by hand from the specification's field numbers (not our
encoder), and commands are written by it."""

from __future__ import annotations

import itertools
import json
import logging
import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.northbound.metrics import MetricsExporter
from edgemodbus.northbound.sparkplug.bdseq import MAGIC
from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher
from tests.integration.test_metrics import lbl, scrape
from tests.mosquitto import Mosquitto, MqttProbe, Received
from tests.peers import ExceptionRange, PymodbusSlave, default_register
from tests.sparkplug_wire import TYPES, Payload, decode, encode, encode_metric
from tests.waiting import wait_for

G, N = "plant1", "gw1"
BASE = f"spBv1.0/{G}"


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    # hr 150..159 answer exception 04 (slave device failure): reads and writes refused
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200,
                       exception_ranges=[ExceptionRange(150, 160, code=4, area="hr")]) as peer:
        yield peer


ITEMS: list[dict[str, Any]] = [
    {"name": "t0", "address": "hr:0", "deviceDataType": "UInt16"},
    {"name": "neg", "address": "hr:1", "deviceDataType": "Int16"},
    {"name": "f", "address": "hr:10", "deviceDataType": "Float32"},
    {"name": "d", "address": "hr:20", "deviceDataType": "Float64"},
    {"name": "u32", "address": "hr:30", "deviceDataType": "UInt32"},
    {"name": "s", "address": "hr:40", "deviceDataType": "String", "quantity": 2},
    {"name": "scaled", "address": "hr:50", "deviceDataType": "Int16", "dataMultiplier": 0.1},
    {"name": "coil", "address": "coil:3", "deviceDataType": "Boolean"},
    {"name": "sp", "address": "hr:100", "deviceDataType": "UInt16"},
    {"name": "bad", "address": "hr:150", "deviceDataType": "UInt16"},
]


def device(port: int, code: str = "dev1", **comm: Any) -> em.DeviceConfig:
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
        "readCycle": 100, "readTimeout": 300, "reconnectInterval": 300, "byteTimeout": 50,
        "offlineAfterFailedCycles": 1,
    }
    base.update(comm)
    return em.load_device_config(
        {"organization": {"deviceCode": code}, "communication": base, "addressList": ITEMS})


def fill(slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 1, [0xFFFB])  # -5
    slave.set_registers(1, "hr", 10, list(struct.unpack(">2H", struct.pack(">f", 1.5))))
    slave.set_registers(1, "hr", 20, list(struct.unpack(">4H", struct.pack(">d", -2.25))))
    slave.set_registers(1, "hr", 30, [0x0001, 0x0002])  # 65538
    slave.set_registers(1, "hr", 40, [0x4F4B, 0x2100])  # "OK!"
    slave.set_registers(1, "hr", 50, [0xFF9C])  # -100 * 0.1
    slave.set_bits(1, "co", 3, [True])


class Node:
    """A Sparkplug publisher plus one driver: started on enter, stopped on exit."""

    def __init__(self, broker_port: int, cfg: em.DeviceConfig, **sparkplug: Any) -> None:
        sparkplug.setdefault("groupId", G)
        settings = {"mode": "sparkplug", "port": broker_port, "sparkplug": sparkplug,
                    "statusCheckInterval": 100}
        self.cfg = cfg
        self.pub = SparkplugPublisher(settings, gateway_id=N)
        self.drv = em.DriverModbusRtu()

    def __enter__(self) -> Node:
        self.pub.start()
        self.pub.attach(self.drv, self.cfg.organization.device_code)
        assert self.drv.start_device(self.cfg.organization, self.cfg.communication,
                                     self.cfg.address_list)
        return self

    def __exit__(self, *exc: object) -> None:
        self.drv.stop_device()
        self.pub.stop()


def payload_of(msg: Received) -> Payload:
    return decode(msg.payload)


def wait_payload(probe: MqttProbe, topic: str, match: Any = lambda p: True,
                 after: int = 0, timeout: float = 10.0) -> Payload:
    msg = probe.wait_for(topic, lambda m: match(decode(m.payload)), timeout=timeout,
                         after=after)
    return decode(msg.payload)


def dcmd(probe: MqttProbe, code: str, *metrics: bytes) -> None:
    probe.publish(f"{BASE}/DCMD/{N}/{code}", encode(list(metrics), int(time.time() * 1000)))


def test_births_aliases_types_quality_and_ddata(broker: Mosquitto,
                                                 slave: PymodbusSlave) -> None:
    fill(slave)
    before = int(time.time() * 1000)
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port,
                                                              device(slave.port)):
        nbirth = wait_payload(probe, f"{BASE}/NBIRTH/{N}")
        assert nbirth.seq == 0
        node = nbirth.by_name()
        assert node["bdSeq"].datatype == TYPES["Int64"] and node["bdSeq"].value == 0
        rebirth = node["Node Control/Rebirth"]
        assert rebirth.datatype == TYPES["Boolean"] and rebirth.raw is False

        birth = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        assert birth.seq == 1
        assert before <= (birth.timestamp or 0) <= int(time.time() * 1000)
        m = birth.by_name()
        assert set(m) == {it["name"] for it in ITEMS}
        expect = {"t0": ("UInt16", default_register(1, "hr", 0)), "neg": ("Int16", -5),
                  "f": ("Float", 1.5), "d": ("Double", -2.25), "u32": ("UInt32", 65538),
                  "s": ("String", "OK!"), "scaled": ("Double", -10.0),
                  "coil": ("Boolean", True), "sp": ("UInt16", default_register(1, "hr", 100))}
        for name, (kind, value) in expect.items():
            assert m[name].datatype == TYPES[kind], name
            assert m[name].value == pytest.approx(value), name
            assert not m[name].is_null and m[name].properties["Quality"] == 192, name
            assert before - 60_000 <= (m[name].timestamp or 0) <= int(time.time() * 1000)
        # an Invalid item: null, bad quality, the reason
        assert m["bad"].datatype == TYPES["UInt16"] and m["bad"].is_null
        assert m["bad"].raw is None and m["bad"].properties["Quality"] == 0
        assert "04" in m["bad"].properties["errorReason"] or \
            "failure" in m["bad"].properties["errorReason"].lower()
        aliases = [metric.alias for metric in birth.metrics]
        assert None not in aliases and len(set(aliases)) == len(aliases)

        # a change: DDATA by alias only, next seq
        mark = probe.mark()
        slave.set_registers(1, "hr", 0, [4242])
        data = wait_payload(probe, f"{BASE}/DDATA/{N}/dev1", after=mark)
        assert data.seq == 2
        assert [(x.name, x.alias, x.value) for x in data.metrics] == [
            (None, m["t0"].alias, 4242)]
        assert data.metrics[0].datatype is None  # DDATA does not repeat it


def test_dbirth_waits_for_the_first_complete_cycle(broker: Mosquitto) -> None:
    """The issue's case: 40 one-register blocks from a slave that takes 15 ms a reply, the
    first answered with an exception.  The device is Running after that first reply; its
    DBIRTH went out then, 39 metrics null ("not read yet") and without a timestamp, and
    the next DDATA repeated values.  Now the DBIRTH carries every value of the first
    cycle, each metric with a timestamp, and no DDATA repeats a value published."""
    items = [{"name": f"r{i}", "address": f"hr:{2 * i}", "deviceDataType": "UInt16"}
             for i in range(40)]
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200, response_delay=0.015,
                       exception_ranges=[ExceptionRange(0, 1, code=4, area="hr")]) as slow:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "dev1"},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": slow.port, "slaveId": 1, "readCycle": 200,
                              "readTimeout": 2000, "maxMergeAddressGap": 0},
            "addressList": items})
        before = int(time.time() * 1000)
        with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port, cfg) as node:
            assert len(node.drv.read_plan()) == 40
            born = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", timeout=30)
            mark = probe.mark()
            metrics = born.by_name()
            assert set(metrics) == {it["name"] for it in items}
            for m in born.metrics:
                assert before <= (m.timestamp or 0) <= int(time.time() * 1000), m
            assert metrics["r0"].is_null and metrics["r0"].properties["Quality"] == 0
            assert "04" in metrics["r0"].properties["errorReason"]
            for i in range(1, 40):
                m = metrics[f"r{i}"]
                assert not m.is_null and m.value == default_register(1, "hr", 2 * i), m
                assert m.properties == {"Quality": 192}, m
            last = {m.alias: m.value for m in born.metrics}
            slow.set_registers(1, "hr", 2, [default_register(1, "hr", 2) ^ 0x5A5A])
            wait_payload(probe, f"{BASE}/DDATA/{N}/dev1", after=mark, timeout=30,
                         match=lambda p: metrics["r1"].alias in p.by_alias())
            for msg in probe.messages()[mark:]:
                if msg.topic != f"{BASE}/DDATA/{N}/dev1":
                    continue
                for alias, value in decode(msg.payload).values(born).items():
                    assert value != last[alias], f"alias {alias}: {value} published again"
                    last[alias] = value
            assert node.pub.stats()["dbirths"] == 1


def test_seq_wraps_after_255(broker: Mosquitto, slave: PymodbusSlave) -> None:
    cfg = device(slave.port, readCycle=10)
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port, cfg):
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        deadline = time.monotonic() + 60
        value = 0
        while time.monotonic() < deadline:
            seqs = [decode(r.payload).seq for r in probe.received
                    if r.topic.startswith(f"{BASE}/D") or "/NBIRTH/" in r.topic]
            if len(seqs) > 260:
                break
            value += 1
            slave.set_registers(1, "hr", 0, [value])
            time.sleep(0.012)  # pacing: one change every few cycles
        assert len(seqs) > 260, f"only {len(seqs)} messages"
        assert seqs[:2] == [0, 1]
        assert all(b == (a + 1) % 256 for a, b in itertools.pairwise(seqs)), seqs
        assert 255 in seqs and seqs[seqs.index(255) + 1] == 0


def test_rebirth_on_ncmd_keeps_bdseq_and_aliases(broker: Mosquitto,
                                                 slave: PymodbusSlave) -> None:
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port,
                                                              device(slave.port)) as node:
        first = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        bd_seq = wait_payload(probe, f"{BASE}/NBIRTH/{N}").by_name()["bdSeq"].value
        mark = probe.mark()
        probe.publish(f"{BASE}/NCMD/{N}", encode(
            [encode_metric(name="Node Control/Rebirth", datatype="Boolean", value=True)]))
        again = wait_payload(probe, f"{BASE}/NBIRTH/{N}", after=mark)
        assert again.seq == 0 and again.by_name()["bdSeq"].value == bd_seq
        dbirth = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", after=mark)
        assert dbirth.seq == 1
        assert {k: v.alias for k, v in dbirth.by_name().items()} == {
            k: v.alias for k, v in first.by_name().items()}
        assert node.pub.stats()["rebirths"] == 1


def test_dcmd_writes_are_confirmed_in_ddata(broker: Mosquitto,
                                           slave: PymodbusSlave) -> None:
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port,
                                                              device(slave.port)) as node:
        born = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        birth = born.by_name()
        mark = probe.mark()
        # by alias (as a host does after the birth), and by name with a negative Int16
        dcmd(probe, "dev1", encode_metric(alias=birth["sp"].alias, datatype="UInt16",
                                          value=777))
        wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",  # (a poll may report first)
                     lambda p: p.values(born).get(birth["sp"].alias) == 777, after=mark)
        assert slave.registers(1, "hr", 100) == [777]
        dcmd(probe, "dev1", encode_metric(name="neg", datatype="Int16", value=-1234))
        wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",
                     lambda p: p.values(born).get(birth["neg"].alias) == -1234, after=mark)
        assert slave.registers(1, "hr", 1) == [(-1234) & 0xFFFF]
        wait_for(lambda: node.pub.stats()["writes"] == 2, what="2 writes counted")
        assert node.pub.stats()["writesRefused"] == 0


def test_refused_writes_are_logged_and_counted(broker: Mosquitto, slave: PymodbusSlave,
                                               caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.sparkplug")
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port,
                                                              device(slave.port)) as node:
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        dcmd(probe, "dev1", encode_metric(name="bad", datatype="UInt16", value=5))
        wait_for(lambda: node.pub.stats()["writesRefused"] == 1, what="a refused write")
        dcmd(probe, "dev1", encode_metric(name="nosuch", datatype="UInt16", value=5))
        wait_for(lambda: node.pub.stats()["writesRefused"] == 2, what="unknown metric")
        dcmd(probe, "dev1", encode_metric(name="sp", datatype="UInt16", value=70000))
        wait_for(lambda: node.pub.stats()["writesRefused"] == 3, what="out of range")
        assert node.pub.stats()["writes"] == 0
        assert slave.registers(1, "hr", 100) == [default_register(1, "hr", 100)]
        text = caplog.text
        assert "dev1: DCMD write bad=5 refused: bad: slave 1 FC06: exception 0x04" in text
        assert "'nosuch' refused: no such metric" in text
        assert "sp=70000 refused: item 'sp': cannot write 70000: allowed 0..65535" in text
        # the silent conversions (12.5 was written as 12, true as 1, "99" as 99);
        # past three refusals in 10 s their log lines are folded into a summary
        for n, metric in enumerate((encode_metric(name="sp", datatype="Float", value=12.5),
                                    encode_metric(name="sp", datatype="Boolean", value=True),
                                    encode_metric(name="sp", datatype="String", value="99")),
                                   start=4):
            dcmd(probe, "dev1", metric)
            wait_for(lambda n=n: node.pub.stats()["writesRefused"] == n, what=f"refusal {n}")
        assert node.pub.stats()["commandLogsSuppressed"] == 3
        assert node.pub.stats()["writes"] == 0
        assert slave.registers(1, "hr", 100) == [default_register(1, "hr", 100)]


def test_a_flood_of_rebirth_requests_is_paced(broker: Mosquitto,
                                             slave: PymodbusSlave) -> None:
    """The issue's 1,000 Rebirth NCMDs made 1,000 NBIRTH and 2,000 DBIRTH.  Now the first
    is answered at once and the others within rebirthInterval are folded into one
    rebirth when it ends: at most one per interval while the flood lasts, plus that one."""
    interval = 1.5
    request = encode([encode_metric(name="Node Control/Rebirth", datatype="Boolean",
                                    value=True)])
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(
            broker.port, device(slave.port), rebirthInterval=int(interval * 1000)) as node:
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        mark = probe.mark()
        started = time.monotonic()
        for _ in range(1000):
            probe.publish(f"{BASE}/NCMD/{N}", request, qos=0)
        wait_for(lambda: node.pub.stats()["commands"] == 1000, timeout=60,
                 what="1,000 NCMD taken")
        flood = time.monotonic() - started
        stats = node.pub.stats()
        wait_for(lambda: node.pub.stats()["rebirths"] == stats["rebirths"] + 1
                 and node.pub.stats()["dbirths"] == stats["dbirths"] + 1,
                 timeout=interval + 30, what="the folded rebirth")
        stats = node.pub.stats()
        # each rebirth answers one request at once or the requests folded before it
        assert 1000 - stats["rebirths"] <= stats["rebirthsFolded"] <= 999, stats
        assert 2 <= stats["rebirths"] <= 2 + flood / interval, (stats, flood)
        # the counter moves when the publisher sends; the probe sees it a moment later
        wait_for(lambda: len([m for m in probe.messages()[mark:] if "/NBIRTH/" in m.topic])
                 >= stats["rebirths"], timeout=30, what="every NBIRTH at the probe")
        nbirths = len([m for m in probe.messages()[mark:] if "/NBIRTH/" in m.topic])
        assert nbirths == stats["rebirths"]
        assert stats["commandErrors"] == 0


def test_prometheus_exports_the_sparkplug_counters(broker: Mosquitto,
                                                   slave: PymodbusSlave) -> None:
    """The real exporter, scraped over HTTP, with the publisher set as the gateway sets
    it: births, DDATA, rebirths, DCMD writes (confirmed, refused), bdSeq, born."""
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(
            broker.port, device(slave.port)) as node, MetricsExporter({"port": 0}) as exporter:
        exporter.set_publisher(node.pub)
        birth = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1").by_name()
        _, samples = scrape(exporter.port)
        assert samples[("edgemodbus_sparkplug_born", ())] == 1
        mark = probe.mark()
        probe.publish(f"{BASE}/NCMD/{N}", encode(
            [encode_metric(name="Node Control/Rebirth", datatype="Boolean", value=True)]))
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", after=mark)
        mark = probe.mark()
        dcmd(probe, "dev1", encode_metric(alias=birth["sp"].alias, datatype="UInt16",
                                          value=4321))
        wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",
                     lambda p: birth["sp"].alias in p.by_alias(), after=mark)
        dcmd(probe, "dev1", encode_metric(name="nosuch", datatype="UInt16", value=5))
        wait_for(lambda: node.pub.stats()["writesRefused"] == 1, what="a refused write")
        _, samples = scrape(exporter.port)
        stats = node.pub.stats()
    got = {name: samples[(f"edgemodbus_sparkplug_{name}_total", ())] for name in (
        "nbirths", "dbirths", "ddata", "ddeaths", "rebirths", "writes", "writes_refused")}
    assert got == {"nbirths": 2, "dbirths": 2, "ddata": stats["ddata"], "ddeaths": 0,
                   "rebirths": 1, "writes": 1, "writes_refused": 1}
    assert got["ddata"] >= 1
    assert samples[("edgemodbus_sparkplug_bd_seq", ())] == stats["bdSeq"] == 0
    assert samples[("edgemodbus_sparkplug_born", ())] == 1
    assert samples[("edgemodbus_mqtt_published_total", lbl(device="dev1"))] == stats[
        "devices"]["dev1"]["published"]


def test_ddeath_when_offline_then_dbirth(broker: Mosquitto, slave: PymodbusSlave) -> None:
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port,
                                                              device(slave.port)) as node:
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        mark = probe.mark()
        slave.set_offline(1)
        death = wait_payload(probe, f"{BASE}/DDEATH/{N}/dev1", after=mark)
        assert death.metrics == [] and death.seq is not None
        slave.set_offline(1, False)
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", after=mark)
        mark = probe.mark()
        node.pub.detach(node.drv)
        wait_payload(probe, f"{BASE}/DDEATH/{N}/dev1", after=mark)


def state(online: bool, stamp: int) -> bytes:
    return json.dumps({"online": online, "timestamp": stamp}).encode()


def connections(broker: Mosquitto) -> int:
    """How many times the edge node connected, as the broker logged it."""
    return broker.log_text.count(f" as edgemodbus-{N} ")


def test_primary_host_state_gates_births(broker: Mosquitto, slave: PymodbusSlave) -> None:
    """Births wait for the host's online STATE; offline: NDEATH (the session's bdSeq),
    disconnect, a new connection, births again only once the host is online, bdSeq + 1
    and the same aliases."""
    host = "spBv1.0/STATE/scada"
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(
            broker.port, device(slave.port), primaryHostId="scada") as node:
        assert node.pub.wait_connected(10)
        wait_for(lambda: node.drv.stats().get("cycles", 0) >= 3, what="3 cycles")
        time.sleep(0.3)  # pacing: a window in which no birth may go out
        assert probe.on(f"{BASE}/NBIRTH/{N}") == [] and probe.on(
            f"{BASE}/DBIRTH/{N}/dev1") == []
        now = int(time.time() * 1000)
        probe.publish(host, state(True, now))  # the host comes online
        first = wait_payload(probe, f"{BASE}/NBIRTH/{N}").by_name()["bdSeq"].value
        aliases = {k: v.alias for k, v in wait_payload(
            probe, f"{BASE}/DBIRTH/{N}/dev1").by_name().items()}
        assert connections(broker) == 1
        mark = probe.mark()
        probe.publish(host, state(True, now - 5000))  # stale: ignored
        probe.publish(host, state(False, now + 1))
        death = wait_payload(probe, f"{BASE}/NDEATH/{N}", after=mark)
        assert death.by_name()["bdSeq"].value == first
        wait_for(lambda: connections(broker) == 2, what="the edge node's new connection")
        assert f"Client edgemodbus-{N} disconnected." in broker.log_text  # not a will
        wait_for(lambda: node.pub.stats()["bdSeq"] == first + 1, what="the new session")
        stats = node.pub.stats()
        assert stats["connects"] == 2 and stats["disconnects"] == 1 and not stats["born"]
        time.sleep(0.3)  # pacing: connected, the host still offline: no birth
        assert probe.on(f"{BASE}/NBIRTH/{N}")[1:] == []
        assert len(probe.on(f"{BASE}/NDEATH/{N}")) == 1
        mark = probe.mark()
        probe.publish(host, state(True, now + 2))
        birth = wait_payload(probe, f"{BASE}/NBIRTH/{N}", after=mark)
        assert birth.seq == 0 and birth.by_name()["bdSeq"].value == first + 1
        dbirth = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", after=mark)
        assert {k: v.alias for k, v in dbirth.by_name().items()} == aliases
        assert len(probe.on(f"{BASE}/NBIRTH/{N}")) == 2  # the stale STATE did nothing
        mark = probe.mark()
        node.pub.stop()  # the new session's NDEATH
        death = wait_payload(probe, f"{BASE}/NDEATH/{N}", after=mark)
        assert death.by_name()["bdSeq"].value == first + 1


def test_ndeath_is_the_will_with_the_sessions_bdseq(broker: Mosquitto, slave: PymodbusSlave,
                                                   tmp_path: Path) -> None:
    """The gateway service in its own process (mode sparkplug): killed, the broker sends
    its will, the NDEATH whose bdSeq is the NBIRTH's; restarted, bdSeq (kept in
    bdSeqFile) is one more; stopped cleanly, it publishes NDEATH itself."""
    folder = tmp_path / "conf"
    folder.mkdir()
    (folder / "gateway.json").write_text(json.dumps({
        "gatewayId": N,
        "mqtt": {"mode": "sparkplug", "port": broker.port, "keepalive": 5,
                 "sparkplug": {"groupId": G, "bdSeqFile": "bdseq"}}}))
    dev = device(slave.port)
    (folder / "dev1.json").write_text(json.dumps({
        "organization": {"deviceCode": "dev1"},
        "communication": dev.communication.to_dict(), "addressList": ITEMS}))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2] / "src"))

    def gateway() -> subprocess.Popen[bytes]:
        return subprocess.Popen([sys.executable, "-m", "edgemodbus.gateway", "--config-dir",
                                 str(folder), "-q"], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)

    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe:
        proc = gateway()
        try:
            birth = wait_payload(probe, f"{BASE}/NBIRTH/{N}", timeout=20)
            wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
            first = birth.by_name()["bdSeq"].value
            mark = probe.mark()
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
            death = wait_payload(probe, f"{BASE}/NDEATH/{N}", after=mark)
            assert death.by_name()["bdSeq"].value == first
            assert death.seq is None
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        assert (folder / "bdseq").read_text() == f"{MAGIC}\n{first + 1}\n"
        mark = probe.mark()
        proc = gateway()
        try:
            birth = wait_payload(probe, f"{BASE}/NBIRTH/{N}", after=mark, timeout=20)
            assert birth.by_name()["bdSeq"].value == first + 1
            wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", after=mark)
            mark = probe.mark()
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(15) == 0
            death = wait_payload(probe, f"{BASE}/NDEATH/{N}", after=mark)
            assert death.by_name()["bdSeq"].value == first + 1
        finally:
            if proc.poll() is None:
                proc.kill()
            stderr = proc.stderr.read().decode() if proc.stderr else ""
            proc.wait()
        assert "Traceback" not in stderr, stderr
