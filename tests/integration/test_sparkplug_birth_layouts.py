"""DBIRTH waits for the device's first complete cycle, for any layout (a property test):
1-60 one-register blocks, some failing (past the slave's registers: exception 02), some
on demand only (``readCycle: "demand"``), some on a slower scan rate, some with a period
report (``reportEvery``).  Read with tests/sparkplug_wire.py (Tahu's schema, not our
encoder), through a real mosquitto and a pymodbus slave:

- every DBIRTH metric has a timestamp; a polled item is born with its value unless its
  block failed (then Invalid with that reason, never "not read yet"); an on-demand item
  is Invalid saying it is read on demand only;
- no DDATA after the DBIRTH repeats a value it carried (one register is then changed:
  only it goes out);
- after a Rebirth (NCMD) the same holds for the new DBIRTH."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.northbound.sparkplug.devices import DEMAND_ONLY
from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, default_register
from tests.sparkplug_wire import Payload, decode, encode, encode_metric

SIZE = 8000  # the slave's registers: an item at or past it fails (exception 02)
SPACING = 130  # past maxBatch: each item its own block
KINDS = ("ok", "fail", "demand", "slow", "every")
_groups = itertools.count()


@pytest.fixture(scope="module")
def peers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Mosquitto, PymodbusSlave]]:
    with Mosquitto(tmp_path_factory.mktemp("mqtt")) as broker, \
            PymodbusSlave("rtu-over-tcp", units=(1,), size=SIZE) as slave:
        yield broker, slave


def item(k: int, kind: str) -> dict[str, Any]:
    address = SIZE + 10 * k if kind == "fail" else SPACING * k
    spec: dict[str, Any] = {"name": f"{kind}{k}", "address": f"hr:{address}",
                            "deviceDataType": "UInt16"}
    if kind == "demand":
        spec["readCycle"] = "demand"
    elif kind == "slow":
        spec["readCycle"] = 5000
    elif kind == "every":
        spec["reportEvery"] = 60000
    return spec


def check_birth(born: Payload, layout: list[str], since: int) -> None:
    now = int(time.time() * 1000)
    metrics = born.by_name()
    assert set(metrics) == {f"{kind}{k}" for k, kind in enumerate(layout)}
    for k, kind in enumerate(layout):
        m = metrics[f"{kind}{k}"]
        assert m.timestamp is not None and since <= m.timestamp <= now, m
        if kind == "fail":
            assert m.is_null and m.properties["Quality"] == 0, m
            reason = m.properties["errorReason"]
            assert "not read yet" not in reason and "02" in reason, m
        elif kind == "demand":
            assert m.is_null and m.properties == {"Quality": 0, "errorReason": DEMAND_ONLY}
        else:
            assert not m.is_null and m.value == default_register(1, "hr", SPACING * k), m


def check_no_repeats(probe: MqttProbe, topic: str, born: Payload, after: int) -> None:
    last = {m.alias: m.value for m in born.metrics}
    for msg in probe.messages()[after:]:
        if msg.topic == topic:
            for alias, value in decode(msg.payload).values(born).items():
                assert value != last[alias], f"alias {alias}: {value} published again"
                last[alias] = value


@settings(max_examples=12, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.lists(st.sampled_from(KINDS), min_size=1, max_size=60))
def test_the_first_dbirth_of_any_layout_carries_the_first_cycle(
        peers: tuple[Mosquitto, PymodbusSlave], layout: list[str]) -> None:
    broker, slave = peers
    group = f"g{next(_groups)}"
    base = f"spBv1.0/{group}"
    cfg = em.load_device_config({
        "organization": {"deviceCode": "dev1"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": slave.port, "slaveId": 1, "readCycle": 100,
                          "readTimeout": 1000, "offlineAfterFailedCycles": 1000},
        "addressList": [item(k, kind) for k, kind in enumerate(layout)]})
    polled = [k for k, kind in enumerate(layout) if kind in ("ok", "slow", "every")]
    for k in polled:  # back to the default of an earlier example's change
        slave.set_registers(1, "hr", SPACING * k, [default_register(1, "hr", SPACING * k)])
    since = int(time.time() * 1000)
    pub = SparkplugPublisher({"mode": "sparkplug", "port": broker.port,
                              "sparkplug": {"groupId": group, "rebirthInterval": 0}},
                             gateway_id="n1")
    drv = em.DriverModbusRtu()
    with MqttProbe(broker.port, [f"{base}/#"]) as probe:
        pub.start()
        try:
            pub.attach(drv, "dev1")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            topic = f"{base}/DDATA/n1/dev1"
            born = decode(probe.wait_for(f"{base}/DBIRTH/n1/dev1", timeout=30).payload)
            mark = probe.mark()
            check_birth(born, layout, since)
            if polled:
                k = polled[-1]
                changed = default_register(1, "hr", SPACING * k) ^ 0x5A5A
                slave.set_registers(1, "hr", SPACING * k, [changed])
                alias = born.by_name()[f"{layout[k]}{k}"].alias
                probe.wait_for(topic, lambda m: decode(m.payload).values(born).get(alias)
                               == changed, after=mark, timeout=30)
            check_no_repeats(probe, topic, born, mark)
            # a rebirth: the new DBIRTH holds what the device holds now
            mark = probe.mark()
            probe.publish(f"{base}/NCMD/n1", encode([encode_metric(
                name="Node Control/Rebirth", datatype="Boolean", value=True)]))
            again = decode(probe.wait_for(f"{base}/DBIRTH/n1/dev1", after=mark,
                                          timeout=30).payload)
            for m in again.metrics:
                assert m.timestamp is not None and m.timestamp >= since, m
                assert m.properties.get("errorReason") in (None, DEMAND_ONLY) or \
                    "not read yet" not in m.properties["errorReason"], m
            if polled:
                k = polled[-1]
                assert again.by_name()[f"{layout[k]}{k}"].value == changed
        finally:
            drv.stop_device()
            pub.stop()


@pytest.mark.usefixtures("engine")
def test_a_dtu_that_comes_back_is_born_with_the_values_of_its_new_connection(
        tmp_path: Path) -> None:
    """A dial-in DTU (20 one-register blocks behind it, 20 ms a reply) hangs up: DDEATH;
    its registers all change while it is away; it dials again: the DBIRTH carries the
    values read through the new connection, every one of them (none from before, none
    null), on both DTU engines."""
    from edgemodbus.datatypes import Area
    from edgemodbus.sim import Simulator
    from tests.engines import with_engine
    from tests.peers import free_port

    port = free_port()
    comm = with_engine({"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                        "listenPort": port, "dtuId": "D1", "registration": "text",
                        "registrationTimeout": 400, "slaveId": 1, "readTimeout": 500,
                        "readCycle": 100, "reconnectInterval": 300})
    cfg = em.load_device_config({
        "organization": {"deviceCode": "dev1"}, "communication": comm,
        "addressList": [{"name": f"r{i}", "address": f"hr:{SPACING * i}",
                         "deviceDataType": "UInt16"} for i in range(20)]})
    base = "spBv1.0/back"
    with Mosquitto(tmp_path / "mqtt") as broker, Simulator(slaves=[1], size=3000) as sim, \
            MqttProbe(broker.port, [f"{base}/#"]) as probe:
        sim.slave(1).set_faults(delay=0.02)
        pub = SparkplugPublisher({"mode": "sparkplug", "port": broker.port,
                                  "statusCheckInterval": 100,
                                  "sparkplug": {"groupId": "back"}}, gateway_id="n1")
        drv = em.DriverModbusRtu()
        pub.start()
        try:
            pub.attach(drv, "dev1")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            sim.dial("127.0.0.1", port, registration=b"D1\r\n")
            probe.wait_for(f"{base}/DBIRTH/n1/dev1", timeout=30)
            for visit in (1, 2):
                mark = probe.mark()
                sim.disconnect_clients()
                probe.wait_for(f"{base}/DDEATH/n1/dev1", timeout=30, after=mark)
                want = [1000 * visit + i for i in range(20)]
                for i, value in enumerate(want):
                    sim.slave(1).set_registers(Area.HOLDING_REGISTER, SPACING * i, [value])
                mark = probe.mark()
                sim.dial("127.0.0.1", port, registration=b"D1\r\n")
                born = decode(probe.wait_for(f"{base}/DBIRTH/n1/dev1", timeout=30,
                                             after=mark).payload)
                got = [born.by_name()[f"r{i}"] for i in range(20)]
                assert [m.value for m in got] == want, [m.value for m in got]
                assert all(m.timestamp and not m.is_null for m in got)
        finally:
            drv.stop_device()
            pub.stop()
