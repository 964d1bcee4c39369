"""Commands from a broker write a value only when the item can hold it as given
(``write_addresses_async(..., exact=True)``, poll/writes.py ``exact_problem``): the MQTT
per-item and batch commands and Sparkplug DCMD use it.  A property test against a real
pymodbus slave: for each item kind (engineering units over a UInt16 and an Int16, Float,
Int24, a coil, a register bit, a String), any value whose conversion to the item's raw
form is not exact is refused naming the item and why, and nothing is written; any exact
one is written and the slave holds what an independent encoding below says."""

from __future__ import annotations

import asyncio
import json
import struct
from collections.abc import Callable, Iterator
from decimal import Decimal
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import edgemodbus as em
from tests.mosquitto import Mosquitto, MqttProbe
from tests.peers import PymodbusSlave
from tests.sparkplug_wire import encode, encode_metric
from tests.waiting import wait_for

ITEMS: list[dict[str, Any]] = [
    {"name": "half", "address": "hr:0", "deviceDataType": "UInt16", "dataMultiplier": 0.5},
    {"name": "tenth", "address": "hr:1", "deviceDataType": "Int16", "dataMultiplier": 0.1},
    {"name": "f", "address": "hr:2", "deviceDataType": "Float32"},
    {"name": "i24", "address": "hr:4", "deviceDataType": "Int24"},
    {"name": "s", "address": "hr:6", "deviceDataType": "String", "quantity": 2},
    {"name": "coil", "address": "coil:0", "deviceDataType": "Boolean"},
    {"name": "bit", "address": "hr:8.3", "deviceDataType": "Boolean"},
]


def f32(x: float) -> float:
    return float(struct.unpack(">f", struct.pack(">f", x))[0])


def shortest_f32(x: float) -> float:
    """The shortest %g text that reads back to float32 ``x`` (written here apart from
    codec/float32.py, which searches decimals by another method)."""
    for digits in range(1, 10):
        text = f"{x:.{digits}g}"
        if f32(float(text)) == x:
            return float(text)
    return x


def _int_of(value: Any) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _scaled(value: Any, factor: int, lo: int, hi: int) -> list[int] | None:
    """Registers of ``value`` * ``factor`` (dataMultiplier 1/factor) when that is a whole
    number in lo..hi as the decimal the value is written as; else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    d = Decimal(repr(value)) if isinstance(value, float) else Decimal(value)
    if not d.is_finite():
        return None
    raw = d * factor
    if raw != raw.to_integral_value() or not lo <= int(raw) <= hi:
        return None
    return [int(raw) & 0xFFFF]


def expect_half(v: Any) -> list[int] | None:
    return _scaled(v, 2, 0, 0xFFFF)


def expect_tenth(v: Any) -> list[int] | None:
    return _scaled(v, 10, -0x8000, 0x7FFF)


def expect_f(v: Any) -> list[int] | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        held = f32(float(v))
    except OverflowError:
        return None
    if held != held or held in (float("inf"), float("-inf")):
        return None  # (not generated)
    if held != v and shortest_f32(held) != v:
        return None
    return list(struct.unpack(">2H", struct.pack(">f", held)))


def expect_i24(v: Any) -> list[int] | None:
    n = _int_of(v)
    if n is None or not -(1 << 23) <= n < (1 << 23):
        return None
    raw = n & 0xFFFFFF  # byte A written as 0 (docs/device-files.md "Int24 and UInt24")
    return [raw >> 16, raw & 0xFFFF]


def expect_s(v: Any) -> list[int] | None:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = str(v)  # a number for a String item is its text (MQTT's bare payload 42)
    if not isinstance(v, str) or len(v.encode()) > 4:
        return None
    data = v.encode().ljust(4, b"\0")
    return list(struct.unpack(">2H", data))


def expect_coil(v: Any) -> list[int] | None:
    if isinstance(v, bool):
        return [int(v)]
    return [int(v)] if _int_of(v) in (0, 1) else None


def from_text(name: str, value: Any) -> Any:
    """Text for a number or Boolean item is read as the value it writes (MQTT payloads
    are text; docs/gateway.md): JSON, and for a Boolean also true/false words; text
    that reads as nothing stays text (refused)."""
    if not isinstance(value, str) or name == "s":
        return value
    if name in ("coil", "bit") and value.strip().lower() in ("true", "on", "yes", "false", "off",
                                                    "no"):
        return value.strip().lower() in ("true", "on", "yes")
    try:
        return json.loads(value.strip())
    except ValueError:
        return value


EXPECT: dict[str, Callable[[Any], list[int] | None]] = {
    "half": expect_half, "tenth": expect_tenth, "f": expect_f, "i24": expect_i24,
    "s": expect_s, "coil": expect_coil, "bit": expect_coil,
}
ADDRESS = {"half": (0, 1), "tenth": (1, 1), "f": (2, 2), "i24": (4, 2), "s": (6, 2)}

numbers = st.one_of(
    st.integers(-70000, 70000),
    st.integers(-(1 << 24), 1 << 24),
    st.integers(-400, 400).map(lambda n: n / 2),
    st.integers(-40000, 40000).map(lambda n: n / 10),
    st.integers(-4000, 4000).map(lambda n: n / 100),
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False),
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=32),
    st.booleans(),
)
texts = st.text("abcXYZ09", max_size=6)


@pytest.fixture(scope="module")
def driver() -> Iterator[tuple[em.DriverModbusRtu, PymodbusSlave]]:
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=50) as slave:
        cfg = em.load_device_config({
            "organization": {"deviceCode": "exact"},
            "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                              "tcpPort": slave.port, "slaveId": 1, "readCycle": 1000,
                              "readTimeout": 1000, "reconnectInterval": 200},
            "addressList": ITEMS})
        drv = em.DriverModbusRtu()
        assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
        try:
            wait_for(lambda: drv.stats()["cycles"] >= 1, timeout=20, what="first cycle")
            yield drv, slave
        finally:
            drv.stop_device()


def held(slave: PymodbusSlave, name: str) -> list[int]:
    if name == "coil":
        return [int(b) for b in slave.bits(1, "co", 0, 1)]
    if name == "bit":
        return [slave.registers(1, "hr", 8)[0] >> 3 & 1]
    address, count = ADDRESS[name]
    return slave.registers(1, "hr", address, count)


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.sampled_from(sorted(EXPECT)), st.one_of(numbers, texts))
def test_a_command_writes_exactly_or_is_refused_saying_why(
        driver: tuple[em.DriverModbusRtu, PymodbusSlave], name: str, value: Any) -> None:
    drv, slave = driver
    before = held(slave, name)
    want = EXPECT[name](from_text(name, value))
    ok, error = asyncio.run(drv.write_addresses_async([(name, value)], exact=True))
    if want is None:
        assert not ok, (name, value, held(slave, name))
        assert error is not None and (error.startswith(f"{name}: ") or f"item {name!r}" in error)
        assert held(slave, name) == before  # nothing written
    else:
        assert ok, (name, value, error)
        assert held(slave, name) == want, (name, value)


def test_the_python_api_still_rounds_as_documented(
        driver: tuple[em.DriverModbusRtu, PymodbusSlave]) -> None:
    """Without ``exact`` (the Python API's writes) a value is rounded half to even, as
    docs/device-files.md says; the refusal is the command channels' rule."""
    drv, slave = driver
    assert drv.write_address("half", 12.3) == (True, None)
    assert held(slave, "half") == [25]  # 24.6 -> 25: 12.5
    ok, error = asyncio.run(drv.write_addresses_async([("half", 12.3)], exact=True))
    assert not ok and error == "half: cannot write 12.3 exactly: it would hold 12.5, not 12.3"


def _config(port: int, code: str) -> em.DeviceConfig:
    return em.load_device_config({
        "organization": {"deviceCode": code},
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": port, "slaveId": 1, "readCycle": 200,
                          "readTimeout": 1000, "reconnectInterval": 200},
        "addressList": ITEMS})


@pytest.mark.parametrize("mode", ["per-item", "batch"])
def test_mqtt_commands_write_only_exact_values(broker: Mosquitto, mode: str) -> None:
    """The brief's case over MQTT: 12.5 to a UInt16 with dataMultiplier 0.5 is 25 on the
    wire and written; 12.3 is not exact (24.6) and refused with the item and why; a batch
    with one inexact value writes nothing."""
    from edgemodbus.northbound.mqtt import MqttPublisher

    with PymodbusSlave("rtu-over-tcp", units=(1,), size=50) as slave, \
            MqttProbe(broker.port) as probe:
        pub = MqttPublisher({"port": broker.port, "mode": mode}, gateway_id="gw1")
        drv = em.DriverModbusRtu()
        cfg = _config(slave.port, "dev1")
        pub.start()
        try:
            pub.attach(drv, "dev1")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            # published after the command topics were subscribed (one connection)
            probe.wait_for("edgemodbus/dev1/$status", timeout=20)

            def command(topic: str, body: str, request: str) -> dict[str, Any]:
                mark = probe.mark()
                probe.publish(f"edgemodbus/dev1/{topic}", body)
                got: dict[str, Any] = probe.wait_for(
                    "edgemodbus/dev1/$reply", lambda m: m.json()["id"] == request,
                    after=mark).json()
                return got

            ok = command("set/half", '{"value": 12.5, "id": "a"}', "a")
            assert ok["ok"] is True, ok
            assert slave.registers(1, "hr", 0) == [25]
            bad = command("set/half", '{"value": 12.3, "id": "b"}', "b")
            assert bad["ok"] is False
            assert bad["error"] == "half: cannot write 12.3 exactly: it would hold 12.5, not 12.3"
            tenth = slave.registers(1, "hr", 1)
            bad = command("set", json.dumps({"items": {"tenth": 1.5, "half": 1.25},
                                             "id": "c"}), "c")
            assert bad["ok"] is False and "half: cannot write 1.25 exactly" in bad["error"]
            bad = command("set/f", '{"value": 0.1000000001, "id": "d"}', "d")
            assert bad["ok"] is False and "f: cannot write 0.1000000001 exactly" in bad["error"]
            assert command("set/f", '{"value": 0.1, "id": "e"}', "e")["ok"] is True
            assert slave.registers(1, "hr", 0, 2) == [25, *tenth]  # the batch wrote nothing
            assert slave.registers(1, "hr", 2, 2) == list(struct.unpack(">2H",
                                                                         struct.pack(">f", 0.1)))
        finally:
            drv.stop_device()
            pub.stop()


def test_sparkplug_dcmd_writes_only_exact_values(broker: Mosquitto) -> None:
    from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher

    base = "spBv1.0/g1"
    with PymodbusSlave("rtu-over-tcp", units=(1,), size=50) as slave, \
            MqttProbe(broker.port, [f"{base}/#"]) as probe:
        pub = SparkplugPublisher({"mode": "sparkplug", "port": broker.port,
                                  "sparkplug": {"groupId": "g1"}}, gateway_id="n1")
        drv = em.DriverModbusRtu()
        cfg = _config(slave.port, "dev1")
        pub.start()
        try:
            pub.attach(drv, "dev1")
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
            probe.wait_for(f"{base}/DBIRTH/n1/dev1", timeout=20)

            def dcmd(metric: bytes) -> None:
                probe.publish(f"{base}/DCMD/n1/dev1", encode([metric], 1))

            before = slave.registers(1, "hr", 0, 2)
            dcmd(encode_metric(name="half", datatype="Double", value=12.3))
            wait_for(lambda: pub.stats()["writesRefused"] == 1, what="12.3 refused")
            assert slave.registers(1, "hr", 0) == before[:1]
            dcmd(encode_metric(name="half", datatype="Double", value=12.5))
            wait_for(lambda: pub.stats()["writes"] == 1, what="12.5 written")
            assert slave.registers(1, "hr", 0) == [25]
            dcmd(encode_metric(name="tenth", datatype="Double", value=0.25))  # 2.5 raw
            wait_for(lambda: pub.stats()["writesRefused"] == 2, what="0.25 refused")
            assert slave.registers(1, "hr", 1) == before[1:]
        finally:
            drv.stop_device()
            pub.stop()
