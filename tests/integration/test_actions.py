"""Actions (NG's Action) end to end: run from Python, the CLI and MQTT against pymodbus
(own process) and our simulator; confirmed or failed as a whole, checked before sending."""

from __future__ import annotations

import asyncio
import json
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.cli import main
from edgemodbus.northbound.mqtt import MqttPublisher
from edgemodbus.sim import Simulator
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import ExceptionRange, PymodbusSlave

ITEMS: list[dict[str, Any]] = [
    {"name": "PumpSpeed", "address": "hr:100", "deviceDataType": "Float"},
    {"name": "Mode", "address": "hr:102", "deviceDataType": "UInt16"},
    {"name": "Setpoint", "address": "hr:103", "deviceDataType": "Int16", "dataMultiplier": 0.1},
    {"name": "Total", "address": "hr:110", "deviceDataType": "Int24", "dataFormat": "CDAB"},
    {"name": "Far", "address": "hr:200", "deviceDataType": "UInt16"},
    {"name": "Farther", "address": "hr:250", "deviceDataType": "UInt16"},
    {"name": "Run", "address": "coil:5", "deviceDataType": "Boolean"},
    {"name": "Lamp", "address": "coil:6", "deviceDataType": "Boolean"},
]

ACTIONS: list[dict[str, Any]] = [
    {"name": "start", "functionCode": 16, "parameters": [
        {"name": "speed", "item": "PumpSpeed", "type": "Float32", "minValue": 0,
         "maxValue": 100},
        {"name": "mode", "item": "Mode", "type": "UInt16", "default": 1},
        {"name": "setpoint", "item": "Setpoint", "default": 21.5},
    ]},
    {"name": "total", "functionCode": "WriteMultipleRegisters",  # NG's spelling
     "inputParameters": [{"key": "value", "item": "Total", "dataType": "Int24"}]},
    {"name": "single", "functionCode": 6, "parameters": [
        {"name": "speed", "item": "PumpSpeed"}, {"name": "mode", "item": "Mode"}]},
    {"name": "coils", "functionCode": 15, "parameters": [
        {"name": "run", "item": "Run", "type": "Boolean"},
        {"name": "lamp", "item": "Lamp", "default": True}]},
    {"name": "one_coil", "functionCode": 5, "parameters": [
        {"name": "run", "item": "Run", "type": "Boolean"}]},
    {"name": "spread", "functionCode": 16, "parameters": [
        {"name": "a", "item": "Mode"}, {"name": "b", "item": "Far"},
        {"name": "c", "item": "Farther"}]},
]


def device(port: int, **extra: Any) -> em.DeviceConfig:
    comm = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
            "slaveId": 1, "readTimeout": 500, "readCycle": 200, "reconnectInterval": 300,
            "byteTimeout": 50}
    comm.update(extra)
    return em.load_device_config({"organization": {"deviceCode": "pump"},
                                  "communication": comm, "addressList": ITEMS,
                                  "actions": ACTIONS})


class Running:
    def __init__(self, cfg: em.DeviceConfig) -> None:
        self.cfg = cfg
        self.drv = em.DriverModbusRtu()

    def __enter__(self) -> em.DriverModbusRtu:
        assert self.drv.start_device(self.cfg.organization, self.cfg.communication,
                                     self.cfg.address_list, self.cfg.actions)
        return self.drv

    def __exit__(self, *exc: object) -> None:
        self.drv.stop_device()


def f32(value: float) -> list[int]:
    return list(struct.unpack(">2H", struct.pack(">f", value)))


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    ranges = [ExceptionRange(200, 201, code=4, area="hr")]  # slave device failure
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=400, fill="zero",
                       exception_ranges=ranges) as peer:
        yield peer


def test_actions_write_every_register_in_their_function_code(slave: PymodbusSlave) -> None:
    cfg = device(slave.port)
    with Running(cfg) as drv:
        writes = drv.stats()["writes"]
        assert drv.run_action("start", {"speed": 42.5}) == (True, None)
        # one FC16 for the three neighbouring items; defaults filled in
        assert slave.registers(1, "hr", 100, 4) == [*f32(42.5), 1, 215]
        assert drv.stats()["writes"] == writes + 1
        values = {it.name: it.value for it in cfg.address_list}
        assert (values["PumpSpeed"], values["Mode"], values["Setpoint"]) == (42.5, 1, 21.5)

        # Int24 in CDAB: register 0 = B C... bytes C D, register 1 = A B with A unused
        assert drv.run_action("total", {"value": -2}) == (True, None)
        assert slave.registers(1, "hr", 110, 2) == [0xFFFE, 0x00FF]
        assert drv.run_action("total", {"value": "8388607"}) == (True, None)
        assert slave.registers(1, "hr", 110, 2) == [0xFFFF, 0x007F]

        assert drv.run_action("single", {"speed": 7, "mode": 9}) == (True, None)
        assert slave.registers(1, "hr", 100, 3) == [*f32(7.0), 9]

        assert drv.run_action("coils", {"run": True}) == (True, None)
        assert slave.bits(1, "co", 5, 2) == [True, True]
        assert drv.run_action("one_coil", {"run": "false"}) == (True, None)
        assert slave.bits(1, "co", 5, 2) == [False, True]

        async def go() -> tuple[bool, str | None]:
            return await drv.run_action_async("start", {"speed": 1, "mode": 2})

        assert asyncio.run(go()) == (True, None)
        assert slave.registers(1, "hr", 100, 3) == [*f32(1.0), 2]


@pytest.mark.parametrize(("name", "params", "expected"), [
    ("start", {}, "action 'start': parameter 'speed' is missing (speed -> PumpSpeed "
                  "(Float, 0..100, required))"),
    ("start", {"speed": "fast"}, "action 'start': parameter 'speed': 'fast' is not a Float "
                                 "value (use a number)"),
    ("start", {"speed": 101}, "action 'start': parameter 'speed': 101 is out of range (0..100)"),
    ("start", {"speed": 5, "mode": 1.5}, "action 'start': parameter 'mode': 1.5 is not allowed: "
                                         "UInt16 takes a whole number"),
    ("start", {"speed": 5, "mode": 70000}, "action 'start': parameter 'mode': 70000 is not "
                                           "allowed: UInt16 takes 0..65535"),
    ("start", {"speed": 5, "sped": 1}, "action 'start': unknown parameter 'sped' (parameters: "
                                       "speed -> PumpSpeed"),
    ("total", {"value": 8388608}, "action 'total': parameter 'value': 8388608 is not allowed: "
                                  "Int24 takes -8388608..8388607"),
    ("coils", {"run": "maybe"}, "action 'coils': parameter 'run': 'maybe' is not a Boolean"),
    ("stop", {}, "unknown action 'stop' (actions: 'start', 'total', 'single', 'coils', "
                 "'one_coil', 'spread')"),
])
def test_bad_parameters_are_refused_before_anything_is_sent(
    slave: PymodbusSlave, name: str, params: dict[str, Any], expected: str
) -> None:
    cfg = device(slave.port)
    with Running(cfg) as drv:
        writes = drv.stats()["writes"]
        ok, err = drv.run_action(name, params)
        assert not ok and err is not None and err.startswith(expected), err
        assert drv.stats()["writes"] == writes


def test_an_exception_from_the_slave_fails_the_action_as_a_whole(slave: PymodbusSlave) -> None:
    cfg = device(slave.port)
    with Running(cfg) as drv:
        ok, err = drv.run_action("spread", {"a": 11, "b": 12, "c": 13})
        assert not ok
        assert err is not None and err.startswith("action 'spread': Far: ")
        assert "exception 4" in err or "device failure" in err.lower(), err
        assert "Farther: not sent" in err and "written before the failure: Mode" in err
        assert slave.registers(1, "hr", 102) == [11]  # the first request was confirmed
        assert slave.registers(1, "hr", 250) == [0]  # the one after the failure never went
        assert drv.stats()["writeErrors"] >= 1


def test_fc16_refused_fails_the_action_without_falling_back() -> None:
    with Simulator([1]) as sim:
        sim.slave(1).faults.refused_functions = frozenset({16})
        cfg = device(sim.serve_tcp("127.0.0.1", 0))
        with Running(cfg) as drv:
            ok, err = drv.run_action("start", {"speed": 3})
            assert not ok and err is not None and err.startswith(
                "action 'start': PumpSpeed, Mode, Setpoint: "), err
            regs = sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 100, 3)
            assert regs != [*f32(3.0), 1]
            # FC06 is not refused: the same values land through the FC06 action
            assert drv.run_action("single", {"speed": 3, "mode": 4}) == (True, None)
            assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 100, 3) == [
                *f32(3.0), 4]


def test_cli_action_runs_and_lists(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with Simulator([1]) as sim:
        port = sim.serve_tcp("127.0.0.1", 0)
        path = tmp_path / "pump.json"
        path.write_text(json.dumps({
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": port, "readTimeout": 500},
            "addressList": ITEMS, "actions": ACTIONS}))
        assert main(["action", str(path), "start", "speed=12.5", "mode=3"]) == 0
        assert capsys.readouterr().out == "ok\n"
        assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 100, 4) == [
            *f32(12.5), 3, 215]
        assert main(["action", str(path), "start", "speed=oops"]) == 2
        err = capsys.readouterr().err
        assert "edgemodbus action: action 'start': parameter 'speed': 'oops' is not a Float" in err
        assert main(["action", str(path), "start", "speed"]) == 2
        assert "give parameters as name=value" in capsys.readouterr().err
    assert main(["action", str(path)]) == 0
    listing = capsys.readouterr().out
    assert "start: functionCode 16\n  speed -> PumpSpeed (Float, 0..100, required)" in listing
    assert "  mode -> Mode (UInt16, default 1)" in listing


def test_actions_from_mqtt(tmp_path: Path, slave: PymodbusSlave) -> None:
    cfg = device(slave.port, readCycle=100)
    with Mosquitto(tmp_path / "broker") as broker, MqttProbe(broker.port) as probe:
        pub = MqttPublisher({"port": broker.port, "reconnectMin": 100, "reconnectMax": 400},
                            gateway_id="gw1")
        drv = em.DriverModbusRtu()
        pub.start()
        try:
            pub.attach(drv, "pump")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list,
                                    cfg.actions)
            probe.wait_for("edgemodbus/pump/Mode")
            reply = "edgemodbus/pump/$reply"

            def command(payload: str, request: Any) -> dict[str, Any]:
                mark = probe.mark()
                probe.publish("edgemodbus/pump/$action", payload)
                msg = probe.wait_for(reply, lambda m: m.json()["id"] == request, after=mark)
                body: dict[str, Any] = msg.json()
                return body

            ok = command(json.dumps({"action": "start", "parameters": {"speed": 50},
                                     "id": "a1"}), "a1")
            assert ok["ok"] is True and ok["error"] is None and ok["action"] == "start"
            assert slave.registers(1, "hr", 100, 4) == [*f32(50.0), 1, 215]
            bad = command(json.dumps({"action": "start", "parameters": {"speed": -1},
                                      "id": "b1"}), "b1")
            assert bad["ok"] is False
            assert bad["error"] == "action 'start': parameter 'speed': -1 is out of range (0..100)"
            failed = command(json.dumps({"action": "spread", "parameters": {"a": 1, "b": 2,
                                                                            "c": 3}, "id": 3}), 3)
            assert failed["ok"] is False and "Farther: not sent" in failed["error"]
            wrong = command('{"parameters": {}}', None)
            assert wrong["ok"] is False and '"action"' in wrong["error"]
        finally:
            drv.stop_device()
            pub.stop()


# -- NG's form: functionCode, address, quantity; the value at run time (#24) ----------------

NG_ACTIONS: list[dict[str, Any]] = [
    # as NG writes them (seed ng-gateway-modbus-driver.zh.md, 2.4): no parameters
    {"name": "coil", "functionCode": "0x05", "address": 20, "quantity": 1},
    {"name": "coils", "functionCode": "WriteMultipleCoils", "address": 30, "quantity": 3},
    {"name": "reg", "functionCode": 6, "address": 300, "quantity": 1},
    {"name": "regs", "functionCode": "0x10", "address": 310, "quantity": 3},
    {"name": "two_singles", "functionCode": 6, "address": 320, "quantity": 2},
]


def ng_device(port: int) -> em.DeviceConfig:
    return em.load_device_config({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": 1, "readTimeout": 500},
        "addressList": ITEMS, "actions": NG_ACTIONS})


def test_ng_actions_load_and_write_the_value_given_when_they_run(slave: PymodbusSlave) -> None:
    """They were refused: "an action needs at least one parameter", address refused."""
    cfg = ng_device(slave.port)
    assert [(a.function_code, a.address, a.count) for a in cfg.actions] == [
        (5, 20, 1), (15, 30, 3), (6, 300, 1), (16, 310, 3), (6, 320, 2)]
    with Running(cfg) as drv:
        writes = drv.stats()["writes"]
        assert drv.run_action("coil", {"value": True}) == (True, None)
        assert slave.bits(1, "co", 20, 1) == [True]
        assert drv.run_action("coils", {"value": [True, False, True]}) == (True, None)
        assert slave.bits(1, "co", 30, 3) == [True, False, True]
        assert drv.run_action("reg", {"value": 1234}) == (True, None)
        assert slave.registers(1, "hr", 300, 1) == [1234]
        assert drv.run_action("regs", {"value": "7, -1, 0x10"}) == (True, None)
        assert slave.registers(1, "hr", 310, 3) == [7, 0xFFFF, 16]
        assert drv.run_action("two_singles", {"value": [5, 6]}) == (True, None)
        assert slave.registers(1, "hr", 320, 2) == [5, 6]
        # one request per action, but FC06 with quantity 2 is one request per register
        # in the same op: every action counts as one write
        assert drv.stats()["writes"] == writes + 5


@pytest.mark.parametrize(("name", "params", "expected"), [
    ("reg", {}, "action 'reg': parameter 'value' is missing (it writes 1 register "
                "(0..65535 or -32768..-1) at hr:300: give value=...)"),
    ("reg", {"v": 1}, "action 'reg': unknown parameter 'v' (it writes 1 register"),
    ("reg", {"value": 70000}, "action 'reg': parameter 'value' 70000: 70000 is not a "
                              "register value"),
    ("regs", {"value": [1, 2]}, "action 'regs': parameter 'value' [1, 2]: 2 values, but it "
                                "writes 3 registers"),
    ("coils", {"value": "1,0,maybe"}, "action 'coils': parameter 'value' '1,0,maybe': "
                                      "'maybe' is not a coil value"),
])
def test_ng_action_values_are_checked_before_anything_is_sent(
        slave: PymodbusSlave, name: str, params: dict[str, Any], expected: str) -> None:
    cfg = ng_device(slave.port)
    with Running(cfg) as drv:
        writes = drv.stats()["writes"]
        ok, err = drv.run_action(name, params)
        assert not ok and err is not None and err.startswith(expected), err
        assert drv.stats()["writes"] == writes


@pytest.mark.parametrize(("action", "expected"), [
    ({"name": "a", "functionCode": 6, "address": 1, "parameters": [
        {"name": "p", "item": "Mode"}]}, "give address"),
    ({"name": "a", "functionCode": 16, "address": 0, "quantity": 124},
     "quantity 124: functionCode 16 writes at most 123 registers"),
    ({"name": "a", "functionCode": 15, "address": 65535, "quantity": 2},
     "address 65535 + quantity 2 runs past 65535"),
    ({"name": "a", "functionCode": 16, "quantity": 2}, "quantity goes with address"),
    ({"name": "a", "functionCode": 3, "address": 0}, "use 5 (WriteSingleCoil)"),
])
def test_bad_ng_actions_are_config_errors(action: dict[str, Any], expected: str) -> None:
    with pytest.raises(em.ConfigError, match=r"^actions\[0\]") as info:
        em.load_device_config({"addressList": ITEMS, "actions": [action]})
    assert expected in str(info.value), str(info.value)


def test_cli_runs_an_ng_action(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with Simulator([1]) as sim:
        path = tmp_path / "ng.json"
        path.write_text(json.dumps({
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": sim.serve_tcp("127.0.0.1", 0), "readTimeout": 500},
            "addressList": ITEMS, "actions": NG_ACTIONS}))
        assert main(["action", str(path), "regs", "value=1,2,3"]) == 0
        assert capsys.readouterr().out == "ok\n"
        assert sim.slave(1).get_registers(em.Area.HOLDING_REGISTER, 310, 3) == [1, 2, 3]


def test_a_reload_that_changes_only_the_actions_applies_them(
        tmp_path: Path, slave: PymodbusSlave) -> None:
    """A device file whose only change is its actions is updated in place (no restart),
    and the new actions run (they were ignored until the device restarted)."""
    from edgemodbus.gateway import Gateway, load_gateway_config

    conf = tmp_path / "conf"
    conf.mkdir()
    (conf / "gateway.json").write_text(json.dumps({"gatewayId": "gw-actions"}))
    comm = {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readTimeout": 500, "readCycle": 200, "byteTimeout": 50}
    body: dict[str, Any] = {"organization": {"deviceCode": "pump"}, "communication": comm,
                            "addressList": ITEMS, "actions": ACTIONS[:1]}
    (conf / "pump.json").write_text(json.dumps(body))
    gateway = Gateway(conf, load_gateway_config(conf / "gateway.json"), conf / "gateway.json")
    gateway.start()
    try:
        (dev,) = gateway.devices.values()
        driver = dev.driver
        assert [a.name for a in driver.actions] == ["start"]
        body["actions"] = [*ACTIONS[:1], {"name": "mode7", "functionCode": 6, "parameters": [
            {"name": "mode", "item": "Mode", "default": 7}]}]
        (conf / "pump.json").write_text(json.dumps(body))
        gateway.reload_devices()
        assert next(iter(gateway.devices.values())).driver is driver  # not restarted
        assert [a.name for a in driver.actions] == ["start", "mode7"]
        assert driver.run_action("mode7") == (True, None)
        assert slave.registers(1, "hr", 102) == [7]
    finally:
        gateway.stop()
