"""Smart Cast (NG) with quantities larger and smaller than the type, and Int24/UInt24:
the C codec against an independent encoder/decoder written here with struct."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ValueSpec, encode, smart_cast
from edgemodbus.datatypes import Area, DataFormat, DataType

T = DataType
F = DataFormat
FORMATS = st.sampled_from(list(DataFormat))


def decode_one(spec: ValueSpec, registers: list[int]) -> object:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, len(registers), [(0, spec)])
    return decoder.decode_values(Block.from_values(registers, bits=False))[0]


def registers_of(data: bytes, fmt: DataFormat) -> list[int]:
    """Bytes in value order (most significant first) -> registers by address: the
    inverse of the format (byte swap inside each register, word order reversed)."""
    words = [struct.unpack("<H" if fmt.byte_swap else ">H", data[k : k + 2])[0]
             for k in range(0, len(data), 2)]
    return words[::-1] if fmt.word_swap else words


# -- Int24 / UInt24: the byte layout per format ---------------------------------------------


@pytest.mark.parametrize(
    ("fmt", "registers"),
    [
        (F.ABCD, [0x0012, 0x3456]),  # byte A = high byte of register 0
        (F.BADC, [0x1200, 0x5634]),  # low byte of register 0
        (F.CDAB, [0x3456, 0x0012]),  # high byte of register 1
        (F.DCBA, [0x5634, 0x1200]),  # low byte of register 1
    ],
)
def test_int24_layout_per_byte_order(fmt: DataFormat, registers: list[int]) -> None:
    for t in (T.INT24, T.UINT24):
        spec = ValueSpec("x", t, fmt)
        assert spec.registers == 2
        assert encode(spec, 0x123456) == registers
        assert decode_one(spec, registers) == 0x123456
        # the unused byte A is ignored when read
        dirty = list(registers)
        a_reg, a_high = {F.ABCD: (0, True), F.BADC: (0, False),
                         F.CDAB: (1, True), F.DCBA: (1, False)}[fmt]
        dirty[a_reg] |= 0xAB00 if a_high else 0x00AB
        assert decode_one(spec, dirty) == 0x123456


def test_int24_sign_and_range() -> None:
    s = ValueSpec("x", T.INT24)
    assert encode(s, -2) == [0x00FF, 0xFFFE]
    assert decode_one(s, [0x00FF, 0xFFFE]) == -2
    assert decode_one(s, [0x0080, 0x0000]) == -8388608
    assert decode_one(ValueSpec("x", T.UINT24), [0x0080, 0x0000]) == 0x800000
    with pytest.raises(ValueError, match=r"-8388608\.\.8388607"):
        encode(s, 8388608)
    with pytest.raises(ValueError, match=r"0\.\.16777215"):
        encode(ValueSpec("x", T.UINT24), -1)


@settings(max_examples=400, deadline=None)
@given(signed=st.booleans(), fmt=FORMATS, data=st.data())
def test_int24_against_struct(signed: bool, fmt: DataFormat, data: st.DataObject) -> None:
    t = T.INT24 if signed else T.UINT24
    lo, hi = (-(2**23), 2**23 - 1) if signed else (0, 2**24 - 1)
    value = data.draw(st.integers(lo, hi))
    spec = ValueSpec("x", t, fmt)
    # independent: the 24-bit two's complement in bytes B C D after a zero byte A
    expected = registers_of(b"\0" + (value & 0xFFFFFF).to_bytes(3, "big"), fmt)
    assert encode(spec, value) == expected
    assert decode_one(spec, expected) == value
    a = data.draw(st.integers(0, 255))
    raw = registers_of(bytes([a]) + (value & 0xFFFFFF).to_bytes(3, "big"), fmt)
    assert decode_one(spec, raw) == value


# -- quantities larger and smaller than the type -------------------------------------------

# (type, signed, range) of the integer types Smart Cast narrows or widens
INTS = {
    T.INT16: (True, -(2**15), 2**15 - 1),
    T.UINT16: (False, 0, 2**16 - 1),
    T.INT24: (True, -(2**23), 2**23 - 1),
    T.UINT24: (False, 0, 2**24 - 1),
    T.INT32: (True, -(2**31), 2**31 - 1),
    T.UINT32: (False, 0, 2**32 - 1),
    T.INT64: (True, -(2**63), 2**63 - 1),
    T.UINT64: (False, 0, 2**64 - 1),
}


def reference_encode(t: DataType, q: int, fmt: DataFormat, value: int) -> list[int]:
    """NG's write: the value as an integer of the widest of 4/2/1 registers that fits in
    q (two's complement), then zero registers up to q, all in value order."""
    signed = INTS[t][0]
    width = 4 if q >= 4 else 2 if q >= 2 else 1
    if t in (T.INT24, T.UINT24) and width == 2:
        data = b"\0" + (value & 0xFFFFFF).to_bytes(3, "big")
    else:
        data = value.to_bytes(2 * width, "big", signed=signed)
    # a one-register value is the register whatever the format says (DESIGN)
    return registers_of(data + bytes(2 * (q - width)), fmt if width > 1 else F.ABCD)


@settings(max_examples=600, deadline=None)
@given(t=st.sampled_from(list(INTS)), fmt=FORMATS, q=st.integers(1, 7), data=st.data())
def test_integer_smart_cast_round_trip(
    t: DataType, fmt: DataFormat, q: int, data: st.DataObject
) -> None:
    signed, lo, hi = INTS[t]
    width = 4 if q >= 4 else 2 if q >= 2 else 1
    bits = 24 if t in (T.INT24, T.UINT24) and width == 2 else 16 * width
    # what fits both the type and the registers read
    lo = max(lo, -(2 ** (bits - 1)) if signed else 0)
    hi = min(hi, 2 ** (bits - 1) - 1 if signed else 2**bits - 1)
    value = data.draw(st.integers(lo, hi))
    spec = ValueSpec("x", t, fmt, quantity=q)
    registers = encode(spec, value)
    assert registers == reference_encode(t, q, fmt, value)
    assert decode_one(spec, registers) == value


def test_narrowing_refuses_values_the_type_cannot_hold() -> None:
    spec = ValueSpec("x", T.INT16, quantity=4)
    assert decode_one(spec, [0, 0, 1, 0]) is None  # 65536 does not fit an Int16
    with pytest.raises(ValueError, match=r"-32768\.\.32767 \(Int16 on the device\)"):
        encode(spec, 40000)
    f = ValueSpec("x", T.FLOAT, quantity=4)
    assert decode_one(f, registers_of(struct.pack(">d", 1.5), F.ABCD)) == 1.5
    assert decode_one(f, registers_of(struct.pack(">d", 1e300), F.ABCD)) is None
    assert encode(f, 2.25) == registers_of(struct.pack(">d", 2.25), F.ABCD)
    with pytest.raises(ValueError, match="Float on the device"):
        encode(f, 1e300)


def test_smart_cast_describes_what_it_does() -> None:
    assert smart_cast(ValueSpec("x", T.INT16)) is None
    assert smart_cast(ValueSpec("x", T.INT16, quantity=1)) is None
    assert smart_cast(ValueSpec("x", T.INT16, quantity=4)) == (
        "Int16 from 4 registers: read as Int64 and narrowed to Int16 "
        "(a value outside -32768..32767 makes the item Invalid)"
    )
    assert smart_cast(ValueSpec("x", T.FLOAT, quantity=1)) == (
        "Float from 1 register: read as Int16 and widened to Float"
    )
    assert smart_cast(ValueSpec("x", T.INT32, F.CDAB, quantity=3)) == (
        "Int32 from 3 registers: read as Int32; register +0 of the item is ignored "
        "when read and written as 0"
    )
