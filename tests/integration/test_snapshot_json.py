"""The driver's snapshot holds Python values (NaN, infinities, bytes, datetime: as the
items hold them, status Ok), and its JSON is strict by the one value conversion of
edgemodbus.codec (NaN and infinities as "NaN", "Infinity", "-Infinity", a Float as its
shortest float32 text, bytes hex, times ISO 8601), as in the CLI's JSON lines and the
MQTT payloads (per-item, batch and snapshot messages through a real mosquitto); a
pymodbus slave serves the registers."""

from __future__ import annotations

import json
import math
import struct
from datetime import datetime, timezone
from typing import Any, NoReturn

import pytest

import edgemodbus as em
from edgemodbus.codec import Float32, json_bytes
from edgemodbus.datatypes import ItemStatus
from tests.integration.test_mqtt import Gateway
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.waiting import wait_for

FLOATS = {100: math.nan, 102: math.inf, 104: -math.inf, 106: 1.5, 108: -0.0,
          110: 69.74495697021484}
BINARY = b"\x01\xab\xff\x00"
WHEN = datetime(2026, 1, 18, 12, 16, 58, tzinfo=timezone.utc)
NAMES = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


def _registers() -> dict[int, int]:
    regs: dict[int, int] = {}
    for address, value in FLOATS.items():
        hi, lo = struct.unpack(">HH", struct.pack(">f", value))
        regs[address], regs[address + 1] = hi, lo
    regs[200], regs[201] = struct.unpack(">HH", BINARY)
    regs[300], regs[301] = struct.unpack(">HH", struct.pack(">I", int(WHEN.timestamp())))
    regs[400] = 3
    return regs


def _strict(text: bytes) -> Any:
    def refuse(constant: str) -> NoReturn:
        raise AssertionError(f"{constant} is not strict JSON")

    return json.loads(text, parse_constant=refuse)


def _config(port: int, **comm: Any) -> em.DeviceConfig:
    items = [{"name": f"f{a}", "address": f"hr:{a}", "deviceDataType": "Float"} for a in FLOATS]
    items += [
        {"name": "bin", "address": "hr:200", "deviceDataType": "Binary", "quantity": 2},
        {"name": "when", "address": "hr:300", "deviceDataType": "DateTime", "quantity": 2},
        # a multiplier makes a double (raw / 10: 0.3), convertedDataType Float a float32
        {"name": "tenths", "address": "hr:400", "deviceDataType": "Int16",
         "dataMultiplier": 0.1},
        {"name": "tenths32", "address": "hr:400", "deviceDataType": "Int16",
         "dataMultiplier": 0.1, "convertedDataType": "Float"},
        {"name": "scaled", "address": "hr:110", "deviceDataType": "Float",
         "dataMultiplier": 0.1},
    ]
    return em.load_device_config({
        "organization": {"deviceCode": "snap"},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": 1, "readCycle": 200,
                          "readTimeout": 500, **comm},
        "addressList": items,
    })


def _peer() -> PymodbusSlave:
    return PymodbusSlave("rtu-over-tcp", units=(1,), initial={1: {"hr": _registers()}})


def _snapshot() -> tuple[dict[str, Any], em.DeviceConfig]:
    with _peer() as peer:
        cfg = _config(peer.port)
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: all(it.status is ItemStatus.OK for it in cfg.address_list),
                     what="every item Ok")
            snapshot = drv.snapshot()
        finally:
            drv.stop_device()
    return snapshot, cfg


def test_snapshot_holds_python_values_and_its_json_is_strict() -> None:
    snapshot, cfg = _snapshot()
    items = snapshot["items"]
    # the Python API: the values the items hold, NaN and infinities too, status Ok
    for address, value in FLOATS.items():
        got = items[f"f{address}"]["value"]
        assert isinstance(got, Float32) and items[f"f{address}"]["status"] == "Ok"
        assert got == value or (math.isnan(got) and math.isnan(value)), (address, got)
        assert math.copysign(1, got) == math.copysign(1, value)
    assert items["f110"]["value"] == 69.74495697021484  # exact: the widened float32
    assert items["bin"]["value"] == BINARY and items["when"]["value"] == WHEN
    assert items["tenths"]["value"] == 0.3 and type(items["tenths"]["value"]) is float
    by_name = {it.name: it.value for it in cfg.address_list}
    assert {k: v["value"] for k, v in items.items() if k.startswith("f1") and k != "f100"} \
        == {k: v for k, v in by_name.items() if k.startswith("f1") and k != "f100"}

    # its JSON: strict, NaN and infinities named (null would say "no value")
    values = {k: v["value"] for k, v in _strict(json_bytes(snapshot))["items"].items()}
    for address, value in FLOATS.items():
        got = values[f"f{address}"]
        if math.isfinite(value):  # the same float32, by its shortest text
            assert struct.pack(">f", got) == struct.pack(">f", value), (address, got)
            assert repr(got) == repr(Float32(value))
        else:
            assert isinstance(got, str) and got in NAMES, (address, got)
            named = NAMES[got]
            assert named == value or (math.isnan(named) and math.isnan(value))
    text = json_bytes(snapshot).decode()
    assert '"f110":{"address":"hr:110","value":69.74496,' in text  # float32, not 69.7449569..
    assert values["tenths"] == 0.3 and values["tenths32"] == 0.3
    assert values["scaled"] == 6.974495697021484  # a double: float32 x 0.1, not rounded
    assert values["bin"] == BINARY.hex()
    assert values["when"] == WHEN.isoformat()
    for entry in _strict(json_bytes(snapshot))["items"].values():
        assert entry["status"] == "Ok"
        assert datetime.fromisoformat(entry["updateTs"]).tzinfo is not None


def _check_values(values: dict[str, Any]) -> None:
    """The JSON values of the device's items, as every payload carries them."""
    for address, value in FLOATS.items():
        got = values[f"f{address}"]
        if math.isfinite(value):
            assert struct.pack(">f", got) == struct.pack(">f", value), (address, got)
        else:
            assert got == {math.inf: "Infinity", -math.inf: "-Infinity"}.get(value, "NaN")
    assert values["f110"] == 69.74496 and values["tenths32"] == 0.3
    assert values["scaled"] == 6.974495697021484 and values["bin"] == BINARY.hex()


@pytest.mark.parametrize("mode", ["per-item", "batch"])
def test_mqtt_payloads_write_values_the_same_way(broker: Mosquitto, mode: str) -> None:
    """Per-item, batch and snapshot messages: strict JSON, a Float as its float32 text
    (69.74496 in the payload's bytes), NaN and infinities by name."""
    with _peer() as peer, MqttProbe(broker.port) as probe:
        cfg = _config(peer.port, snapshotInterval=200)
        with Gateway(broker.port, cfg, mode=mode):
            snap = probe.wait_for("/real/snap", lambda m: all(
                e["status"] == "Ok" for e in m.json()["items"].values()))
            if mode == "batch":
                batch = probe.wait_for("edgemodbus/snap/$batch")
                assert b'"f110":69.74496,' in batch.payload
                values = _strict(batch.payload)["values"]
            else:
                values = {}
                for it in cfg.address_list:
                    msg = probe.wait_for(f"edgemodbus/snap/{it.name}")
                    values[it.name] = _strict(msg.payload)["value"]
                    assert _strict(msg.payload)["status"] == "Ok"
                assert probe.on("edgemodbus/snap/f110")[0].payload.startswith(
                    b'{"value":69.74496,')
    _check_values(values)
    _check_values({k: v["value"] for k, v in _strict(snap.payload)["items"].items()})
