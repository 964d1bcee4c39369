"""An independent Sparkplug B reader and writer for tests: the protobuf wire format
(varints, fixed32/64, length-delimited) by hand, with the field numbers of the Sparkplug
3.0 specification's Payload, Metric, PropertySet and PropertyValue messages.  It shares
nothing with edgemodbus' encoder (which uses the protobuf package and generated code),
so a wrong field number or value encoding on either side fails the tests."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

# Sparkplug data types (spec 3.0, 6.4.16)
TYPES = {"Int8": 1, "Int16": 2, "Int32": 3, "Int64": 4, "UInt8": 5, "UInt16": 6,
         "UInt32": 7, "UInt64": 8, "Float": 9, "Double": 10, "Boolean": 11, "String": 12,
         "DateTime": 13, "Bytes": 17}
_SIGNED32 = {1, 2, 3}


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        byte = buf[i]
        i += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, i
        shift += 7


def fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    """(field number, wire type, value): int for varint, bytes for the others."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i:i + 8], i + 8
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        elif wire == 2:
            size, i = _varint(buf, i)
            value, i = buf[i:i + size], i + size
        else:
            raise ValueError(f"wire type {wire} at field {number}")
        yield number, wire, value


@dataclass
class Metric:
    name: str | None = None
    alias: int | None = None
    timestamp: int | None = None
    datatype: int | None = None
    is_null: bool = False
    raw: Any = None  # the value field as on the wire
    value_field: int | None = None
    properties: dict[str, Any] = field(default_factory=dict)

    @property
    def value(self) -> Any:
        """The value read as its datatype (signed types from two's complement)."""
        if self.raw is None:
            return None
        if self.datatype in _SIGNED32 and self.raw >= 1 << 31:
            return self.raw - (1 << 32)
        if self.datatype == 4 and self.raw >= 1 << 63:
            return self.raw - (1 << 64)
        return self.raw


@dataclass
class Payload:
    timestamp: int | None = None
    seq: int | None = None
    metrics: list[Metric] = field(default_factory=list)

    def by_name(self) -> dict[str, Metric]:
        return {m.name: m for m in self.metrics if m.name is not None}

    def by_alias(self) -> dict[int, Metric]:
        return {m.alias: m for m in self.metrics if m.alias is not None}

    def values(self, birth: Payload) -> dict[int, Any]:
        """DDATA values by alias, read as a host reads them: with the datatype their
        DBIRTH gave (DDATA need not repeat it)."""
        born = birth.by_alias()
        return {m.alias: replace(m, datatype=m.datatype or born[m.alias].datatype).value
                for m in self.metrics if m.alias is not None}


def _metric_value(number: int, raw: Any) -> Any:
    if number in (10, 11):
        return raw
    if number == 12:
        return struct.unpack("<f", raw)[0]
    if number == 13:
        return struct.unpack("<d", raw)[0]
    if number == 14:
        return bool(raw)
    if number == 15:
        return raw.decode("utf-8")
    if number == 16:
        return bytes(raw)
    raise ValueError(f"metric value field {number} not supported here")


def _property_value(buf: bytes) -> Any:
    value: Any = None
    for number, _wire, raw in fields(buf):
        if number in (3, 4):
            value = raw
        elif number == 5:
            value = struct.unpack("<f", raw)[0]
        elif number == 6:
            value = struct.unpack("<d", raw)[0]
        elif number == 7:
            value = bool(raw)
        elif number == 8:
            value = raw.decode("utf-8")
    return value


def _properties(buf: bytes) -> dict[str, Any]:
    keys: list[str] = []
    values: list[Any] = []
    for number, _wire, raw in fields(buf):
        if number == 1:
            keys.append(raw.decode("utf-8"))
        elif number == 2:
            values.append(_property_value(raw))
    assert len(keys) == len(values), (keys, values)
    return dict(zip(keys, values, strict=True))


def _metric(buf: bytes) -> Metric:
    metric = Metric()
    for number, _wire, raw in fields(buf):
        if number == 1:
            metric.name = raw.decode("utf-8")
        elif number == 2:
            metric.alias = raw
        elif number == 3:
            metric.timestamp = raw
        elif number == 4:
            metric.datatype = raw
        elif number == 7:
            metric.is_null = bool(raw)
        elif number == 9:
            metric.properties = _properties(raw)
        elif 10 <= number <= 16:
            metric.value_field = number
            metric.raw = _metric_value(number, raw)
    return metric


def decode(buf: bytes) -> Payload:
    payload = Payload()
    for number, _wire, raw in fields(buf):
        if number == 1:
            payload.timestamp = raw
        elif number == 2:
            payload.metrics.append(_metric(raw))
        elif number == 3:
            payload.seq = raw
    return payload


# -- writing (what a host application sends: NCMD, DCMD) --------------------------------
def _put_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _put_varint(number << 3 | wire)


def _len(number: int, data: bytes) -> bytes:
    return _key(number, 2) + _put_varint(len(data)) + data


def encode_metric(*, name: str | None = None, alias: int | None = None,
                  datatype: str, value: Any, timestamp: int = 0) -> bytes:
    """One Metric as a host writes it (signed ints as 32-bit two's complement)."""
    code = TYPES[datatype]
    out = b""
    if name is not None:
        out += _len(1, name.encode())
    if alias is not None:
        out += _key(2, 0) + _put_varint(alias)
    out += _key(3, 0) + _put_varint(timestamp) + _key(4, 0) + _put_varint(code)
    if datatype == "Boolean":
        out += _key(14, 0) + _put_varint(int(bool(value)))
    elif datatype == "Float":
        out += _key(12, 5) + struct.pack("<f", value)
    elif datatype == "Double":
        out += _key(13, 1) + struct.pack("<d", value)
    elif datatype == "String":
        out += _len(15, value.encode())
    elif datatype in ("Int64", "UInt64", "DateTime"):
        out += _key(11, 0) + _put_varint(value & 0xFFFF_FFFF_FFFF_FFFF)
    else:
        out += _key(10, 0) + _put_varint(value & 0xFFFF_FFFF)
    return out


def encode(metrics: list[bytes], timestamp: int = 0, seq: int | None = None) -> bytes:
    out = _key(1, 0) + _put_varint(timestamp)
    for metric in metrics:
        out += _len(2, metric)
    if seq is not None:
        out += _key(3, 0) + _put_varint(seq)
    return out
