"""Encoding a write: a value into the registers (or bit) of its item."""

from __future__ import annotations

import datetime as _dt
import math
import struct
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation

from .. import _ffi
from ..datatypes import Area, DataType
from .scaling import factor_of, to_eng, to_raw
from .spec import _EPOCH, _F, _WIRE_RANGE, _WIRE_TYPE, ValueSpec, _compile, _scale, check_spec

__all__ = ["encode", "register_bit"]

_FLT_MAX = 3.4028234663852886e38


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
    what = _WIRE_TYPE[wire]
    t = spec.data_type
    if t.is_integer and spec.converted_type in (None, t):
        tlo, thi = t.integer_range
        if tlo > lo or thi < hi:  # Smart Cast from a wider read: the type's own range
            lo, hi, what = max(lo, tlo), min(hi, thi), t.value
    if spec.scaled:
        return _encode_scaled_int(spec, value, x, lo, hi, what)
    if (isinstance(x, float) and not math.isfinite(x)) or (
        isinstance(x, Decimal) and not x.is_finite()
    ):
        raise _fail(spec, value, _scaled_range(lo, hi, m))
    d = _decimal(x)
    if m != 1:
        d = d / _decimal(m)
    raw = int(d.to_integral_value(rounding=ROUND_HALF_EVEN))
    if not lo <= raw <= hi:
        raise _fail(spec, value, f"{_scaled_range(lo, hi, m)} ({what} on the device)")
    return raw


def _encode_scaled_int(spec: ValueSpec, value: object, x: int | float | Decimal, lo: int,
                       hi: int, what: str) -> int:
    """An integer item's raw value through the exact inverse of its engineering units
    (codec/scaling.py: offset, range, the last scale factor read)."""
    sf = factor_of(spec)
    a, b = sorted((to_eng(spec, lo, sf), to_eng(spec, hi, sf)))
    allowed = f"{_fmt_decimal(a)}..{_fmt_decimal(b)} ({what} on the device)"
    d = _decimal(x)
    if not d.is_finite():
        raise _fail(spec, value, allowed)
    try:
        raw = int(to_raw(spec, d, sf).to_integral_value(rounding=ROUND_HALF_EVEN))
    except ValueError as exc:
        raise _fail(spec, value, str(exc).partition(": allowed ")[2]) from None
    if not lo <= raw <= hi:
        raise _fail(spec, value, allowed)
    return raw


def _encode_float(spec: ValueSpec, value: object, wire: str) -> float:
    x = float(_number(spec, value))
    flag, k = _scale(spec.multiplier)
    if spec.scaled:
        if not math.isfinite(x):
            raise _fail(spec, value, "a finite number (the item is scaled)")
        sf = factor_of(spec)
        try:
            x = float(to_raw(spec, _decimal(x), sf))
        except ValueError as exc:
            raise _fail(spec, value, str(exc).partition(": allowed ")[2]) from None
        flag = 0
    if flag == _F["DIVIDE"]:
        x = x * k
    elif flag:
        x = x / k
    if (wire == "F32" or spec.data_type is DataType.FLOAT) and math.isfinite(x):
        try:
            rounded: float = struct.unpack(">f", struct.pack(">f", x))[0]
        except OverflowError:
            limit = _FLT_MAX * abs(spec.multiplier)
            raise _fail(spec, value, f"-{limit:g}..{limit:g} (Float on the device)") from None
        if wire == "F32":
            # the float32 the registers will hold, rounded here: a value just past
            # FLT_MAX that rounds to it (3.4028235e+38, FLT_MAX's shortest text, which
            # every JSON output writes) is FLT_MAX, which C's range check lets through
            x = rounded
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
    register's 16-bit byte swap (as when it is read), so with ``byte_swap16`` bit 3 is
    wire bit 11; ``dataFormat`` does not move it (a bit is in one register)."""
    if spec.bit is None:
        raise ValueError(f"item {spec.name!r} is not a bit of a register")
    return spec.bit ^ 8 if spec.byte_swap16 else spec.bit


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
    regs = _ffi.codec_encode(item, raw, fval, data)
    pad = (spec.quantity or item.nregs) - len(regs)
    if pad > 0:  # Smart Cast: the registers the value does not use are written as 0
        return [0] * pad + regs if item.offset else regs + [0] * pad
    return regs
