"""Sparkplug B payloads (protobuf, the specification's schema in sparkplug_b.proto): our
data types as Sparkplug's and item values as metrics (the metrics of commands are read by
commands.py).

Values (Sparkplug 3.0, 6.4.16 and Eclipse Tahu's encoders): Int8/Int16/Int32 go in the
uint32 ``int_value`` as 32-bit two's complement, Int64 in ``long_value`` as 64-bit two's
complement, UInt8..UInt32 in ``int_value``, UInt64 and DateTime (ms since the epoch, UTC)
in ``long_value``.  An item without a good value is ``is_null`` and carries the quality
property (Ignition / Cirrus Link convention, an Int32 property ``Quality``): 192 good,
0 bad (Invalid, or Unknown: never read); a bad item also carries ``errorReason``."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from ...datatypes import DataType, ItemStatus
from . import sparkplug_b_pb2 as pb

# Sparkplug data type numbers (sparkplug_b.proto, enum DataType)
INT8, INT16, INT32, INT64 = 1, 2, 3, 4
UINT8, UINT16, UINT32, UINT64 = 5, 6, 7, 8
FLOAT, DOUBLE, BOOLEAN, STRING, DATETIME, BYTES = 9, 10, 11, 12, 13, 17

SPARKPLUG_TYPES: dict[DataType, int] = {
    DataType.BOOLEAN: BOOLEAN,
    DataType.BYTE: UINT8,
    DataType.SBYTE: INT8,
    DataType.CHAR: STRING,  # a 1-character str
    DataType.INT16: INT16,
    DataType.UINT16: UINT16,
    DataType.INT24: INT32,
    DataType.UINT24: UINT32,
    DataType.INT32: INT32,
    DataType.UINT32: UINT32,
    DataType.INT64: INT64,
    DataType.UINT64: UINT64,
    DataType.FLOAT: FLOAT,
    DataType.DOUBLE: DOUBLE,
    DataType.STRING: STRING,
    DataType.DATETIME: DATETIME,
    DataType.TIMESTAMP: DATETIME,  # int ms since the epoch
    DataType.BINARY: BYTES,
    DataType.BCD16: UINT16,  # 0..9999
    DataType.BCD32: UINT32,  # 0..99999999
}
TYPE_NAMES = {value: pb.DataType.Name(value) for value in set(SPARKPLUG_TYPES.values())}
_SIGNED_BITS = {INT8: 8, INT16: 16, INT32: 32, INT64: 64}
_UNSIGNED_MAX = {UINT8: 0xFF, UINT16: 0xFFFF, UINT32: 0xFFFF_FFFF}

REBIRTH = "Node Control/Rebirth"
NODE_READ = "Node Control/Read"  # reads on demand (northbound/sparkplug/reads.py)
DEVICE_READ = "Device Control/Read"
QUALITY_GOOD = 192
QUALITY_BAD = 0


def sparkplug_type(device_type: DataType, converted: DataType | None,
                   multiplier: float) -> int:
    """The Sparkplug type of an item's values: its convertedDataType, else Double when
    a multiplier other than 1 makes its values floats, else its deviceDataType."""
    if converted is not None:
        return SPARKPLUG_TYPES[converted]
    if multiplier != 1 and device_type.is_numeric:
        return DOUBLE
    return SPARKPLUG_TYPES[device_type]


def epoch_ms(when: datetime | None) -> int | None:
    return None if when is None else int(when.timestamp() * 1000)


@dataclass(frozen=True, slots=True)
class Sample:
    """One item's report: what a metric carries."""

    name: str
    value: Any
    status: ItemStatus
    ts: int | None  # ms since the epoch (the item's updateTs)
    reason: str | None


@dataclass(frozen=True, slots=True)
class MetricDef:
    """A metric as born: its name, node-wide alias and Sparkplug type."""

    name: str
    alias: int
    datatype: int


def _set_value(metric: Any, datatype: int, value: Any) -> None:
    """The typed field of ``metric`` (Metric or PropertyValue); raises ValueError,
    TypeError or OverflowError when ``value`` does not fit ``datatype``."""
    if datatype == BOOLEAN:
        metric.boolean_value = bool(value)
    elif datatype == FLOAT:
        metric.float_value = float(value)
    elif datatype == DOUBLE:
        metric.double_value = float(value)
    elif datatype == STRING:
        metric.string_value = value if isinstance(value, str) else str(value)
    elif datatype == BYTES:
        metric.bytes_value = bytes(value)
    elif datatype == DATETIME:
        ms = int(value.timestamp() * 1000) if isinstance(value, datetime) else int(value)
        metric.long_value = ms & 0xFFFF_FFFF_FFFF_FFFF
    elif datatype == INT64:
        metric.long_value = _integer(value, -(1 << 63), (1 << 63) - 1) & 0xFFFF_FFFF_FFFF_FFFF
    elif datatype == UINT64:
        metric.long_value = _integer(value, 0, (1 << 64) - 1)
    elif datatype in (INT8, INT16, INT32):
        bits = _SIGNED_BITS[datatype]
        number = _integer(value, -(1 << (bits - 1)), (1 << (bits - 1)) - 1)
        metric.int_value = number & 0xFFFF_FFFF
    else:  # UInt8, UInt16, UInt32
        metric.int_value = _integer(value, 0, _UNSIGNED_MAX.get(datatype, 0xFFFF_FFFF))


def _integer(value: Any, low: int, high: int) -> int:
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{value} is not an integer")
        value = round(value)
    number = int(value)
    if not low <= number <= high:
        raise OverflowError(f"{number} is outside {low}..{high}")
    return number


def _add_metric(payload: Any, sample: Sample, spec: MetricDef, birth: bool,
                quality: bool) -> None:
    """One metric; a birth names it and gives its datatype, data refers to it by alias
    only, without repeating the datatype (Sparkplug 3.0 asks for it in births only).
    Every metric has a timestamp (required in births): its item's updateTs, else (an
    item never read) the payload's."""
    metric = payload.metrics.add()
    if birth:
        metric.name = spec.name
        metric.datatype = spec.datatype
    metric.alias = spec.alias
    metric.timestamp = sample.ts if sample.ts is not None else payload.timestamp
    good = sample.status is ItemStatus.OK and sample.value is not None
    if good:
        try:
            _set_value(metric, spec.datatype, sample.value)
        except (ValueError, TypeError, OverflowError) as exc:
            good = False
            sample = Sample(sample.name, None, ItemStatus.INVALID, sample.ts,
                            f"value {sample.value!r} is not a Sparkplug "
                            f"{TYPE_NAMES.get(spec.datatype, spec.datatype)}: {exc}")
    if not good:
        metric.is_null = True
    if quality or not good:
        props = metric.properties
        props.keys.append("Quality")
        prop = props.values.add()
        prop.type = INT32
        prop.int_value = QUALITY_GOOD if good else QUALITY_BAD
        reason = sample.reason or ("not read yet" if sample.status is ItemStatus.UNKNOWN
                                   else None)
        if not good and reason:
            props.keys.append("errorReason")
            text = props.values.add()
            text.type = STRING
            text.string_value = reason


def node_birth(bd_seq: int, now: int) -> bytes:
    """NBIRTH: seq 0, the session's bdSeq, ``Node Control/Rebirth`` and ``Node
    Control/Read`` (false)."""
    payload = pb.Payload(timestamp=now, seq=0)
    payload.metrics.add(name="bdSeq", timestamp=now, datatype=INT64, long_value=bd_seq)
    payload.metrics.add(name=REBIRTH, timestamp=now, datatype=BOOLEAN,
                        boolean_value=False)
    payload.metrics.add(name=NODE_READ, timestamp=now, datatype=BOOLEAN,
                        boolean_value=False)
    return bytes(payload.SerializeToString())


def node_death(bd_seq: int, now: int) -> bytes:
    """NDEATH (the MQTT will): the bdSeq of the session it ends, no seq."""
    payload = pb.Payload(timestamp=now)
    payload.metrics.add(name="bdSeq", timestamp=now, datatype=INT64, long_value=bd_seq)
    return bytes(payload.SerializeToString())


def device_birth(seq: int, now: int, metrics: Iterable[tuple[Sample, MetricDef]]) -> bytes:
    """DBIRTH: every metric with name, alias, type, timestamp, value (or null) and
    quality."""
    payload = pb.Payload(timestamp=now, seq=seq)
    for sample, spec in metrics:
        _add_metric(payload, sample, spec, birth=True, quality=True)
    return bytes(payload.SerializeToString())


def device_data(seq: int, now: int,
                metrics: Iterable[tuple[Sample, MetricDef, bool]]) -> bytes:
    """DDATA: metrics by alias only, without their datatype; the flag asks for the
    quality property (an item back to good after being bad; bad ones always carry it)."""
    payload = pb.Payload(timestamp=now, seq=seq)
    for sample, spec, quality in metrics:
        _add_metric(payload, sample, spec, birth=False, quality=quality)
    return bytes(payload.SerializeToString())


def device_death(seq: int, now: int) -> bytes:
    return bytes(pb.Payload(timestamp=now, seq=seq).SerializeToString())
