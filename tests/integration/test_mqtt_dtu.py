"""DTUs on an MQTT broker (transport mqtt-dtu, line/mqtt_dtu.py, docs/links.md):
mosquitto as the broker, a simulated DTU in its own process (a paho client bridging its
topics to a pymodbus RTU-over-TCP slave: its RS-485 side), the driver polling through
them like a TCP DTU."""

from __future__ import annotations

import threading
from contextlib import ExitStack
from typing import Any

import edgemodbus as em
from edgemodbus.line import line_registry
from tests.conftest import SlaveFactory
from tests.integration.test_driver import Running
from tests.mosquitto import Mosquitto
from tests.mqtt_dtu_peer import MqttDtu
from tests.peers import default_register
from tests.waiting import wait_for


def config(broker: Mosquitto, dtu: str, slave: int, **extra: Any) -> em.DeviceConfig:
    comm: dict[str, Any] = {
        "transport": "mqtt-dtu", "mqttHost": "127.0.0.1", "mqttPort": broker.port,
        "dtuId": dtu, "slaveId": slave, "readCycle": 100, "readTimeout": 1000,
        "reconnectInterval": 200, "maxBackoff": 500, "retries": 0,
    }
    comm.update(extra)
    return em.load_device_config({
        "organization": {"deviceCode": f"{dtu}-{slave}"}, "communication": comm,
        "addressList": [{"name": "a", "address": "hr:3", "deviceDataType": "UInt16"},
                        {"name": "b", "address": "hr:4", "deviceDataType": "UInt16"}],
    })


def values(drv: em.DriverModbusRtu) -> list[Any]:
    return [i.value if i.status == "Ok" else None for i in drv.address_items]


def expected(slave: int) -> list[int]:
    return [default_register(slave, "hr", 3), default_register(slave, "hr", 4)]


def hub_threads() -> list[str]:
    return [t.name for t in threading.enumerate()
            if t.name.startswith("edgemodbus-mqtt-dtu") or t.name.startswith("paho")]


def test_two_devices_on_one_mqtt_dtu_are_polled_through_the_broker(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", units=(1, 2))
    with MqttDtu("d1", broker.port, slave.port), ExitStack() as stack:
        one = stack.enter_context(Running(config(broker, "d1", 1)))
        two = stack.enter_context(Running(config(broker, "d1", 2)))
        wait_for(lambda: values(one) == expected(1) and values(two) == expected(2), 15,
                 "both slaves' values through the broker")
        line = one.stats()["line"]
        assert line["connects"] == 1 and line["timeouts"] == 0
        lines = [w for w in line_registry.lines() if w.endpoint.key[0] == "mqtt-dtu"]
        assert len(lines) == 1  # one line (one link, one socketpair) for both devices
        ok, err = one.write_address("a", 4321)  # a write goes down and its echo comes up
        assert ok, err
        wait_for(lambda: values(one)[0] == 4321, 10, "the written value read back")
    assert not hub_threads()


def test_a_slow_dtu_is_waited_for_and_times_out_past_the_read_timeout(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", units=(1,))
    with MqttDtu("slow", broker.port, slave.port, delay=0.3):
        with Running(config(broker, "slow", 1, readTimeout=1500)) as drv:
            wait_for(lambda: values(drv) == expected(1), 15, "values from the slow DTU")
            assert drv.stats()["line"]["timeouts"] == 0
        with Running(config(broker, "slow", 1, readTimeout=100, readCycle=200)) as drv:
            wait_for(lambda: drv.stats()["line"]["timeouts"] >= 2, 15, "timeouts")
            # the late replies are settled away, never taken as the next one's answer
            assert values(drv) == [None, None]
            reason = drv.address_items[0].error_reason or ""
            assert "timed out" in reason or "timeout" in reason, reason


def test_a_dtu_that_drops_off_the_broker_is_reported_and_comes_back(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", units=(1,))
    dtu = MqttDtu("d7", broker.port, slave.port).start()
    try:
        with Running(config(broker, "d7", 1)) as drv:
            wait_for(lambda: values(drv) == expected(1), 15, "values")
            dtu.kill()  # no DISCONNECT: mosquitto publishes its will ("offline")
            # the link drops at once; the connects that follow say why
            wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RECONNECTING
                     and "the DTU is offline (its status topic 'dtu/d7/status' says "
                     "b'offline')" in (drv.address_items[0].error_reason or ""),
                     15, "the device reconnecting: the DTU is offline")
            dtu.start()  # its "online" status: the line connects at once
            wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RUNNING
                     and values(drv) == expected(1), 15, "values again")
            assert drv.stats()["line"]["reconnects"] >= 1
    finally:
        dtu.stop()


def test_the_broker_going_away_takes_the_dtus_down_until_it_returns(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    slave = slave_factory("rtu-over-tcp", units=(1,))
    with Running(config(broker, "d9", 1, statusTopic="")) as drv:
        with MqttDtu("d9", broker.port, slave.port):
            wait_for(lambda: values(drv) == expected(1), 15, "values")
        broker.restart()  # (the DTU is gone too: no status topic, so nothing tells us)
        wait_for(lambda: drv.device_driver_status is not em.DeviceDriverStatus.RUNNING,
                 15, "the device not running")
        with MqttDtu("d9", broker.port, slave.port):
            wait_for(lambda: drv.device_driver_status is em.DeviceDriverStatus.RUNNING,
                     30, "running again once the broker and the DTU are back")


def test_a_flood_on_the_uplink_topic_is_dropped_counted_and_polling_recovers(
        broker: Mosquitto, slave_factory: SlaveFactory) -> None:
    """The uplink topic is untrusted input: a 4 MB message (more than the link's stream
    holds) is cut to what fits, counted, logged once; the garbage is discarded by the
    stream framing and the device reads its values again."""
    from paho.mqtt import publish

    slave = slave_factory("rtu-over-tcp", units=(1,))
    with MqttDtu("d3", broker.port, slave.port), \
            Running(config(broker, "d3", 1, readTimeout=500)) as drv:
        wait_for(lambda: values(drv) == expected(1), 15, "values")
        publish.single("dtu/d3/up", b"\x01" * (4 << 20), hostname="127.0.0.1",
                       port=broker.port)
        wait_for(lambda: drv.stats()["line"]["uplinkDroppedBytes"] > 0, 15, "the drop")
        line = drv.stats()["line"]
        assert line["uplinkMessages"] >= 2
        cycles = drv.stats()["cycles"]
        wait_for(lambda: drv.stats()["cycles"] >= cycles + 3 and values(drv) == expected(1),
                 20, "polling again after the flood")
