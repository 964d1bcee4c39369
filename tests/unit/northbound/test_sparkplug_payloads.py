"""Our Sparkplug encoder read back by the independent wire-format reader of the tests."""

from __future__ import annotations

from datetime import datetime, timezone

import pytest

from edgemodbus.datatypes import DataType, ItemStatus
from edgemodbus.northbound.sparkplug.commands import command_value, parse_command
from edgemodbus.northbound.sparkplug.payloads import (
    MetricDef,
    Sample,
    device_birth,
    device_data,
    sparkplug_type,
)
from tests.sparkplug_wire import TYPES, decode, encode, encode_metric

CASES = [
    (DataType.SBYTE, -3), (DataType.BYTE, 250), (DataType.INT16, -32768),
    (DataType.UINT16, 65535), (DataType.INT24, -8_000_000), (DataType.UINT32, 4_000_000_000),
    (DataType.INT64, -(1 << 62)), (DataType.UINT64, (1 << 64) - 1), (DataType.FLOAT, 0.5),
    (DataType.DOUBLE, -1e300), (DataType.BOOLEAN, True), (DataType.STRING, "naïve"),
    (DataType.CHAR, "x"), (DataType.BINARY, b"\x00\xff"), (DataType.BCD32, 99_999_999),
    (DataType.TIMESTAMP, 1_700_000_000_123),
    (DataType.DATETIME, datetime(2026, 1, 2, 3, 4, 5, 678000, tzinfo=timezone.utc)),
]


@pytest.mark.parametrize(("ours", "value"), CASES, ids=[c[0].value for c in CASES])
def test_each_type_is_read_back_by_an_independent_reader(ours: DataType, value: object) -> None:
    kind = sparkplug_type(ours, None, 1.0)
    spec = MetricDef("m", 7, kind)
    payload = decode(device_birth(5, 1000, [(Sample("m", value, ItemStatus.OK, 999, None),
                                             spec)]))
    assert payload.seq == 5 and payload.timestamp == 1000
    (metric,) = payload.metrics
    assert (metric.name, metric.alias, metric.datatype, metric.timestamp) == ("m", 7, kind, 999)
    expected = (int(value.timestamp() * 1000) if isinstance(value, datetime) else value)
    assert metric.value == pytest.approx(expected) if isinstance(value, float) else (
        metric.value == expected)
    assert metric.properties == {"Quality": 192} and not metric.is_null


def test_a_value_that_does_not_fit_is_null_with_bad_quality() -> None:
    spec = MetricDef("m", 1, TYPES["UInt16"])
    (metric,) = decode(device_birth(0, 0, [(Sample("m", 70000, ItemStatus.OK, None, None),
                                            spec)])).metrics
    assert metric.is_null and metric.raw is None and metric.properties["Quality"] == 0
    assert "70000" in metric.properties["errorReason"]


def test_multiplier_makes_a_double_unless_converted() -> None:
    assert sparkplug_type(DataType.INT16, None, 0.1) == TYPES["Double"]
    assert sparkplug_type(DataType.INT16, DataType.FLOAT, 0.1) == TYPES["Float"]
    assert sparkplug_type(DataType.BOOLEAN, None, 2.0) == TYPES["Boolean"]


def test_commands_written_by_the_independent_writer_are_read() -> None:
    (neg, big, text) = parse_command(encode([
        encode_metric(name="a", datatype="Int16", value=-2),
        encode_metric(alias=9, datatype="Int64", value=-(1 << 40)),
        encode_metric(name="s", datatype="String", value="hi")]))
    assert neg.name == "a" and command_value(neg, TYPES["Int16"]) == -2
    assert big.alias == 9 and command_value(big, TYPES["Int64"]) == -(1 << 40)
    assert command_value(text, TYPES["String"]) == "hi"
    with pytest.raises(ValueError, match="not a Sparkplug B payload"):
        parse_command(b"\xff\xff\xff")


def test_every_birth_metric_has_a_timestamp_and_data_does_not_repeat_the_type() -> None:
    """An item never read has no updateTs: its DBIRTH metric takes the payload's
    timestamp (Sparkplug 3.0 wants one on every birth metric); DDATA refers to metrics by
    alias and leaves their datatype out."""
    spec = MetricDef("m", 3, TYPES["UInt16"])
    never = Sample("m", None, ItemStatus.UNKNOWN, None, None)
    (born,) = decode(device_birth(1, 5000, [(never, spec)])).metrics
    assert born.timestamp == 5000 and born.datatype == TYPES["UInt16"] and born.is_null
    assert born.properties == {"Quality": 0, "errorReason": "not read yet"}
    (data,) = decode(device_data(2, 6000, [(Sample("m", 7, ItemStatus.OK, 5500, None),
                                            spec, False)])).metrics
    assert (data.name, data.alias, data.datatype, data.timestamp) == (None, 3, None, 5500)
    assert data.raw == 7
