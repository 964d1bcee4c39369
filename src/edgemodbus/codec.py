"""Python face of the C value codec: item specs, block decoding with change detection,
and encoding of writes.

Choices this module makes (DESIGN.md leaves them open):

* A ``quantity`` larger than a fixed-size type needs: the value is read from the item's
  first registers (as many as the type needs, combined in the item's word order); the
  other registers are ignored on read and not written by :func:`encode`.
* Smart Cast (a ``quantity`` smaller than the type needs) reads the widest smaller
  value that fits: Int64/UInt64/Double from 2 registers read Int32/UInt32/Float32, from
  1 register Int16/UInt16/Int16; Int32/UInt32/Float from 1 register read Int16/UInt16/Int16;
  BCD32 from 1 register reads BCD16; DateTime/Timestamp need 2 (seconds) or 4 (ms).
* Byte/Sbyte and Char are the low byte of the register after the byte swap; Char is a
  1-character str of that byte's code point (latin-1: ``chr(byte)``).
* A bit of a register (``hr:100.3``) is taken after the byte swap, so it agrees with the
  UInt16 reading of the same register in the same format (bit 0 = least significant).
* ``convertedDataType`` Float keeps double precision but must fit a float32's range.
* Deadband applies to numeric results (int, float); bool, str, bytes and datetime values
  report any change.
* An item that stays Invalid is reported again when its reason changes (the slave now
  holds another bad value); the reason always names the value just read.
"""

from __future__ import annotations

import codecs
import datetime as _dt
import itertools
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from typing import Any

from . import _ffi
from ._ffi import Block, CodecItem, CodecPlan
from .datatypes import Area, DataFormat, DataType

__all__ = ["BlockDecoder", "Report", "ValueSpec", "check_spec", "encode", "register_bit"]

_W = _ffi.codec_constants("W")
_F = _ffi.codec_constants("F")
_C = _ffi.codec_constants("C")
_O = _ffi.codec_constants("O")
_E = _ffi.codec_constants("E")

MAX_QUANTITY = 125  # registers one read may return (Application Protocol 6.3)
_EPOCH = _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)
_FLT_MAX = 3.4028234663852886e38

Report = tuple[int, object, "str | None"]  # (item index, value or None, error reason or None)


@dataclass(frozen=True, slots=True)
class ValueSpec:
    """How one item's registers (or bit) become a value and back.

    ``data_format`` is the effective one (the item's override or the device's);
    ``quantity`` is in registers (None = the type's default); ``deadband`` is absolute
    on the final value (0 = report any change).
    """

    name: str
    data_type: DataType
    data_format: DataFormat = DataFormat.ABCD
    quantity: int | None = None
    bit: int | None = None
    multiplier: float = 1.0
    converted_type: DataType | None = None
    deadband: float = 0.0
    encoding: str = "utf-8"

    @property
    def registers(self) -> int:
        """Registers the item occupies in a register area (1 for a bit item)."""
        if self.bit is not None:
            return 1
        if self.quantity is not None:
            return self.quantity
        return self.data_type.registers


# -- validation ------------------------------------------------------------------------

_NO_CONVERSION = (
    DataType.CHAR,
    DataType.STRING,
    DataType.BINARY,
    DataType.DATETIME,
    DataType.TIMESTAMP,
)
_BAD_TARGETS = (DataType.CHAR, DataType.BINARY, DataType.DATETIME, DataType.TIMESTAMP)


def _bad(spec: ValueSpec, field: str, value: object, allowed: str) -> ValueError:
    return ValueError(f"item {spec.name!r}: {field} {value!r} is not allowed ({allowed})")


def check_spec(spec: ValueSpec, area: Area) -> None:
    """Raise ValueError naming the item if its spec cannot work in ``area``."""
    t = spec.data_type
    q = spec.quantity
    if q is not None and not (isinstance(q, int) and 1 <= q <= MAX_QUANTITY):
        raise _bad(spec, "quantity", q, f"1..{MAX_QUANTITY} registers")
    if area.is_bit:
        if t is not DataType.BOOLEAN:
            raise _bad(spec, "data type", t.value, f"{area.short_name} items are Boolean")
        if spec.bit is not None:
            raise _bad(spec, "bit", spec.bit, "only register items have a bit")
        if q not in (None, 1):
            raise _bad(spec, "quantity", q, f"a {area.short_name} item is 1 bit")
    elif spec.bit is not None:
        if t is not DataType.BOOLEAN:
            raise _bad(spec, "data type", t.value, "a bit of a register is Boolean")
        if not (isinstance(spec.bit, int) and 0 <= spec.bit <= 15):
            raise _bad(spec, "bit", spec.bit, "0..15")
        if q not in (None, 1):
            raise _bad(spec, "quantity", q, "a bit item is in 1 register")
    if t.needs_quantity and q is None:
        raise _bad(spec, "quantity", q, f"{t.value} needs a quantity of registers, 1..125")
    if t in (DataType.DATETIME, DataType.TIMESTAMP) and q is not None and q < 2:
        raise _bad(spec, "quantity", q, f"{t.value} takes 2 (seconds) or 4 (ms) registers")
    m = spec.multiplier
    if not (isinstance(m, (int, float)) and math.isfinite(m) and m != 0):
        raise _bad(spec, "dataMultiplier", m, "a finite number other than 0")
    if m != 1 and not t.is_numeric:
        raise _bad(spec, "dataMultiplier", m, f"{t.value} values take no multiplier, use 1")
    c = spec.converted_type
    if c is not None and c is not t:
        if t in _NO_CONVERSION:
            raise _bad(spec, "convertedDataType", c.value, f"{t.value} values are not converted")
        if c in _BAD_TARGETS:
            raise _bad(spec, "convertedDataType", c.value, "a numeric type, Boolean or String")
    db = spec.deadband
    if not (isinstance(db, (int, float)) and math.isfinite(db) and db >= 0):
        raise _bad(spec, "deadband", db, "a finite number >= 0")
    try:
        text_codec = getattr(codecs.lookup(spec.encoding), "_is_text_encoding", True)
    except LookupError:
        text_codec = False
    if not text_codec:
        raise _bad(spec, "encoding", spec.encoding, "a text encoding: utf-8, gbk, ascii...")


# -- compiling a spec into a C item ------------------------------------------------------

# (wire, registers) for each width a fixed-size type may be read with, widest first.
_WIDTHS: dict[DataType, tuple[tuple[str, int], ...]] = {
    DataType.INT16: (("I16", 1),),
    DataType.UINT16: (("U16", 1),),
    DataType.BCD16: (("BCD16", 1),),
    DataType.BYTE: (("U8", 1),),
    DataType.SBYTE: (("I8", 1),),
    DataType.CHAR: (("U8", 1),),
    DataType.BOOLEAN: (("REGBOOL", 1),),
    DataType.INT32: (("I32", 2), ("I16", 1)),
    DataType.UINT32: (("U32", 2), ("U16", 1)),
    DataType.FLOAT: (("F32", 2), ("I16", 1)),
    DataType.BCD32: (("BCD32", 2), ("BCD16", 1)),
    DataType.INT64: (("I64", 4), ("I32", 2), ("I16", 1)),
    DataType.UINT64: (("U64", 4), ("U32", 2), ("U16", 1)),
    DataType.DOUBLE: (("F64", 4), ("F32", 2), ("I16", 1)),
    DataType.DATETIME: (("MS64", 4), ("SEC32", 2)),
    DataType.TIMESTAMP: (("MS64", 4), ("SEC32", 2)),
}

# Integer range of each integer wire (what the registers can hold).
_WIRE_RANGE: dict[str, tuple[int, int]] = {
    "U8": (0, 0xFF),
    "I8": (-0x80, 0x7F),
    "U16": (0, 0xFFFF),
    "I16": (-0x8000, 0x7FFF),
    "U32": (0, 0xFFFF_FFFF),
    "I32": (-0x8000_0000, 0x7FFF_FFFF),
    "U64": (0, 0xFFFF_FFFF_FFFF_FFFF),
    "I64": (-(1 << 63), (1 << 63) - 1),
    "BCD16": (0, 9999),
    "BCD32": (0, 99_999_999),
}
_WIRE_TYPE = {
    "U8": "Byte",
    "I8": "Sbyte",
    "U16": "UInt16",
    "I16": "Int16",
    "U32": "UInt32",
    "I32": "Int32",
    "U64": "UInt64",
    "I64": "Int64",
    "BCD16": "BCD16",
    "BCD32": "BCD32",
    "F32": "Float",
    "F64": "Double",
}

_TARGET = {
    DataType.BOOLEAN: "BOOL",
    DataType.SBYTE: "I8",
    DataType.BYTE: "U8",
    DataType.INT16: "I16",
    DataType.UINT16: "U16",
    DataType.INT32: "I32",
    DataType.UINT32: "U32",
    DataType.INT64: "I64",
    DataType.UINT64: "U64",
    DataType.BCD16: "BCD16",
    DataType.BCD32: "BCD32",
    DataType.FLOAT: "F32",
    DataType.DOUBLE: "F64",
}


def _wire(spec: ValueSpec, area: Area) -> tuple[str, int]:
    """The wire kind and register count the item is read with (after Smart Cast)."""
    if area.is_bit:
        return "COIL", 1
    if spec.bit is not None:
        return "REGBIT", 1
    t = spec.data_type
    if t.needs_quantity:
        return "BYTES", spec.quantity or 0
    widths = _WIDTHS[t]
    have = spec.quantity if spec.quantity is not None else t.registers
    for wire, n in widths:
        if n <= have:
            return wire, n
    return widths[-1]


def _scale(m: float) -> tuple[int, float]:
    """Flag and factor for a multiplier: divide by 1/m when that is an exact integer
    (so 0.1 gives raw/10, the correctly rounded decimal), else multiply."""
    if m == 1:
        return 0, 1.0
    inverse = 1 / m
    if abs(m) < 1 and math.isfinite(inverse):
        k = round(inverse)
        if k != 0 and 1 / k == m:
            return _F["DIVIDE"], float(k)
    return _F["MULTIPLY"], float(m)


def _to_datetime(ms: int) -> _dt.datetime:
    return _EPOCH + _dt.timedelta(milliseconds=ms)


def _string_post(encoding: str) -> Callable[[bytes], str]:
    def post(raw: bytes) -> str:
        return raw.decode(encoding, "replace")

    return post


@dataclass(frozen=True, slots=True)
class _Compiled:
    item: CodecItem
    post: Callable[[Any], object] | None
    wire: str
    target_label: str  # type name in error reasons
    target_range: tuple[int, int] | None


def _compile(spec: ValueSpec, area: Area, offset: int) -> _Compiled:
    t = spec.data_type
    wire, nregs = _wire(spec, area)
    fmt = spec.data_format
    flags = (_F["BYTE_SWAP"] if fmt.byte_swap else 0) | (_F["WORD_SWAP"] if fmt.word_swap else 0)
    scale_flag, scale = _scale(spec.multiplier)
    flags |= scale_flag
    conv = spec.converted_type
    if conv is t and (t in _NO_CONVERSION or spec.multiplier == 1):
        conv = None
    post: Callable[[Any], object] | None = None
    target = "NONE"
    label = t.value
    rng: tuple[int, int] | None = None
    if wire == "BYTES":
        out = "BYTES"
        if t is DataType.STRING:
            flags |= _F["STRIP"]
            post = _string_post(spec.encoding)
    elif t is DataType.CHAR:
        out, post = "I64", chr
    elif t is DataType.DATETIME:
        out, target, post = "I64", "DATETIME", _to_datetime
    elif conv is None or conv is DataType.STRING:
        if scale_flag:
            out = "F64"
        elif t is DataType.BOOLEAN:
            out = "BOOL"
        elif t in (DataType.FLOAT, DataType.DOUBLE):
            out = "F64"
        elif wire == "U64":
            out = "U64"
        else:
            out = "I64"
        if conv is DataType.STRING:
            post = str
    else:
        target = _TARGET[conv]
        label = conv.value
        if conv is DataType.BOOLEAN:
            out = "BOOL"
        elif conv in (DataType.FLOAT, DataType.DOUBLE):
            out = "F64"
        else:
            out = "U64" if conv is DataType.UINT64 else "I64"
            rng = conv.integer_range
    # a deadband is a distance between numbers: values made by `post` (chr, datetime,
    # str) are compared for any change, as bool and bytes are
    deadband = float(spec.deadband) if post is None else 0.0
    item = CodecItem(
        offset=offset,
        nregs=nregs,
        wire=_W[wire],
        flags=flags,
        bit=spec.bit or 0,
        target=_C[target],
        out=_O[out],
        scale=scale,
        deadband=deadband,
    )
    return _Compiled(item, post, wire, label, rng)


# -- decoding ---------------------------------------------------------------------------


def _fmt_number(v: float) -> str:
    if isinstance(v, int):
        return str(v)
    if math.isfinite(v) and v == int(v) and abs(v) < 2**53:
        return str(int(v))
    return repr(v)


_NO_TEXT = object()  # a String item whose last report was not a text


class BlockDecoder:
    """Decodes every item of one read block in one C call, reporting only what changed.

    Compiled once per plan; each decode reuses the same arrays.  Use from one thread at a
    time (the bus worker that owns the block).
    """

    __slots__ = (
        "_indices",
        "_offsets",
        "_plan",
        "_reported",
        "_texts",
        "area",
        "count",
        "specs",
    )

    def __init__(self, area: Area, count: int, items: Sequence[tuple[int, ValueSpec]]) -> None:
        if not (isinstance(count, int) and count >= 0):
            raise ValueError(f"block count {count!r} is not allowed (an int >= 0)")
        compiled: list[_Compiled] = []
        for offset, spec in items:
            check_spec(spec, area)
            size = 1 if area.is_bit else spec.registers
            if not (isinstance(offset, int) and offset >= 0 and offset + size <= count):
                raise ValueError(
                    f"item {spec.name!r}: offset {offset!r} (+{size}) is outside the block "
                    f"of {count} {'bits' if area.is_bit else 'registers'}"
                )
            compiled.append(_compile(spec, area, offset))
        self.area = area
        self.count = count
        self.specs = [spec for _, spec in items]
        self._offsets = [offset for offset, _ in items]
        # the compiled items live on in the C plan only: error reasons, which are rare,
        # compile their item again (see _reason), which keeps a decoder small per tag
        self._plan = CodecPlan(area.is_bit, [c.item for c in compiled], [c.post for c in compiled])
        self._indices = list(range(len(compiled)))
        # The tuple last reported for each item: mirrors the C state, so that a report of
        # every item rebuilds only the tuples whose value or status moved.
        self._reported: list[Report] = []
        # String items decode bytes that are not valid text to U+FFFD, so different
        # bytes (which C compares) can give the text already reported: the last text
        # reported for each String item (_NO_TEXT after an error or a reset).
        self._texts: dict[int, object] = {
            k: _NO_TEXT for k, spec in enumerate(self.specs) if spec.data_type is DataType.STRING
        }

    def _reason(self, index: int, code: int) -> str:
        if code == _E["MISSING"]:
            return "not in response"
        c = _compile(self.specs[index], self.area, self._offsets[index])
        if code == _E["NAN"]:
            return f"NaN cannot be converted to {c.target_label}"
        v = self._plan.errval(index)
        if v is None:  # the C codec gives every status but MISSING a value
            raise AssertionError(f"codec: item {index} failed (status {code}) without a value")
        if code == _E["BCD"]:
            digits = 4 if c.wire == "BCD16" else 8
            return f"invalid BCD value 0x{v:0{digits}X} (a digit above 9)"
        if c.target_label == "DateTime":
            return f"{_fmt_number(v)} ms is outside the dates Python can hold (years 1..9999)"
        if c.target_range is not None:
            lo, hi = c.target_range
            return f"value {_fmt_number(v)} is out of range for {c.target_label} ({lo}..{hi})"
        return f"value {_fmt_number(v)} is out of range for {c.target_label}"

    def decode(self, block: Block, report_all: bool = False) -> list[Report]:
        """(index, value or None, error reason or None) of every item whose value, status
        or error reason changed since it was last reported (all of them when
        ``report_all``)."""
        plan, mode = self.begin(report_all)
        return self.finish(plan.decode(block, mode), report_all)

    def begin(self, report_all: bool) -> tuple[CodecPlan, int]:
        """The C plan and mode of the next decode, for a caller that runs it itself (the
        bus reads and decodes a block in one C call); then call :meth:`finish`."""
        if report_all:
            if not self._reported:
                self._plan.reset()  # no tuples cached: have C report every item
            return self._plan, _ffi.CODEC_MODE_ALL
        if self._reported:
            self._reported = []  # the report-all cache no longer mirrors the C state
        return self._plan, _ffi.CODEC_MODE_TRACK

    def finish(self, n: int, report_all: bool) -> list[Report]:
        """The reports of a decode that returned ``n`` (see :meth:`decode`)."""
        if report_all:
            return self._finish_all(n)
        if not n:
            return []
        plan = self._plan
        changed = plan.changed(n)
        if n * 8 >= plan.n_items:  # many changed: convert the arrays in one go
            values = plan.values()
            errors = {k: self._reason(k, plan.status(k)) for k in plan.errors()}
            reports = [(k, values[k], errors.get(k)) for k in changed]
        else:
            status = plan.status_view
            reports = [
                (k, None, self._reason(k, status[k])) if status[k] else (k, plan.value(k), None)
                for k in changed
            ]
        return self._new_texts_only(reports) if self._texts else reports

    def _new_texts_only(self, reports: list[Report]) -> list[Report]:
        """``reports`` without the String items whose text is the one last reported."""
        texts = self._texts
        kept: list[Report] = []
        for report in reports:
            k, value, error = report
            if k in texts:
                last = texts[k]
                texts[k] = _NO_TEXT if error is not None else value
                if error is None and last == value:
                    continue
            kept.append(report)
        return kept

    def _finish_all(self, n: int) -> list[Report]:
        """Report every item; keeps the last tuples so that only the items whose value
        or status moved are rebuilt (reportMode "cycle" reports everything each read)."""
        plan = self._plan
        total = plan.n_items
        reported = self._reported
        if n == total or 2 * n >= total or not reported:
            # Most items are new: build every tuple in one go (a report of all items
            # holds the current value of each, so the rebuilt cache still mirrors C).
            values = plan.values()
            reported = list(zip(self._indices, values, itertools.repeat(None), strict=False))
            if plan.n_errors:
                for k in plan.errors():
                    reported[k] = (k, None, self._reason(k, plan.status(k)))
            self._reported = reported
        elif n:
            status = plan.status_view
            for k in plan.changed(n):
                code = status[k]
                reported[k] = (k, None, self._reason(k, code)) if code else (k, plan.value(k), None)
        texts = self._texts
        if texts:
            for k in texts:
                _, value, error = reported[k]
                texts[k] = _NO_TEXT if error is not None else value
        return reported[:]

    def decode_values(self, block: Block) -> list[object]:
        """Every item's value (None where it failed); change tracking is not touched."""
        plan = self._plan
        plan.decode(block, _ffi.CODEC_MODE_VALUES)
        return plan.values()

    def errors(self) -> dict[int, str]:
        """Reasons of the items that failed in the last decode, by index."""
        plan = self._plan
        return {k: self._reason(k, plan.status(k)) for k in plan.errors()}

    def reset(self) -> None:
        """Forget the last reported values: the next decode reports every item."""
        self._plan.reset()
        self._reported = []
        for k in self._texts:
            self._texts[k] = _NO_TEXT


# -- encoding ---------------------------------------------------------------------------


def _fail(spec: ValueSpec, value: object, allowed: str) -> ValueError:
    return ValueError(f"item {spec.name!r}: cannot write {value!r}: allowed {allowed}")


def _number(spec: ValueSpec, value: object) -> int | float | Decimal:
    """A write value as a number (bool -> 0/1; str only for convertedDataType String)."""
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, (int, float, Decimal)):
        return value
    if isinstance(value, str) and spec.converted_type is DataType.STRING:
        try:
            return Decimal(value.strip())
        except InvalidOperation:
            raise _fail(spec, value, "a number") from None
    raise _fail(spec, value, f"a number for {spec.data_type.value}")


def _decimal(x: int | float | Decimal) -> Decimal:
    # repr() is the shortest decimal that round-trips: 0.35 stays 0.35, not 0.34999...
    return x if isinstance(x, Decimal) else Decimal(repr(x)) if isinstance(x, float) else Decimal(x)


def _scaled_range(lo: int | float, hi: int | float, m: float) -> str:
    a, b = _decimal(lo) * _decimal(m), _decimal(hi) * _decimal(m)
    a, b = min(a, b), max(a, b)
    return f"{_fmt_decimal(a)}..{_fmt_decimal(b)}"


def _fmt_decimal(d: Decimal) -> str:
    return format(d.normalize(), "f") if d == d.to_integral_value() else str(d.normalize())


def _encode_int(spec: ValueSpec, value: object, wire: str) -> int:
    x = _number(spec, value)
    m = spec.multiplier
    lo, hi = _WIRE_RANGE[wire]
    if (isinstance(x, float) and not math.isfinite(x)) or (
        isinstance(x, Decimal) and not x.is_finite()
    ):
        raise _fail(spec, value, _scaled_range(lo, hi, m))
    d = _decimal(x)
    if m != 1:
        d = d / _decimal(m)
    raw = int(d.to_integral_value(rounding=ROUND_HALF_EVEN))
    if not lo <= raw <= hi:
        what = _WIRE_TYPE[wire]
        raise _fail(spec, value, f"{_scaled_range(lo, hi, m)} ({what} on the device)")
    return raw


def _encode_float(spec: ValueSpec, value: object, wire: str) -> float:
    x = float(_number(spec, value))
    flag, k = _scale(spec.multiplier)
    if flag == _F["DIVIDE"]:
        x = x * k
    elif flag:
        x = x / k
    if wire == "F32" and math.isfinite(x):
        try:
            struct.pack(">f", x)
        except OverflowError:
            limit = _FLT_MAX * abs(spec.multiplier)
            raise _fail(spec, value, f"-{limit:g}..{limit:g} (Float on the device)") from None
    return x


def _as_bool(spec: ValueSpec, value: object) -> bool:
    if isinstance(value, str):
        key = value.strip().lower()
        if key in ("true", "1", "on"):
            return True
        if key in ("false", "0", "off"):
            return False
        raise _fail(spec, value, "true/false, 1/0")
    if isinstance(value, (bool, int, float, Decimal)):
        return bool(value)
    raise _fail(spec, value, "a bool")


def _utc(value: _dt.datetime) -> _dt.datetime:
    return value.replace(tzinfo=_dt.timezone.utc) if value.tzinfo is None else value


def _encode_time(spec: ValueSpec, value: object, wire: str) -> int:
    """DateTime/Timestamp as Unix seconds (SEC32) or ms (MS64), rounding half to even."""
    if isinstance(value, _dt.datetime):
        delta = _utc(value) - _EPOCH
        us = (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
        ms = Decimal(us) / 1000
    elif (
        spec.data_type is DataType.TIMESTAMP
        and isinstance(value, int)
        and not isinstance(value, bool)
    ):
        ms = Decimal(value)
    else:
        kind = "a datetime" if spec.data_type is DataType.DATETIME else "int ms or a datetime"
        raise _fail(spec, value, kind)
    if wire == "SEC32":
        secs = int((ms / 1000).to_integral_value(rounding=ROUND_HALF_EVEN))
        if not 0 <= secs <= 0xFFFF_FFFF:
            raise _fail(spec, value, "1970-01-01..2106-02-07 (uint32 seconds)")
        return secs
    raw = int(ms.to_integral_value(rounding=ROUND_HALF_EVEN))
    if not -(1 << 63) <= raw < (1 << 63):
        raise _fail(spec, value, "an int64 of milliseconds")
    return raw


def register_bit(spec: ValueSpec) -> int:
    """The position on the wire of a bit item's bit: the item's bit is counted after the
    format's byte swap (as when it is read), so under BADC/DCBA bit 3 is wire bit 11."""
    if spec.bit is None:
        raise ValueError(f"item {spec.name!r} is not a bit of a register")
    return spec.bit ^ 8 if spec.data_format.byte_swap else spec.bit


def encode(spec: ValueSpec, value: object) -> list[int]:
    """The registers to write for ``value`` (or [0 | 1] for a Boolean: a coil, a bit of a
    register — at :func:`register_bit` — or a whole register).  Applies the
    inverse of the converted type and multiplier, then the item's format."""
    check_spec(spec, Area.HOLDING_REGISTER)
    t = spec.data_type
    if t is DataType.BOOLEAN:
        return [1 if _as_bool(spec, value) else 0]
    compiled = _compile(spec, Area.HOLDING_REGISTER, 0)
    wire, item = compiled.wire, compiled.item
    raw, fval, data = 0, 0.0, b""
    if t is DataType.STRING:
        if not isinstance(value, str):
            raise _fail(spec, value, "a str")
        try:
            data = value.encode(spec.encoding)
        except UnicodeEncodeError:
            raise _fail(spec, value, f"text that {spec.encoding} can encode") from None
        if len(data) > 2 * item.nregs:
            raise _fail(spec, value, f"at most {2 * item.nregs} bytes in {spec.encoding}")
    elif t is DataType.BINARY:
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise _fail(spec, value, "bytes")
        data = bytes(value)
        if len(data) > 2 * item.nregs:
            raise _fail(spec, value, f"at most {2 * item.nregs} bytes")
    elif t is DataType.CHAR:
        code = ord(value) if isinstance(value, str) and len(value) == 1 else value
        if not (isinstance(code, int) and not isinstance(code, bool) and 0 <= code <= 0xFF):
            raise _fail(spec, value, "one character U+0000..U+00FF (or its code 0..255)")
        raw = code
    elif t in (DataType.DATETIME, DataType.TIMESTAMP):
        raw = _encode_time(spec, value, wire)
    elif wire in ("F32", "F64"):
        fval = _encode_float(spec, value, wire)
    else:
        raw = _encode_int(spec, value, wire)
    return _ffi.codec_encode(item, raw, fval, data)
