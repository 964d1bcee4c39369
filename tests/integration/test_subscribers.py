"""A driver's subscribers are a list (driver.subscribe / unsubscribe): end to end with
libmodbus on our side and pymodbus (own process) as the slave, and the gateway's
subscribers (the MQTT publisher, the Modbus TCP server) side by side on one driver."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

import edgemodbus as em
from edgemodbus.datatypes import DeviceDriverStatus
from edgemodbus.gateway import Gateway, load_gateway_config
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.serve import ModbusTcpServer
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for


class Recorder(em.Listener[em.DriverModbusRtu]):
    """Records every batch and status it hears (line worker), under a lock."""

    def __init__(self, name: str, fail: bool = False) -> None:
        self.name = name
        self.fail = fail
        self.lock = threading.Lock()
        self.batches: list[list[em.DeviceAddressItem]] = []
        self.statuses: list[tuple[DeviceDriverStatus, str | None]] = []
        self.sources: set[int] = set()

    def on_changes(self, source: em.DriverModbusRtu,
                   items: list[em.DeviceAddressItem]) -> None:
        with self.lock:
            self.batches.append(items)
            self.sources.add(id(source))
        if self.fail:
            raise RuntimeError(f"{self.name}: listener bug")

    def on_status(self, source: em.DriverModbusRtu, status: DeviceDriverStatus,
                  reason: str | None) -> None:
        with self.lock:
            self.statuses.append((status, reason))

    def got(self) -> list[list[em.DeviceAddressItem]]:
        with self.lock:
            return list(self.batches)


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=200) as peer:
        yield peer


def config(peer: PymodbusSlave, **extra: Any) -> em.DeviceConfig:
    comm = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": peer.port,
            "slaveId": 1, "readTimeout": 300, "readCycle": 50, "reconnectInterval": 200,
            "retries": 0, "offlineAfterFailedCycles": 1}
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": "meter1"}, "communication": comm,
        "addressList": [{"name": f"r{a}", "address": f"hr:{a}", "deviceDataType": "UInt16"}
                        for a in range(4)],
    })


def start(cfg: em.DeviceConfig, drv: em.DriverModbusRtu | None = None) -> em.DriverModbusRtu:
    drv = drv or em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    return drv


def test_removing_b_keeps_a_and_c_on_every_batch(slave: PymodbusSlave) -> None:
    drv = em.DriverModbusRtu()
    head: list[list[em.DeviceAddressItem]] = []
    drv.addresses_updated_callback = head.append  # the seed's callback: the head
    a, b, c = Recorder("a"), Recorder("b"), Recorder("c")
    for listener in (a, b, c):
        drv.subscribe(listener)  # before start_device: heard from the first cycle on
    start(config(slave), drv)
    try:
        wait_for(lambda: len(c.got()) >= 1, what="the first batch")
        drv.unsubscribe(b)
        kept = len(b.got())
        for value in (11, 12, 13):
            slave.set_registers(1, "hr", 0, [value])
            wait_for(lambda v=value: any(i.name == "r0" and i.value == v  # type: ignore[misc]
                                         for batch in c.got() for i in batch),
                     what=f"r0 = {value} reported")
    finally:
        drv.stop_device()  # joins the line's worker: nothing is delivered after this
    assert a.batches == c.batches == head  # the very same batches, every one
    assert len(a.batches) >= 4
    # a delivery already under way when B left may still reach it: one at most
    assert b.batches == a.batches[:len(b.batches)] and kept <= len(b.batches) <= kept + 1
    assert a.sources == c.sources == {id(drv)}
    assert drv.stats()["callbackErrors"] == 0


def test_an_exception_in_one_listener_is_counted_the_others_still_run(
        slave: PymodbusSlave, caplog: pytest.LogCaptureFixture) -> None:
    drv = em.DriverModbusRtu()
    a, bad, c = Recorder("a"), Recorder("bad", fail=True), Recorder("c")
    for listener in (a, bad, c):
        drv.subscribe(listener)
    start(config(slave), drv)
    try:
        slave.set_registers(1, "hr", 1, [7])
        wait_for(lambda: len(c.got()) >= 2 or any(i.name == "r1" and i.value == 7
                                                  for batch in c.got() for i in batch),
                 what="batches after the failing listener")
    finally:
        drv.stop_device()
    assert a.batches == bad.batches == c.batches
    assert drv.stats()["callbackErrors"] == len(bad.batches) > 0
    assert "meter1: listener Recorder failed" in caplog.text


def test_status_changes_reach_the_listeners(slave: PymodbusSlave) -> None:
    drv = em.DriverModbusRtu()
    seen = Recorder("status")
    drv.subscribe(seen)
    start(config(slave), drv)
    try:
        wait_for(lambda: (DeviceDriverStatus.RUNNING, None) in seen.statuses,
                 what="Running")
        slave.set_offline(1)
        wait_for(lambda: any(s is DeviceDriverStatus.OFFLINE for s, _ in seen.statuses),
                 what="Offline")
        slave.set_offline(1, False)
        wait_for(lambda: seen.statuses[-1] == (DeviceDriverStatus.RUNNING, None),
                 what="Running again")
    finally:
        drv.stop_device()
    offline = [reason for s, reason in seen.statuses if s is DeviceDriverStatus.OFFLINE]
    assert offline and all(r == "offline after 1 failed cycles" for r in offline)
    # one call per change: never the same status twice in a row
    assert all(x[0] is not y[0] for x, y in zip(seen.statuses, seen.statuses[1:], strict=False))


def test_a_publisher_swap_keeps_the_servers_subscription(slave: PymodbusSlave) -> None:
    """The MQTT publisher subscribed first, the server's unit after it; detaching the
    publisher (as the gateway's publisher swap does) leaves the server's listener: the
    unit keeps following the slave, with no re-hook.  (With chained callbacks the
    publisher's detach restored what it had replaced and dropped the server's.)"""
    cfg = config(slave)
    drv = start(cfg)
    server = ModbusTcpServer("127.0.0.1", 0)
    old = MqttPublisher({"host": "127.0.0.1", "port": 1}, gateway_id="gw")
    new = MqttPublisher({"host": "127.0.0.1", "port": 1}, gateway_id="gw")
    client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
    try:
        old.attach(drv, "meter1")
        server.serve_device(1, drv, cfg)
        server.start()
        assert client.connect()

        def served(value: int) -> bool:
            rr = client.read_holding_registers(0, count=1, device_id=1)
            return getattr(rr, "registers", None) == [value]

        wait_for(lambda: served(default_register(1, "hr", 0)), what="r0 served")
        old.detach(drv)  # the swap: old out, new in
        new.attach(drv, "meter1")
        slave.set_registers(1, "hr", 0, [4321])
        wait_for(lambda: served(4321), what="a new value served after the swap")
        new.detach(drv)
        server.remove_unit(1)
        server.serve_device(1, drv, cfg)  # the server's own swap keeps nobody else's
        slave.set_registers(1, "hr", 0, [4322])
        wait_for(lambda: served(4322), what="a new value served after re-serving")
    finally:
        client.close()
        server.stop()
        old.stop()
        new.stop()
        drv.stop_device()
    with pytest.raises(ValueError, match="is not subscribed"):
        drv.unsubscribe(Recorder("never"))


def test_a_gateway_reload_that_swaps_the_publisher_keeps_the_units_served(
        tmp_path: Path, broker: Mosquitto, slave: PymodbusSlave) -> None:
    """A reload with new MQTT settings swaps the publisher (old detached, new attached);
    the server's unit, subscribed to the same driver, keeps following the slave, and the
    new publisher publishes: each is its own subscriber, with no re-hook."""
    device = {"organization": {"deviceCode": "meter1"},
              "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                                "tcpPort": slave.port, "slaveId": 1, "readCycle": 50,
                                "readTimeout": 500, "retries": 0},
              "addressList": [{"name": "t0", "address": "hr:0", "deviceDataType": "UInt16"}]}
    (tmp_path / "meter1.json").write_text(json.dumps(device))

    def gateway_json(prefix: str) -> None:
        (tmp_path / "gateway.json").write_text(json.dumps({
            "gatewayId": "gw",
            "mqtt": {"port": broker.port, "topicPrefix": prefix, "reconnectMin": 100,
                     "reconnectMax": 500},
            "serve": {"listen": "127.0.0.1:0", "units": [{"unitId": 1, "device": "meter1"}]},
        }))

    gateway_json("plant1")
    gateway = Gateway(tmp_path, load_gateway_config(tmp_path / "gateway.json"),
                      tmp_path / "gateway.json")
    client: ModbusTcpClient | None = None
    with MqttProbe(broker.port) as probe:
        gateway.start()
        try:
            server = gateway.serving.server
            assert server is not None
            client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
            assert client.connect()
            tcp = client

            def served(value: int) -> bool:
                rr = tcp.read_holding_registers(0, count=1, device_id=1)
                return getattr(rr, "registers", None) == [value]

            wait_for(lambda: served(default_register(1, "hr", 0)), what="t0 served")
            old = gateway.publisher
            gateway_json("plant2")
            gateway.reload()
            new = gateway.publisher
            assert new is not None and new is not old
            assert gateway.serving.server is server  # the server itself was kept
            slave.set_registers(1, "hr", 0, [4321])
            wait_for(lambda: served(4321), what="a new value served after the swap")
            topic = new.item_topic("meter1", "t0")
            assert topic.startswith("plant2/")
            probe.wait_for(topic, lambda m: b"4321" in m.payload)
        finally:
            if client is not None:
                client.close()
            gateway.stop()
