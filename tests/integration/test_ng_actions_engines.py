"""Issue 24, "NG Gateway parity" on today's engines: an NG action (functionCode 05/0F/06/10,
address, quantity, the value given at run time; seed ng-gateway-modbus-driver.zh.md 2.4)
runs on a DTU that dials in, on the thread and on the loop engine, from Python and as an
MQTT ``$action`` command, and writes what it was given (read back by the simulator)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.sim import Simulator
from tests.engines import with_engine
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import free_port
from tests.waiting import wait_for

NG_ACTIONS: list[dict[str, Any]] = [
    {"name": "coil", "functionCode": "0x05", "address": 20, "quantity": 1},
    {"name": "coils", "functionCode": "WriteMultipleCoils", "address": 30, "quantity": 3},
    {"name": "reg", "functionCode": 6, "address": 300, "quantity": 1},
    {"name": "regs", "functionCode": "0x10", "address": 310, "quantity": 3},
]


def _dtu_device(port: int) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": "ngdtu"},
        "communication": with_engine({
            "transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": port, "dtuId": "NG-DTU-1", "registration": "text",
            "registrationTimeout": 2000, "slaveId": 1, "readTimeout": 500,
            "readCycle": 100, "reconnectInterval": 300}),
        "addressList": [{"name": "Mode", "address": "hr:7", "deviceDataType": "UInt16"}],
        "actions": NG_ACTIONS,
    })


@pytest.mark.usefixtures("engine")
def test_ng_actions_run_on_a_dtu_from_python_and_mqtt(tmp_path: Path) -> None:
    port = free_port()
    cfg = _dtu_device(port)
    with Simulator([1], 0x400) as sim, Mosquitto(tmp_path / "broker") as broker, \
            MqttProbe(broker.port) as probe:
        pub = MqttPublisher({"port": broker.port, "reconnectMin": 100, "reconnectMax": 400},
                            gateway_id="gw1")
        drv = em.DriverModbusRtu()
        pub.start()
        try:
            pub.attach(drv, "ngdtu")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list,
                                    cfg.actions)
            sim.dial("127.0.0.1", port, registration=b"NG-DTU-1")
            wait_for(lambda: cfg.address_list[0].status is em.ItemStatus.OK, timeout=30,
                     what="the DTU registered and polled")
            assert drv.run_action("reg", {"value": 1234}) == (True, None)
            assert drv.run_action("coils", {"value": [True, False, True]}) == (True, None)
            hr, co = em.Area.HOLDING_REGISTER, em.Area.COIL
            assert sim.slave(1).get_registers(hr, 300, 1) == [1234]
            assert sim.slave(1).get_bits(co, 30, 3) == [True, False, True]
            probe.wait_for("edgemodbus/ngdtu/Mode")
            for request, name, value in (("m1", "regs", "7, -1, 0x10"), ("m2", "coil", True)):
                mark = probe.mark()
                probe.publish("edgemodbus/ngdtu/$action", json.dumps(
                    {"action": name, "parameters": {"value": value}, "id": request}))
                reply = probe.wait_for("edgemodbus/ngdtu/$reply",
                                       lambda m, r=request: m.json()["id"] == r, after=mark)
                assert reply.json()["ok"] is True, reply.json()
            assert sim.slave(1).get_registers(hr, 310, 3) == [7, 0xFFFF, 16]
            assert sim.slave(1).get_bits(co, 20, 1) == [True]
        finally:
            drv.stop_device()
            pub.stop()
