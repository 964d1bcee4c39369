"""An item's value spec: what it is (ValueSpec), whether it can work in an area
(check_spec), and how it compiles into the C codec's item (wire kind, width, scale,
output group and post-processing)."""

from __future__ import annotations

import codecs
import datetime as _dt
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .. import _ffi
from .._ffi import CodecItem, ScaleFactors
from ..datatypes import Area, DataFormat, DataFormat64, DataType
from ..protocol.limits import MAX_READ_REGISTERS
from .float32 import Float32, float32_text
from .scaling import check_scaling

__all__ = ["MAX_QUANTITY", "SMART_CAST_TYPES", "ValueSpec", "check_spec", "smart_cast"]

_W = _ffi.codec_constants("W")
_F = _ffi.codec_constants("F")
_C = _ffi.codec_constants("C")
_O = _ffi.codec_constants("O")

MAX_QUANTITY = MAX_READ_REGISTERS
"""An item's quantity of registers: at most one read's (protocol/limits.py)."""
_EPOCH = _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)


@dataclass(frozen=True, slots=True)
class ValueSpec:
    """How one item's registers (or bit) become a value and back.

    ``data_format`` is the effective one (the item's override or the device's): the
    order of values of two or more registers; ``byte_swap16`` swaps the two bytes of a
    one-register value (and of the register a bit is counted in), which ``data_format``
    never does; ``data_format64`` orders 64-bit (4-register) values, None: what
    ``data_format`` means for them (docs/device-files.md "Byte order").  ``quantity`` is in
    registers (None = the type's default); ``deadband`` is absolute on the final value
    (0 = report any change).

    Engineering units (codec/scaling.py): ``offset`` is added after the multiplier;
    ``raw_range``/``eng_range`` (rawMin, rawMax)/(engMin, engMax) map the raw value
    linearly, a raw value outside it Invalid, or with ``clamp`` the value held in the
    engineering range; ``scale_factor`` names the Int16 item whose value sf scales this
    one by 10^sf, ``holds_factor`` is the name an item that is a scale factor stores
    its value under, both in the device's ``factors``.
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
    byte_swap16: bool = False
    data_format64: DataFormat64 | None = None
    offset: float = 0.0
    raw_range: tuple[float, float] | None = None
    eng_range: tuple[float, float] | None = None
    clamp: bool = False
    scale_factor: str | None = None
    holds_factor: str | None = None
    factors: ScaleFactors | None = None

    @property
    def scaled(self) -> bool:
        """Whether the item has an engineering units step (an offset, a range or a
        scale factor) beyond the multiplier."""
        return bool(self.offset) or self.raw_range is not None or self.scale_factor is not None

    @property
    def format64(self) -> DataFormat64:
        """The order of this item's 64-bit values: its own, else ``data_format``'s."""
        if self.data_format64 is not None:
            return self.data_format64
        return DataFormat64.from_format(self.data_format)

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
        raise _bad(spec, "quantity", q,
                   f"{t.value} needs a quantity of registers, 1..{MAX_QUANTITY}")
    if t in (DataType.DATETIME, DataType.TIMESTAMP) and q is not None and q < 2:
        raise _bad(spec, "quantity", q, f"{t.value} takes 2 (seconds) or 4 (ms) registers")
    m = spec.multiplier
    if not (isinstance(m, (int, float)) and math.isfinite(m) and m != 0):
        raise _bad(spec, "dataMultiplier", m, "a finite number other than 0")
    if m != 1 and not t.is_numeric:
        raise _bad(spec, "dataMultiplier", m, f"{t.value} values take no multiplier, use 1")
    wrong = check_scaling(spec)
    if wrong is not None:
        raise _bad(spec, *wrong)
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
# Smart Cast (NG, docs/device-files.md "Smart Cast"): an item of `quantity` registers is read with
# the widest of these that fits in it: fewer registers than the type needs hold a smaller
# value that is widened; more registers hold a wider integer (or Float64) that is
# narrowed to the type, range-checked (out of range -> Invalid, never a silent wrap).
_WIDTHS: dict[DataType, tuple[tuple[str, int], ...]] = {
    DataType.INT16: (("I64", 4), ("I32", 2), ("I16", 1)),
    DataType.UINT16: (("U64", 4), ("U32", 2), ("U16", 1)),
    DataType.BCD16: (("BCD32", 2), ("BCD16", 1)),
    DataType.BYTE: (("U64", 4), ("U32", 2), ("U8", 1)),
    DataType.SBYTE: (("I64", 4), ("I32", 2), ("I8", 1)),
    DataType.CHAR: (("U8", 1),),
    DataType.BOOLEAN: (("REGBOOL", 1),),
    DataType.INT24: (("I64", 4), ("I24", 2), ("I16", 1)),
    DataType.UINT24: (("U64", 4), ("U24", 2), ("U16", 1)),
    DataType.INT32: (("I64", 4), ("I32", 2), ("I16", 1)),
    DataType.UINT32: (("U64", 4), ("U32", 2), ("U16", 1)),
    DataType.FLOAT: (("F64", 4), ("F32", 2), ("I16", 1)),
    DataType.BCD32: (("BCD32", 2), ("BCD16", 1)),
    DataType.INT64: (("I64", 4), ("I32", 2), ("I16", 1)),
    DataType.UINT64: (("U64", 4), ("U32", 2), ("U16", 1)),
    DataType.DOUBLE: (("F64", 4), ("F32", 2), ("I16", 1)),
    DataType.DATETIME: (("MS64", 4), ("SEC32", 2)),
    DataType.TIMESTAMP: (("MS64", 4), ("SEC32", 2)),
}

SMART_CAST_TYPES: frozenset[DataType] = frozenset(
    t for t, widths in _WIDTHS.items() if len(widths) > 1 and t.is_numeric
)
"""Types that take any quantity 1..MAX_QUANTITY (Smart Cast); the others keep their own."""

# Integer range of each integer wire (what the registers can hold).
_WIRE_RANGE: dict[str, tuple[int, int]] = {
    "U8": (0, 0xFF),
    "I8": (-0x80, 0x7F),
    "U16": (0, 0xFFFF),
    "I16": (-0x8000, 0x7FFF),
    "U24": (0, 0xFF_FFFF),
    "I24": (-0x80_0000, 0x7F_FFFF),
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
    "U24": "UInt24",
    "I24": "Int24",
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
    DataType.INT24: "I24",
    DataType.UINT24: "U24",
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


def _wire_shift(spec: ValueSpec, n: int) -> int:
    """Where the value's ``n`` registers start inside the item's ``quantity``: the item's
    registers in its format's order, most significant first, hold the value in their
    first ``n`` (NG's rule); the word swap reverses that order, so they are the last
    ``n`` in address order under CDAB/DCBA.  The others are ignored when read and
    written as 0."""
    q = spec.quantity
    if q is None or q <= n or not spec.data_format.word_swap or spec.bit is not None:
        return 0
    return q - n


def smart_cast(spec: ValueSpec) -> str | None:
    """What Smart Cast does with this item's quantity (None: nothing, the quantity is the
    type's own): the text of the warning logged once when the item is configured."""
    t, q = spec.data_type, spec.quantity
    if q is None or t not in SMART_CAST_TYPES or q == t.registers or spec.bit is not None:
        return None
    wire, n = _wire(spec, Area.HOLDING_REGISTER)
    what = _WIRE_TYPE[wire]
    if n > t.registers:
        how = f"read as {what} and narrowed to {t.value}"
        if spec.multiplier != 1:
            how += " (with a dataMultiplier the scaled value is reported as read)"
        elif spec.scaled:
            how += " (in engineering units the scaled value is reported as read)"
        elif t.is_integer:
            lo, hi = t.integer_range
            how += f" (a value outside {lo}..{hi} makes the item Invalid)"
        else:
            how += " (a value beyond Float's range makes the item Invalid)"
    elif n < t.registers:
        how = f"read as {what} and widened to {t.value}"
    else:
        how = f"read as {what}"
    text = f"{t.value} from {q} register{'s' if q != 1 else ''}: {how}"
    if q > n:
        first = _wire_shift(spec, n)
        unused = [k for k in range(q) if not first <= k < first + n]
        text += (
            f"; register{'s' if len(unused) > 1 else ''} "
            f"+{', +'.join(map(str, unused))} of the item "
            f"{'are' if len(unused) > 1 else 'is'} ignored when read and written as 0"
        )
    return text


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


def order_flags(spec: ValueSpec, wire: str, nregs: int) -> int:
    """The codec's byte and word order flags for a value read as ``wire`` in ``nregs``
    registers (DESIGN: ``dataFormat`` orders values of two or more registers).  One
    register (16-bit types, a bit, Smart Cast's one-register read): swapped only by
    ``byte_swap16``.  Four registers (64-bit values): ``format64``.  Two registers, and
    String/Binary (bytes in ``dataFormat``'s order, docs/device-files.md "Byte order"):
    ``data_format``."""
    if wire == "BYTES" or nregs == 2:
        fmt = spec.data_format
        return (_F["BYTE_SWAP"] if fmt.byte_swap else 0) | (
            _F["WORD_SWAP"] if fmt.word_swap else 0)
    if nregs == 4:
        f64 = spec.format64
        return ((_F["BYTE_SWAP"] if f64.byte_swap else 0)
                | (_F["WORD_SWAP"] if f64.word_swap else 0)
                | (_F["DWORD_SWAP"] if f64.dword_swap else 0))
    return _F["BYTE_SWAP"] if spec.byte_swap16 else 0


def _compile(spec: ValueSpec, area: Area, offset: int) -> _Compiled:
    t = spec.data_type
    wire, nregs = _wire(spec, area)
    flags = order_flags(spec, wire, nregs)
    scale_flag, scale = _scale(spec.multiplier)
    flags |= scale_flag
    scaled = bool(scale_flag) or spec.scaled  # the value is a double before conversion
    conv = spec.converted_type
    if conv is t and (t in _NO_CONVERSION or not scaled):
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
        if scaled:
            out = "F64"
        elif t is DataType.BOOLEAN:
            out = "BOOL"
        elif t in (DataType.FLOAT, DataType.DOUBLE):
            out = "F64"
        elif wire == "U64":
            out = "U64"
        else:
            out = "I64"
        if nregs > t.registers and not scaled and t in SMART_CAST_TYPES:
            # Smart Cast from a wider read: narrowed to the type, range-checked in C
            target = _TARGET[t]
            if t.is_integer:
                out, rng = "I64", t.integer_range
        float32 = t is DataType.FLOAT and not scaled
        if conv is DataType.STRING:
            post = float32_text if float32 else str
        elif float32:
            post = Float32
    else:
        target = _TARGET[conv]
        label = conv.value
        if conv is DataType.BOOLEAN:
            out = "BOOL"
        elif conv in (DataType.FLOAT, DataType.DOUBLE):
            out = "F64"
            if conv is DataType.FLOAT:
                post = Float32
        else:
            out = "U64" if conv is DataType.UINT64 else "I64"
            rng = conv.integer_range
    # a deadband is a distance between numbers: values made by `post` (chr, datetime,
    # str) are compared for any change, as bool and bytes are; a Float32 is a number
    deadband = float(spec.deadband) if post is None or post is Float32 else 0.0
    item = CodecItem(
        offset=offset + _wire_shift(spec, nregs),
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
