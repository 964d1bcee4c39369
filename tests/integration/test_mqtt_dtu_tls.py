"""MQTT DTUs over TLS (transport mqtt-dtu with mqttTls, line/mqtt_dtu.py): mosquitto
with a TLS listener beside its plain one (certificates made by openssl in the test,
tests/fake_brokers.py), the simulated DTUs on the plain port, the gateway's hub on the
TLS port."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

import edgemodbus as em
from tests.coalescing_broker import CoalescingBroker, register
from tests.conftest import SlaveFactory
from tests.fake_brokers import self_signed_cert
from tests.integration.test_driver import Running
from tests.integration.test_mqtt_dtu import config, expected, hub_threads, values
from tests.mosquitto import Mosquitto
from tests.mqtt_dtu_peer import MqttDtu
from tests.peers import free_port
from tests.waiting import wait_for


@pytest.fixture
def tls_broker(tmp_path: Path) -> Iterator[tuple[Mosquitto, int, Path]]:
    """mosquitto with its plain listener and a TLS-only one: (broker, TLS port, CA)."""
    cert, key = self_signed_cert(tmp_path / "tls")
    tls_port = free_port()
    extra = [f"listener {tls_port} 127.0.0.1", f"certfile {cert}", f"keyfile {key}"]
    with Mosquitto(tmp_path / "broker", extra_config=extra) as peer:
        yield peer, tls_port, cert


def test_dtus_are_polled_over_tls_with_exact_values_and_no_timeouts(
        tls_broker: tuple[Mosquitto, int, Path], slave_factory: SlaveFactory) -> None:
    """Several DTUs on one TLS connection: their replies often arrive in one read, the
    later ones already decrypted inside the TLS layer, which select() does not see; each
    is handed on at once (else it waits for the next packet or a 1 s tick: timeouts)."""
    broker, tls_port, ca = tls_broker
    slave = slave_factory("rtu-over-tcp", units=(1, 2, 3))
    tls = {"mqttPort": tls_port, "mqttTls": True, "mqttCaFile": str(ca),
           "readTimeout": 700}
    with ExitStack() as stack:
        for dtu in ("t1", "t2", "t3"):
            stack.enter_context(MqttDtu(dtu, broker.port, slave.port))
        drivers = [stack.enter_context(Running(config(broker, f"t{unit}", unit, **tls)))
                   for unit in (1, 2, 3)]
        wait_for(lambda: all(values(d) == expected(u) for u, d in enumerate(drivers, 1)),
                 20, "the three DTUs' values over TLS")
        cycles = [d.stats()["cycles"] for d in drivers]
        wait_for(lambda: all(d.stats()["cycles"] >= c + 40
                             for c, d in zip(cycles, drivers, strict=True)),
                 60, "40 more cycles each")
        for unit, drv in enumerate(drivers, 1):
            assert values(drv) == expected(unit)
            line = drv.stats()["line"]
            assert line["timeouts"] == 0 and line["connects"] == 1, line
        ok, err = drivers[0].write_address("b", 777)
        assert ok, err
        wait_for(lambda: values(drivers[0])[1] == 777, 10, "the write read back")
    assert not hub_threads()


def test_a_wrong_ca_is_told_on_the_devices_status(
        tls_broker: tuple[Mosquitto, int, Path], slave_factory: SlaveFactory,
        tmp_path: Path) -> None:
    broker, tls_port, _ = tls_broker
    other_ca, _ = self_signed_cert(tmp_path / "other")
    slave = slave_factory("rtu-over-tcp", units=(1,))
    with MqttDtu("w1", broker.port, slave.port), Running(config(
            broker, "w1", 1, mqttPort=tls_port, mqttTls=True,
            mqttCaFile=str(other_ca))) as drv:
        want = (f"cannot connect to the broker mqtts://127.0.0.1:{tls_port}: TLS "
                "certificate check failed: ")
        wait_for(lambda: want in (drv.address_items[0].error_reason or ""), 20,
                 "the TLS failure on the items")
        reason = drv.address_items[0].error_reason or ""
        assert "self-signed certificate" in reason or "self signed" in reason, reason
        assert drv.device_driver_status is em.DeviceDriverStatus.RECONNECTING
        assert values(drv) == [None, None]
    # a TLS client on the plain port: the hint that the port may not speak TLS
    with Running(config(broker, "w1", 1, mqttTls=True)) as drv:
        wait_for(lambda: "mqttTls is on: does this port speak TLS?" in
                 (drv.address_items[0].error_reason or ""), 20, "the plain-port hint")
    assert not hub_threads()


def test_packets_that_share_a_tls_record_are_all_handed_on_at_once(
        tmp_path: Path) -> None:
    """A broker that writes two PUBLISH packets in one TLS record: select() sees the
    first, the second waits decrypted inside the TLS layer; the hub reads on while the
    TLS layer holds bytes, so each reply is whole within the read timeout."""
    cert, key = self_signed_cert(tmp_path / "tls")
    with CoalescingBroker(cert, key, "c1") as peer:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "c1"},
            "communication": {"transport": "mqtt-dtu", "mqttHost": "127.0.0.1",
                              "mqttPort": peer.port, "mqttTls": True,
                              "mqttCaFile": str(cert), "dtuId": "c1", "statusTopic": "",
                              "slaveId": 1, "readCycle": 50, "readTimeout": 500,
                              "retries": 0},
            "addressList": [{"name": "a", "address": "hr:3", "deviceDataType": "UInt16"},
                            {"name": "b", "address": "hr:4", "deviceDataType": "UInt16"}]})
        with Running(cfg) as drv:
            wait_for(lambda: drv.stats()["cycles"] >= 20, 30, "20 cycles")
            assert values(drv) == [register(3), register(4)]
            line = drv.stats()["line"]
            assert line["timeouts"] == 0, line
    assert not hub_threads()
