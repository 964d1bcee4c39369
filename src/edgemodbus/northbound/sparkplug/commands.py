"""The metrics of NCMD and DCMD messages: read from untrusted bytes (the broker delivers
whatever any client publishes), within caps, and a command's value taken as the type of
the metric it writes only when nothing is lost.

Caps (a message past one is refused whole, before anything is written): the payload's
size (:data:`MAX_COMMAND_BYTES`), its metrics (:data:`MAX_COMMAND_METRICS`) and a metric
name's length (:data:`MAX_NAME_CHARS`).  Refusals say which cap and never repeat the
oversized text.

Values: Boolean only from a boolean; String only from a string; Bytes only from bytes;
DateTime from an integer (ms since the epoch); an integer type from an integer (signed
types read as two's complement, as Eclipse Tahu's encoders send them) or from a Float or
Double that is a whole number; Float and Double from a number they hold exactly.  A
declared ``datatype`` of another kind (a Boolean for a UInt16, a String for a Float) is
refused, whatever the value."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

from ...line.log_limit import short_text
from . import sparkplug_b_pb2 as pb
from .payloads import (
    BOOLEAN,
    BYTES,
    DATETIME,
    DOUBLE,
    FLOAT,
    INT8,
    INT16,
    INT32,
    INT64,
    REBIRTH,
    STRING,
    UINT8,
    UINT16,
    UINT32,
    UINT64,
)

MAX_COMMAND_BYTES = 256 * 1024
"""A command payload larger than this is refused unread."""
MAX_COMMAND_METRICS = 1000
"""Metrics per command message."""
MAX_NAME_CHARS = 256
"""Characters of one metric name."""

_SIGNED_BITS = {INT8: 8, INT16: 16, INT32: 32, INT64: 64}
_INTEGERS = {INT8, INT16, INT32, INT64, UINT8, UINT16, UINT32, UINT64}
_FLOATS = {FLOAT, DOUBLE}
_TEXT = {STRING, 14, 15}  # String, Text, UUID
_INT_FIELDS = ("int_value", "long_value")
_FLOAT_FIELDS = ("float_value", "double_value")


def type_name(datatype: int) -> str:
    """A Sparkplug data type number in words (``UInt16``), or the number if unknown."""
    try:
        return str(pb.DataType.Name(datatype))
    except ValueError:
        return str(datatype)


def _kind(datatype: int) -> str:
    if datatype in _INTEGERS or datatype in _FLOATS:
        return "number"
    if datatype in _TEXT:
        return "text"
    return {BOOLEAN: "boolean", DATETIME: "datetime", BYTES: "bytes"}.get(datatype,
                                                                          type_name(datatype))


@dataclass(frozen=True, slots=True)
class CommandMetric:
    """One metric of an NCMD or DCMD: named (``name``) or by ``alias``; ``field`` is the
    value field that was set (``int_value``...), None when it carries no value."""

    name: str | None
    alias: int | None
    datatype: int | None
    field: str | None
    raw: Any

    @property
    def label(self) -> str:
        """How a log line or refusal names it (a short prefix of the name)."""
        return short_text(self.name) if self.name is not None else f"alias {self.alias}"


def parse_command(payload: bytes) -> list[CommandMetric]:
    """The metrics of a command payload; ValueError when it is not a Sparkplug payload or
    is past a cap (the message says which, not the oversized text)."""
    if len(payload) > MAX_COMMAND_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is over the limit of "
                         f"{MAX_COMMAND_BYTES}")
    message = pb.Payload()
    try:
        message.ParseFromString(payload)
    except Exception:  # google.protobuf.message.DecodeError
        raise ValueError(f"not a Sparkplug B payload ({len(payload)} bytes)") from None
    if len(message.metrics) > MAX_COMMAND_METRICS:
        raise ValueError(f"{len(message.metrics)} metrics in one message, over the limit "
                         f"of {MAX_COMMAND_METRICS}")
    found: list[CommandMetric] = []
    for i, metric in enumerate(message.metrics):
        name = metric.name if metric.HasField("name") else None
        if name is not None and len(name) > MAX_NAME_CHARS:
            raise ValueError(f"metric {i}: a name of {len(name)} characters, over the "
                             f"limit of {MAX_NAME_CHARS}")
        field = metric.WhichOneof("value")
        found.append(CommandMetric(
            name,
            metric.alias if metric.HasField("alias") else None,
            metric.datatype if metric.HasField("datatype") else None,
            None if metric.is_null else field,
            getattr(metric, field) if field is not None else None,
        ))
    return found


def _signed(raw: int, datatype: int, field: str) -> int:
    """``raw`` of ``field`` read as signed ``datatype`` (two's complement: 32-bit in
    int_value, or the type's own width as Tahu's Python encoder sends it; 64-bit in
    long_value)."""
    if field == "long_value":
        return raw - (1 << 64) if raw >= 1 << 63 else raw
    if raw >= 1 << 31:
        return raw - (1 << 32)
    bits = min(_SIGNED_BITS[datatype], 32)
    return raw - (1 << bits) if raw >= 1 << (bits - 1) else raw


def _exact_float(value: float | int, datatype: int) -> float:
    number = float(value)
    if isinstance(value, int) and int(number) != value:
        raise ValueError(f"{value} has no exact {type_name(datatype)} value")
    if datatype == FLOAT and math.isfinite(number):
        try:
            exact = struct.unpack("<f", struct.pack("<f", number))[0] == number
        except OverflowError:
            exact = False
        if not exact:
            raise ValueError(f"{number!r} has no exact Float (32-bit) value")
    return number


def command_value(command: CommandMetric, datatype: int) -> Any:
    """The value a command sets, as ``datatype`` (the metric's as born), converted only
    without loss (the module's docstring lists what is taken); ValueError says why not."""
    field, raw, declared = command.field, command.raw, command.datatype
    wanted = type_name(datatype)
    if field is None:
        raise ValueError("the metric carries no value")
    if field in ("dataset_value", "template_value", "extension_value"):
        raise ValueError(f"{field} is not supported for writes")
    if declared is not None and declared != datatype and _kind(declared) != _kind(datatype):
        raise ValueError(f"its datatype {type_name(declared)} does not match the metric's "
                         f"{wanted}")
    if datatype == BOOLEAN:
        if field != "boolean_value":
            raise ValueError(f"a Boolean metric takes a boolean value, not {field}")
        return bool(raw)
    if datatype in _TEXT:
        if field != "string_value":
            raise ValueError(f"a {wanted} metric takes a string value, not {field}")
        return str(raw)
    if datatype == BYTES:
        if field != "bytes_value":
            raise ValueError(f"a Bytes metric takes a bytes value, not {field}")
        return bytes(raw)
    if field in _INT_FIELDS:
        source = declared if declared in _SIGNED_BITS else datatype
        number = _signed(int(raw), source, field) if source in _SIGNED_BITS else int(raw)
        return _exact_float(number, datatype) if datatype in _FLOATS else number
    if field in _FLOAT_FIELDS and datatype in _INTEGERS:
        if not math.isfinite(raw) or raw != math.floor(raw):
            raise ValueError(f"{raw!r} is not a whole number; {wanted} takes integers only")
        return int(raw)
    if field in _FLOAT_FIELDS and datatype in _FLOATS:
        return _exact_float(raw, datatype)
    raise ValueError(f"a {wanted} metric cannot take {field}")


def node_command(metrics: list[CommandMetric]) -> tuple[bool, list[CommandMetric]]:
    """(rebirth asked: ``Node Control/Rebirth`` = true, the other metrics of the NCMD)."""
    rebirth, others = False, []
    for metric in metrics:
        if metric.name == REBIRTH and metric.field == "boolean_value" and metric.raw:
            rebirth = True
        else:
            others.append(metric)
    return rebirth, others


def split_reads(metrics: list[CommandMetric], name: str, items: bool = False
                ) -> tuple[bool, list[str], list[CommandMetric]]:
    """(whole: a ``name`` metric is the Boolean true, the items named by ``name``
    metrics with a String value (``items``: allowed), the other metrics); ValueError for
    a ``name`` metric of another value (nothing is read or written then)."""
    whole, names, others = False, [], []
    for metric in metrics:
        if metric.name != name:
            others.append(metric)
        elif metric.field == "boolean_value" and metric.raw:
            whole = True
        elif items and metric.field == "string_value" and metric.raw:
            names.append(str(metric.raw))
        else:
            allowed = "the Boolean true, or a String: an item's name" if items else (
                "the Boolean true")
            raise ValueError(f"{name} takes {allowed} (got {metric.field or 'null'})")
    return whole, names, others
