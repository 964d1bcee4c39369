"""Writes are the exact inverse of reads on every path (docs/device-files.md "Byte
order": "Writes are the exact inverse of reads"; docs/engineering-units.md "Writes"):
random values written through the driver (``write_address``), the MQTT write command
and the web console's write (POST /api/devices/{code}/write) to a pymodbus slave, whose registers
are then decoded by tests/value_reference.py (not our codec).  The items cover the byte
orders per device and per item (dataFormat, byteSwap16, dataFormat64), Int24, and the
engineering-unit keys (dataMultiplier with offset, a range map), whose raw value must be
the exact decimal inverse."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.codec import jsonable
from tests.console_gateway import Client, console_gateway
from tests.integration.test_mqtt import Gateway as MqttGateway
from tests.integration.test_mqtt import P
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.value_reference import SIZES, decode, raw_value, same
from tests.waiting import wait_for

COMM: dict[str, Any] = {"dataFormat": "CDAB", "byteSwap16": True,
                        "dataFormat64": "EFGHABCD"}  # the device's orders; items override
ITEMS: list[dict[str, Any]] = [
    {"name": "u16", "address": "hr:0", "deviceDataType": "UInt16"},
    {"name": "i16", "address": "hr:1", "deviceDataType": "Int16", "byteSwap16": False},
    {"name": "i32", "address": "hr:2", "deviceDataType": "Int32"},
    {"name": "f32", "address": "hr:4", "deviceDataType": "Float", "dataFormat": "BADC"},
    {"name": "i24", "address": "hr:6", "deviceDataType": "Int24", "dataFormat": "DCBA"},
    {"name": "i64", "address": "hr:8", "deviceDataType": "Int64"},
    {"name": "u64", "address": "hr:12", "deviceDataType": "UInt64",
     "dataFormat64": "FEHGBADC"},
    {"name": "dbl", "address": "hr:16", "deviceDataType": "Double",
     "dataFormat64": "CDABGHEF"},
    {"name": "temp", "address": "hr:20", "deviceDataType": "Int16", "dataMultiplier": 0.1,
     "offset": -40},
    {"name": "pct", "address": "hr:21", "deviceDataType": "UInt16", "rawMin": 0,
     "rawMax": 1000, "engMin": 0, "engMax": 100},
    {"name": "energy", "address": "hr:22", "deviceDataType": "Int32", "dataMultiplier": 0.01,
     "byteSwap16": False},
]
BY_NAME = {it["name"]: it for it in ITEMS}


def _registers(slave: PymodbusSlave, item: dict[str, Any]) -> list[int]:
    start = int(item["address"].split(":")[1])
    return slave.registers(1, "hr", start, SIZES[item["deviceDataType"]])


@st.composite
def writes(draw: st.DrawFn) -> tuple[str, Any, int | None]:
    """(item, value, the raw value the registers must hold for a scaled item or None);
    NaN and the infinities too (JSON paths send them as their strings)."""
    name = draw(st.sampled_from(sorted(BY_NAME)))
    if name in ("temp", "pct", "energy"):
        lo, hi, step, add = {"temp": (-32768, 32767, 10, -40), "pct": (0, 1000, 10, 0),
                             "energy": (-2**31, 2**31 - 1, 100, 0)}[name]
        raw = draw(st.integers(lo, hi))
        return name, float(Decimal(raw) / step + add), raw
    bounds = {"u16": (0, 0xFFFF), "i16": (-0x8000, 0x7FFF), "i32": (-2**31, 2**31 - 1),
              "i24": (-2**23, 2**23 - 1), "i64": (-2**63, 2**63 - 1), "u64": (0, 2**64 - 1)}
    if name in bounds:
        return name, draw(st.integers(*bounds[name])), None
    if name == "f32":
        return name, draw(st.floats(width=32)), None
    return name, draw(st.floats()), None


def check(slave: PymodbusSlave, name: str, value: Any, raw: int | None) -> None:
    item = BY_NAME[name]
    registers = _registers(slave, item)
    if raw is not None:  # the exact decimal inverse of the engineering units
        assert raw_value(registers, item, COMM) == (True, raw), (name, value, registers)
        return
    ok, back = decode(registers, item, COMM)
    assert ok, (name, value, registers)
    if isinstance(value, float) and math.isnan(value):
        assert isinstance(back, float) and math.isnan(back), (name, registers)
    else:
        assert same(back, value), (name, value, registers, back)


@pytest.fixture
def slave() -> Iterator[PymodbusSlave]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=100, fill="zero") as peer:
        yield peer


def _comm(slave: PymodbusSlave) -> dict[str, Any]:
    return {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "tcpPort": slave.port,
            "slaveId": 1, "readTimeout": 1000, "readCycle": 200, **COMM}


def test_a_driver_write_is_the_exact_inverse(slave: PymodbusSlave) -> None:
    cfg = em.load_device_config({"organization": {"deviceCode": "w"},
                                 "communication": _comm(slave), "addressList": ITEMS})
    drv = em.DriverModbusRtu()
    assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    try:
        @settings(max_examples=80, deadline=None)
        @given(write=writes())
        def through_driver(write: tuple[str, Any, int | None]) -> None:
            name, value, raw = write
            ok, error = drv.write_address(name, value)
            assert ok, (name, value, error)
            check(slave, name, value, raw)

        through_driver()
    finally:
        drv.stop_device()


def test_a_console_write_is_the_exact_inverse(tmp_path: Path, slave: PymodbusSlave) -> None:
    with console_gateway(tmp_path / "cfg", slave.port,
                         extra={"communication": _comm(slave), "addressList": ITEMS}) as gw:
        assert gw.console is not None
        client = Client(gw.console.port)
        client.session()  # its CSRF token
        wait_for(lambda: client.get("/api/devices/Dev1/tags")[1]["status"] == "Running",
                 what="the device running")

        @settings(max_examples=40, deadline=None)
        @given(write=writes())
        def through_console(write: tuple[str, Any, int | None]) -> None:
            name, value, raw = write
            status, out = client.post("/api/devices/Dev1/write", {"name": name,
                                                                   "value": jsonable(value)})
            assert status == 200 and out["ok"], (name, value, out)
            check(slave, name, value, raw)

        through_console()


def test_an_mqtt_write_is_the_exact_inverse(broker: Mosquitto, slave: PymodbusSlave) -> None:
    """The MQTT write command (``<prefix>/<device>/set/<item>``, a JSON value; NaN and
    the infinities as the strings the JSON outputs write, codec/jsonable.py)."""
    cfg = em.load_device_config({"organization": {"deviceCode": "dev1"},
                                 "communication": _comm(slave), "addressList": ITEMS})
    with MqttProbe(broker.port) as probe, MqttGateway(broker.port, cfg):
        probe.wait_for(f"{P}/dev1/u16")
        count = iter(range(10**9))

        @settings(max_examples=40, deadline=None)
        @given(write=writes())
        def through_mqtt(write: tuple[str, Any, int | None]) -> None:
            name, value, raw = write
            request = f"w{next(count)}"
            mark = probe.mark()
            probe.publish(f"{P}/dev1/set/{name}",
                          json.dumps({"value": jsonable(value), "id": request}))
            reply = probe.wait_for(f"{P}/dev1/$reply", lambda m: m.json()["id"] == request,
                                   after=mark).json()
            assert reply["ok"] is True, (name, value, reply)
            check(slave, name, value, raw)

        through_mqtt()
