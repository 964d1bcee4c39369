"""Reads on demand from Sparkplug (``Device Control/Read`` in a DCMD, ``Node
Control/Read`` in an NCMD; docs/reporting.md) and period reports in DDATA: a real
mosquitto, payloads read and written by tests/sparkplug_wire.py (written from the
specification, not our encoder), a pymodbus slave."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

import edgemodbus as em
from tests.integration.test_sparkplug import BASE, N, Node, dcmd, wait_payload
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.sparkplug_wire import TYPES, decode, encode, encode_metric
from tests.waiting import wait_for


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200, fill="zero") as peer:
        yield peer


def device(port: int, **comm: Any) -> em.DeviceConfig:
    base: dict[str, Any] = {
        "transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port, "slaveId": 1,
        "readCycle": 100, "readTimeout": 300, "reconnectInterval": 300, "byteTimeout": 50,
    }
    base.update(comm)
    items = [
        {"name": "p", "address": "hr:0", "deviceDataType": "UInt16"},
        {"name": "d", "address": "hr:40", "deviceDataType": "UInt16", "readCycle": "demand"},
        {"name": "slow", "address": "hr:60", "deviceDataType": "UInt16", "reportEvery": 300},
    ]
    return em.load_device_config(
        {"organization": {"deviceCode": "dev1"}, "communication": base, "addressList": items})


def test_device_control_read_reads_the_device_into_ddata(broker: Mosquitto,
                                                         slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 40, [4040])
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, \
            Node(broker.port, device(slave.port)) as node:
        nbirth = wait_payload(probe, f"{BASE}/NBIRTH/{N}").by_name()
        read = nbirth["Node Control/Read"]
        assert read.datatype == TYPES["Boolean"] and read.raw is False
        born = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        alias = born.by_name()["d"].alias
        assert born.by_name()["d"].is_null  # never read yet
        requests = slave.request_count(1)
        mark = probe.mark()
        dcmd(probe, "dev1", encode_metric(name="Device Control/Read", datatype="Boolean",
                                          value=True))
        wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",
                     lambda p: p.values(born).get(alias) == 4040, after=mark)
        assert slave.request_count(1) > requests
        # the node-wide read: every device, the same value published again
        mark = probe.mark()
        probe.publish(f"{BASE}/NCMD/{N}", encode(
            [encode_metric(name="Node Control/Read", datatype="Boolean", value=True)]))
        wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",
                     lambda p: p.values(born).get(alias) == 4040, after=mark)
        # one item, named by a String value
        slave.set_registers(1, "hr", 40, [4141])
        mark = probe.mark()
        dcmd(probe, "dev1", encode_metric(name="Device Control/Read", datatype="String",
                                          value="d"))
        ddata = wait_payload(probe, f"{BASE}/DDATA/{N}/dev1",
                             lambda p: p.values(born).get(alias) == 4141, after=mark)
        assert set(ddata.values(born)) == {alias}  # p unchanged: not in it
        # a read metric that is not true: refused, counted, nothing read
        dcmd(probe, "dev1", encode_metric(name="Device Control/Read", datatype="Boolean",
                                          value=False))
        wait_for(lambda: node.pub.stats()["readsRefused"] == 1, what="the refusal")
        stats = node.pub.stats()
        assert stats["reads"] == 3 and stats["commandErrors"] == 0


def test_report_every_goes_out_in_ddata(broker: Mosquitto, slave: PymodbusSlave) -> None:
    slave.set_registers(1, "hr", 60, [66])
    with MqttProbe(broker.port, [f"{BASE}/#"]) as probe, Node(broker.port, device(slave.port)):
        born = wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1")
        slow, p = born.by_name()["slow"].alias, born.by_name()["p"].alias

        def ddata_with(alias: int) -> int:
            return sum(alias in decode(m.payload).values(born)
                       for m in probe.on(f"{BASE}/DDATA/{N}/dev1"))

        wait_for(lambda: ddata_with(slow) >= 3, timeout=15, what="3 period reports")
        assert ddata_with(p) == 0  # unchanged, no period: only in the DBIRTH


def test_a_storm_of_read_commands_joins_waiting_reads_and_polling_goes_on(
        broker: Mosquitto) -> None:
    """500 DCMD reads of one item, and NCMD reads, as fast as a client sends them, to a
    slave that takes 20 ms a request: each joins a read still waiting on the line
    (poll/on_demand.py), so none is refused (past the line's 64 jobs they were), few reach
    the slave, and the device goes on polling.  Hostile read metrics (a 200-character
    item name, a read of a name the DBIRTH did not have) are refused and counted."""
    n = 500
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200, fill="zero",
                       response_delay=0.02) as slow, \
            MqttProbe(broker.port, [f"{BASE}/#"]) as probe, \
            Node(broker.port, device(slow.port, readTimeout=2000)) as node:
        wait_payload(probe, f"{BASE}/DBIRTH/{N}/dev1", timeout=30)
        cycles = node.drv.stats()["cycles"]
        requests = slow.request_count(1)
        read_d = encode([encode_metric(name="Device Control/Read", datatype="String",
                                       value="d")])
        for k in range(n):
            probe.publish(f"{BASE}/DCMD/{N}/dev1", read_d, qos=0)
            if k % 100 == 0:
                probe.publish(f"{BASE}/NCMD/{N}", encode([encode_metric(
                    name="Node Control/Read", datatype="Boolean", value=True)]), qos=0)
        wait_for(lambda: node.pub.stats()["reads"] == n + 5, timeout=60,
                 what=f"{n + 5} reads started")
        stats = node.pub.stats()
        assert stats["readsRefused"] == 0, stats
        wait_for(lambda: node.drv.stats()["cycles"] >= cycles + 5, timeout=30,
                 what="polling goes on")
        coalesced = node.drv.stats()["readsCoalesced"]
        assert coalesced > n // 2, coalesced
        assert slow.request_count(1) - requests < n // 2
        for name in ("x" * 200, "nosuch"):
            dcmd(probe, "dev1", encode_metric(name="Device Control/Read", datatype="String",
                                              value=name))
        wait_for(lambda: node.pub.stats()["readsRefused"] == 2, what="2 refusals")
