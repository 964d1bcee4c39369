"""Property tests: the C codec agrees with a plain struct decoder, and encode is the
inverse of decode for every type, format (dataFormat x byteSwap16 x dataFormat64) and
multiplier within range."""

from __future__ import annotations

import datetime as dt
import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ValueSpec, encode
from edgemodbus.datatypes import Area, DataFormat, DataFormat64, DataType

T = DataType
HR = Area.HOLDING_REGISTER
FORMATS = st.sampled_from(list(DataFormat))
SWAP16 = st.booleans()
# the 64-bit orders, spelled here (not taken from the package): the bytes A..H of the
# value as they sit in the registers by address; None: what dataFormat means
ORDERS64 = ["ABCDEFGH", "BADCFEHG", "CDABGHEF", "DCBAHGFE",
            "EFGHABCD", "FEHGBADC", "GHEFCDAB", "HGFEDCBA"]
FORMATS64 = st.one_of(st.none(), st.sampled_from(ORDERS64).map(DataFormat64))
REGISTER = st.integers(0, 0xFFFF)
EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)


def decode_one(spec: ValueSpec, registers: list[int]) -> object:
    decoder = BlockDecoder(HR, len(registers), [(0, spec)])
    return decoder.decode_values(Block.from_values(registers, bits=False))[0]


# -- the reference: struct over the registers put in big-endian byte order ----------------


def ordered_bytes(registers: list[int], fmt: DataFormat) -> bytes:
    """Registers as bytes in value order: word order reversed for CDAB/DCBA, each
    register's two bytes swapped for BADC/DCBA."""
    words = registers[::-1] if fmt.word_swap else registers
    return b"".join(struct.pack("<H" if fmt.byte_swap else ">H", w) for w in words)


def by_letters(registers: list[int], order: str) -> bytes:
    """The value's bytes, most significant first, from registers whose bytes (by address)
    are the value's bytes named by ``order`` (``"CDAB"``: the first register holds C D)."""
    wire = b"".join(struct.pack(">H", r) for r in registers)
    value = bytearray(len(wire))
    for at, letter in enumerate(order):
        value[ord(letter) - ord("A")] = wire[at]
    return bytes(value)


def value_bytes(spec: ValueSpec, registers: list[int], width: int) -> bytes:
    """The bytes of a value of ``width`` registers read from the item's registers
    (docs/device-files.md "Byte order"): one register is the register, byte-swapped only with
    byte_swap16; two follow dataFormat; four dataFormat64 (default: dataFormat's
    letters stretched, ABCD -> ABCDEFGH, CDAB -> GHEFCDAB).  An item with more registers
    than the value keeps it in the first ones by address, the last under CDAB/DCBA."""
    fmt = spec.data_format
    q = len(registers)
    start = q - width if fmt.word_swap and q > width else 0
    regs = registers[start : start + width]
    if width == 1:
        return by_letters(regs, "BA" if spec.byte_swap16 else "AB")
    if width == 2:
        return by_letters(regs, fmt.value)
    if spec.data_format64 is not None:
        order = spec.data_format64.value
    else:
        order = {"ABCD": "ABCDEFGH", "BADC": "BADCFEHG", "CDAB": "GHEFCDAB",
                 "DCBA": "HGFEDCBA"}[fmt.value]
    return by_letters(regs, order)


# type -> [(registers, how to read them)] widest first: the Smart Cast table (NG), in
# which an item of q registers is read with the widest entry that fits in q.
I64, U64, I32, U32, I16, U16 = ">q", ">Q", ">i", ">I", ">h", ">H"
REFERENCE: dict[DataType, list[tuple[int, str]]] = {
    T.INT16: [(4, I64), (2, I32), (1, I16)],
    T.UINT16: [(4, U64), (2, U32), (1, U16)],
    T.INT24: [(4, I64), (2, "i24"), (1, I16)],
    T.UINT24: [(4, U64), (2, "u24"), (1, U16)],
    T.INT32: [(4, I64), (2, I32), (1, I16)],
    T.UINT32: [(4, U64), (2, U32), (1, U16)],
    T.INT64: [(4, I64), (2, I32), (1, I16)],
    T.UINT64: [(4, U64), (2, U32), (1, U16)],
    T.FLOAT: [(4, ">d"), (2, ">f"), (1, I16)],
    T.DOUBLE: [(4, ">d"), (2, ">f"), (1, I16)],
    T.BYTE: [(4, U64), (2, U32), (1, "low")],
    T.SBYTE: [(4, I64), (2, I32), (1, "slow")],
}
# the types' ranges, written out (not taken from the package)
RANGE: dict[DataType, tuple[int, int]] = {
    T.INT16: (-32768, 32767),
    T.UINT16: (0, 65535),
    T.INT24: (-8388608, 8388607),
    T.UINT24: (0, 16777215),
    T.INT32: (-(2**31), 2**31 - 1),
    T.UINT32: (0, 2**32 - 1),
    T.BYTE: (0, 255),
    T.SBYTE: (-128, 127),
}
FLT_MAX = struct.unpack(">f", b"\x7f\x7f\xff\xff")[0]


def smart_value(t: DataType, data: bytes, code: str) -> object:
    """The value of ``data`` (the item's leading bytes in value order) read as ``code``
    and narrowed to ``t``: None when it does not fit."""
    if code in ("i24", "u24"):  # byte A (data[0]) unused: the low 3 bytes are the value
        value: object = int.from_bytes(data[1:4], "big", signed=code == "i24")
    elif code == "low":
        value = data[1]
    elif code == "slow":
        value = struct.unpack(">b", data[1:2])[0]
    else:
        (value,) = struct.unpack(code, data)
    if t in (T.FLOAT, T.DOUBLE):
        f = float(value)  # type: ignore[arg-type]
        return None if t is T.FLOAT and math.isfinite(f) and abs(f) > FLT_MAX else f
    lo, hi = RANGE.get(t, (-(2**63), 2**64))
    return value if lo <= value <= hi else None  # type: ignore[operator]


def reference(spec: ValueSpec, registers: list[int]) -> object:
    t, fmt = spec.data_type, spec.data_format
    quantity = spec.quantity or t.registers
    if t in REFERENCE:
        # the widest value that fits in q registers; whatever else is ignored (NG's
        # Smart Cast)
        width, code = next((w, c) for w, c in REFERENCE[t] if w <= quantity)
        return smart_value(t, value_bytes(spec, registers, width), code)
    if t is T.CHAR:
        return chr(value_bytes(spec, registers[:1], 1)[1])
    if t is T.BOOLEAN:
        return registers[0] != 0
    if t is T.STRING:
        return ordered_bytes(registers[:quantity], fmt).rstrip(b"\0").decode("utf-8", "replace")
    if t is T.BINARY:
        return ordered_bytes(registers[:quantity], fmt)
    if t in (T.DATETIME, T.TIMESTAMP):
        if quantity >= 4:
            (ms,) = struct.unpack(">q", value_bytes(spec, registers, 4))
        else:
            ms = struct.unpack(">I", value_bytes(spec, registers, 2))[0] * 1000
        if t is T.TIMESTAMP:
            return ms
        try:
            return EPOCH + dt.timedelta(milliseconds=ms)
        except OverflowError:
            return None
    if t in (T.BCD16, T.BCD32):
        digits = value_bytes(spec, registers, 1 if quantity < 2 else 2).hex()
        if not digits.isdigit():
            return None
        return int(digits) if t is T.BCD32 or int(digits) <= 9999 else None
    raise AssertionError(t)


def same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return struct.pack(">d", a) == struct.pack(">d", b) or (math.isnan(a) and math.isnan(b))
    return type(a) is type(b) and a == b


def _spec(t: DataType, f: DataFormat, q: int | None, s16: bool,
          f64: DataFormat64 | None) -> ValueSpec:
    return ValueSpec("x", t, f, quantity=q, byte_swap16=s16, data_format64=f64)


SPECS = st.one_of(
    st.builds(
        _spec,
        st.sampled_from([*REFERENCE, T.BCD16, T.BCD32]),
        FORMATS,
        st.one_of(st.none(), st.integers(1, 6)),
        SWAP16,
        FORMATS64,
    ),
    st.builds(
        _spec, st.sampled_from([T.CHAR, T.BOOLEAN]), FORMATS, st.none(), SWAP16, FORMATS64
    ),
    st.builds(
        _spec,
        st.sampled_from([T.STRING, T.BINARY]),
        FORMATS,
        st.integers(1, 12),
        SWAP16,
        FORMATS64,
    ),
    st.builds(
        _spec,
        st.sampled_from([T.DATETIME, T.TIMESTAMP]),
        FORMATS,
        st.one_of(st.none(), st.integers(2, 5)),
        SWAP16,
        FORMATS64,
    ),
)


@settings(max_examples=1000, deadline=None)
@given(spec=SPECS, data=st.data())
def test_decode_agrees_with_a_struct_reference(spec: ValueSpec, data: st.DataObject) -> None:
    registers = data.draw(st.lists(REGISTER, min_size=spec.registers, max_size=spec.registers))
    assert same(decode_one(spec, registers), reference(spec, registers))


@settings(max_examples=600, deadline=None)
@given(spec=SPECS, data=st.data())
def test_encode_agrees_with_the_struct_reference(spec: ValueSpec, data: st.DataObject) -> None:
    """Writes are the exact inverse: the registers a value is written as read back, by
    the reference, as that value (every order, 16-bit swap and 64-bit order)."""
    registers = data.draw(st.lists(REGISTER, min_size=spec.registers, max_size=spec.registers))
    value = reference(spec, registers)
    if value is None or spec.data_type in (T.STRING, T.BOOLEAN):
        return  # not a value (Invalid), or not one-to-one with its registers
    written = encode(spec, value)
    assert len(written) == spec.registers
    assert same(reference(spec, written), value)
    assert same(decode_one(spec, written), value)


# -- encode then decode ------------------------------------------------------------------------

MULTIPLIERS = st.sampled_from([1.0, 0.1, 0.01, 0.001, 0.5, 2.0, 10.0, -1.0, 0.25, 1.5])
INTEGER_TYPES = [
    T.INT16,
    T.UINT16,
    T.INT24,
    T.UINT24,
    T.INT32,
    T.UINT32,
    T.INT64,
    T.UINT64,
    T.BYTE,
    T.SBYTE,
    T.BCD16,
    T.BCD32,
]


@settings(max_examples=600, deadline=None)
@given(t=st.sampled_from(INTEGER_TYPES), fmt=FORMATS, m=MULTIPLIERS, s16=SWAP16, f64=FORMATS64,
       data=st.data())
def test_integer_round_trip(t: DataType, fmt: DataFormat, m: float, s16: bool,
                            f64: DataFormat64 | None, data: st.DataObject) -> None:
    lo, hi = t.integer_range
    if m != 1:  # a scaled value is a double: keep raw where doubles are exact
        lo, hi = max(lo, -(2**50)), min(hi, 2**50)
    raw = data.draw(st.integers(lo, hi))
    spec = ValueSpec("x", t, fmt, multiplier=m, byte_swap16=s16, data_format64=f64)
    # What a reader sees: the raw integer, or raw x multiplier as a float (raw / 10 for 0.1).
    if m == 1:
        value: object = raw
    else:
        k = round(1 / m)
        value = raw / k if abs(m) < 1 and 1 / k == m else raw * m
    registers = encode(spec, value)
    assert len(registers) == t.registers
    decoded = decode_one(spec, registers)
    assert same(decoded, value)
    assert encode(spec, decoded) == registers
    assert same(reference(spec, registers), raw)  # and what the reference reads


@settings(max_examples=400, deadline=None)
@given(
    t=st.sampled_from([T.FLOAT, T.DOUBLE]),
    fmt=FORMATS,
    m=MULTIPLIERS,
    f=st.floats(width=32, allow_nan=False, allow_infinity=True),
    f64=FORMATS64,
)
def test_float_round_trip(
    t: DataType, fmt: DataFormat, m: float, f: float, f64: DataFormat64 | None
) -> None:
    spec = ValueSpec("x", t, fmt, multiplier=m, data_format64=f64)
    k = round(1 / m)
    value = f / k if m != 1 and abs(m) < 1 and 1 / k == m else f * m
    decoded = decode_one(spec, encode(spec, value))
    if t is T.DOUBLE and m != 1 and math.isfinite(value):
        assert math.isclose(decoded, value, rel_tol=1e-15)  # type: ignore[arg-type]
    else:
        assert same(decoded, value)


@settings(max_examples=200, deadline=None)
@given(fmt=FORMATS, f=st.floats(allow_nan=True), f64=FORMATS64)
def test_double_bits_round_trip(fmt: DataFormat, f: float, f64: DataFormat64 | None) -> None:
    spec = ValueSpec("x", T.DOUBLE, fmt, data_format64=f64)
    registers = encode(spec, f)
    assert same(decode_one(spec, registers), f)
    assert same(reference(spec, registers), f)


@settings(max_examples=300, deadline=None)
@given(
    fmt=FORMATS,
    q=st.integers(1, 16),
    text=st.text(st.characters(blacklist_categories=("Cs",)), max_size=12),
    encoding=st.sampled_from(["utf-8", "gbk", "ascii"]),
)
def test_string_round_trip(fmt: DataFormat, q: int, text: str, encoding: str) -> None:
    spec = ValueSpec("s", T.STRING, fmt, quantity=q, encoding=encoding)
    text = text.encode(encoding, "ignore").rstrip(b"\0").decode(encoding)  # what it can carry
    while len(text.encode(encoding)) > 2 * q:
        text = text[:-1].rstrip("\0")
    assert decode_one(spec, encode(spec, text)) == text


@settings(max_examples=200, deadline=None)
@given(fmt=FORMATS, s16=SWAP16, data=st.data())
def test_binary_char_bool_round_trip(fmt: DataFormat, s16: bool, data: st.DataObject) -> None:
    q = data.draw(st.integers(1, 10))
    blob = data.draw(st.binary(min_size=2 * q, max_size=2 * q))
    assert (
        decode_one(
            ValueSpec("b", T.BINARY, fmt, quantity=q),
            encode(ValueSpec("b", T.BINARY, fmt, quantity=q), blob),
        )
        == blob
    )
    ch = chr(data.draw(st.integers(0, 255)))
    char = ValueSpec("c", T.CHAR, fmt, byte_swap16=s16)
    assert decode_one(char, encode(char, ch)) == ch
    flag = data.draw(st.booleans())
    flag_spec = ValueSpec("f", T.BOOLEAN, fmt)
    assert decode_one(flag_spec, encode(flag_spec, flag)) is flag


@settings(max_examples=300, deadline=None)
@given(fmt=FORMATS, q=st.sampled_from([2, 4]), f64=FORMATS64, data=st.data())
def test_time_round_trip(
    fmt: DataFormat, q: int, f64: DataFormat64 | None, data: st.DataObject
) -> None:
    if q == 2:
        ms = data.draw(st.integers(0, 0xFFFF_FFFF)) * 1000
    else:
        ms = data.draw(st.integers(-62135596800000, 253402300799999))
    when = EPOCH + dt.timedelta(milliseconds=ms)
    stamp = ValueSpec("t", T.TIMESTAMP, fmt, quantity=q, data_format64=f64)
    assert decode_one(stamp, encode(stamp, ms)) == ms
    assert reference(stamp, encode(stamp, ms)) == ms
    date = ValueSpec("t", T.DATETIME, fmt, quantity=q, data_format64=f64)
    assert decode_one(date, encode(date, when)) == when
