"""Known vectors, Smart Cast, conversions, errors and change detection of the C codec."""

from __future__ import annotations

import datetime as dt
import math

import pytest

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ValueSpec, check_spec, encode, register_bit
from edgemodbus.datatypes import Area, DataFormat, DataType

HR = Area.HOLDING_REGISTER
T = DataType
F = DataFormat
UTC = dt.timezone.utc


def regs(*values: int) -> Block:
    return Block.from_values(list(values), bits=False)


def one(spec: ValueSpec, *registers: int) -> object:
    """Decode a single item sitting at offset 0 of a block holding ``registers``."""
    decoder = BlockDecoder(HR, len(registers), [(0, spec)])
    return decoder.decode_values(regs(*registers))[0]


def reason(spec: ValueSpec, *registers: int) -> str | None:
    decoder = BlockDecoder(HR, len(registers), [(0, spec)])
    [(index, value, why)] = decoder.decode(regs(*registers), report_all=True)
    assert index == 0
    if why is not None:
        assert value is None
    return why


# -- byte and word order: the registers a device sends, written out literally -----------

FLOAT_123456 = {  # 123456.0 = 0x47F12000
    F.ABCD: (0x47F1, 0x2000),
    F.BADC: (0xF147, 0x0020),
    F.CDAB: (0x2000, 0x47F1),
    F.DCBA: (0x0020, 0xF147),
}
INT32_M123456 = {  # -123456 = 0xFFFE1DC0
    F.ABCD: (0xFFFE, 0x1DC0),
    F.BADC: (0xFEFF, 0xC01D),
    F.CDAB: (0x1DC0, 0xFFFE),
    F.DCBA: (0xC01D, 0xFEFF),
}
DOUBLE_123456_789 = {  # 0x40FE240C9FBE76C9: ABCDEFGH, BADCFEHG, GHEFCDAB, HGFEDCBA
    F.ABCD: (0x40FE, 0x240C, 0x9FBE, 0x76C9),
    F.BADC: (0xFE40, 0x0C24, 0xBE9F, 0xC976),
    F.CDAB: (0x76C9, 0x9FBE, 0x240C, 0x40FE),
    F.DCBA: (0xC976, 0xBE9F, 0x0C24, 0xFE40),
}


@pytest.mark.parametrize("fmt", list(F))
def test_float32_in_every_format(fmt: DataFormat) -> None:
    spec = ValueSpec("f", T.FLOAT, fmt)
    assert one(spec, *FLOAT_123456[fmt]) == 123456.0
    assert encode(spec, 123456.0) == list(FLOAT_123456[fmt])


@pytest.mark.parametrize("fmt", list(F))
def test_int32_in_every_format(fmt: DataFormat) -> None:
    spec = ValueSpec("i", T.INT32, fmt)
    assert one(spec, *INT32_M123456[fmt]) == -123456
    assert encode(spec, -123456) == list(INT32_M123456[fmt])


@pytest.mark.parametrize("fmt", list(F))
def test_double_in_every_format(fmt: DataFormat) -> None:
    spec = ValueSpec("d", T.DOUBLE, fmt)
    assert one(spec, *DOUBLE_123456_789[fmt]) == 123456.789
    assert encode(spec, 123456.789) == list(DOUBLE_123456_789[fmt])


@pytest.mark.parametrize("fmt", list(F))
def test_int16_is_the_register_whatever_the_format(fmt: DataFormat) -> None:
    """DESIGN: a one-register value is the register, big-endian, whatever dataFormat says
    (BADC/DCBA used to swap it); only byte_swap16 swaps it."""
    assert one(ValueSpec("x", T.INT16, fmt), 0xFF85) == -123
    assert encode(ValueSpec("x", T.INT16, fmt), -123) == [0xFF85]
    assert one(ValueSpec("x", T.UINT16, fmt), 0x1234) == 0x1234
    swapped = ValueSpec("x", T.INT16, fmt, byte_swap16=True)
    assert one(swapped, 0x85FF) == -123
    assert encode(swapped, -123) == [0x85FF]


def test_64_bit_integers() -> None:
    # -1234567890123 = 0xFFFFFEE08E04FB35
    assert one(ValueSpec("x", T.INT64), 0xFFFF, 0xFEE0, 0x8E04, 0xFB35) == -1234567890123
    assert one(ValueSpec("x", T.INT64, F.CDAB), 0xFB35, 0x8E04, 0xFEE0, 0xFFFF) == -1234567890123
    assert one(ValueSpec("x", T.UINT64), 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE) == 2**64 - 2
    assert encode(ValueSpec("x", T.UINT64, F.DCBA), 2**64 - 2) == [0xFEFF, 0xFFFF, 0xFFFF, 0xFFFF]


# -- seed examples ----------------------------------------------------------------------


def test_seed_pump_speed_int16_times_0_1_as_float() -> None:
    spec = ValueSpec("PumpSpeed", T.INT16, multiplier=0.1, converted_type=T.FLOAT)
    assert one(spec, 255) == 25.5
    assert one(spec, 253) == 25.3  # raw / 10: the correctly rounded decimal, not 25.300000000000001
    assert one(spec, 0xFFF6) == -1.0
    assert encode(spec, 25.5) == [255]


def test_seed_energy_float_badc() -> None:
    spec = ValueSpec("Energy", T.FLOAT, F.BADC)
    # 1234.5 = 0x449A5000 -> BADC registers 0x9A44 0x0050
    assert one(spec, 0x9A44, 0x0050) == 1234.5
    assert encode(spec, 1234.5) == [0x9A44, 0x0050]


def test_multiplier_without_converted_type_gives_a_float() -> None:
    value = one(ValueSpec("x", T.UINT16, multiplier=2), 21)
    assert value == 42.0 and isinstance(value, float)
    value = one(ValueSpec("x", T.UINT16), 21)
    assert value == 21 and isinstance(value, int)


# -- Smart Cast and quantities ----------------------------------------------------------


def test_smart_cast_reads_the_smaller_type() -> None:
    assert one(ValueSpec("x", T.FLOAT, quantity=1, multiplier=0.1), 255) == 25.5
    assert one(ValueSpec("x", T.FLOAT, quantity=1), 0xFFFE) == -2.0
    assert one(ValueSpec("x", T.DOUBLE, quantity=2), *FLOAT_123456[F.ABCD]) == 123456.0
    assert one(ValueSpec("x", T.INT64, quantity=2), *INT32_M123456[F.CDAB][::-1]) == -123456
    assert one(ValueSpec("x", T.UINT64, quantity=2), 0xFFFF, 0xFFFE) == 0xFFFFFFFE
    assert one(ValueSpec("x", T.INT32, quantity=1), 0xFFFF) == -1
    assert one(ValueSpec("x", T.UINT32, quantity=1), 0xFFFF) == 0xFFFF
    assert one(ValueSpec("x", T.BCD32, quantity=1), 0x1234) == 1234
    assert encode(ValueSpec("x", T.INT64, quantity=2), -2) == [0xFFFF, 0xFFFE]
    assert encode(ValueSpec("x", T.DOUBLE, quantity=2), 123456.0) == [0x47F1, 0x2000]


def test_a_larger_quantity_reads_a_wider_value_and_narrows_it() -> None:
    """Smart Cast (NG): 4 registers are an Int64 narrowed to the type, range-checked;
    3 registers read the first 2 in format order (the last 2 by address under CDAB)."""
    spec = ValueSpec("x", T.INT32, F.CDAB, quantity=4)
    assert spec.registers == 4
    assert one(spec, 0x1DC0, 0xFFFE, 0xFFFF, 0xFFFF) == -123456
    assert one(spec, 0x1DC0, 0xFFFE, 0x1111, 0x2222) is None
    assert reason(spec, 0x1DC0, 0xFFFE, 0x1111, 0x2222) == (
        f"value {0x22221111FFFE1DC0} is out of range for Int32 (-2147483648..2147483647)"
    )
    assert encode(spec, -123456) == [0x1DC0, 0xFFFE, 0xFFFF, 0xFFFF]
    assert one(ValueSpec("x", T.INT16, quantity=4), 0xFFFF, 0xFFFF, 0xFFFF, 0xFFF9) == -7
    assert one(ValueSpec("x", T.INT16, quantity=3), 0, 7, 9) == 7
    assert encode(ValueSpec("x", T.INT16, quantity=3), 7) == [0, 7, 0]
    assert one(ValueSpec("x", T.INT32, F.CDAB, quantity=3), 9, 0x1DC0, 0xFFFE) == -123456
    assert encode(ValueSpec("x", T.INT32, F.CDAB, quantity=3), -123456) == [0, 0x1DC0, 0xFFFE]


# -- bits, bytes, chars -------------------------------------------------------------------


def test_coils_and_bits_of_registers() -> None:
    coils = BlockDecoder(
        Area.COIL, 3, [(0, ValueSpec("a", T.BOOLEAN)), (2, ValueSpec("b", T.BOOLEAN))]
    )
    assert coils.decode_values(Block.from_values([1, 0, 0], bits=True)) == [True, False]
    items = [(0, ValueSpec(f"b{k}", T.BOOLEAN, bit=k)) for k in (0, 3, 8, 15)]
    decoder = BlockDecoder(HR, 1, items)
    assert decoder.decode_values(regs(0b1000_0000_0000_1000)) == [False, True, False, True]
    swapped = [(0, ValueSpec(f"b{k}", T.BOOLEAN, F.BADC, bit=k, byte_swap16=True))
               for k in (0, 3, 8, 15)]
    decoder = BlockDecoder(HR, 1, swapped)  # bit of the value after the 16-bit swap
    assert decoder.decode_values(regs(0x0980)) == [True, True, False, True]
    plain = [(0, ValueSpec(f"b{k}", T.BOOLEAN, F.DCBA, bit=k)) for k in (0, 3, 8, 15)]
    decoder = BlockDecoder(HR, 1, plain)  # dataFormat does not move a register's bits
    assert decoder.decode_values(regs(0b1000_0000_0000_1000)) == [False, True, False, True]
    assert one(ValueSpec("x", T.BOOLEAN), 0x0100) is True
    assert one(ValueSpec("x", T.BOOLEAN), 0) is False


def test_bit_writes_target_the_wire_bit() -> None:
    spec = ValueSpec("b", T.BOOLEAN, bit=3)
    assert encode(spec, True) == [1]
    assert register_bit(spec) == 3
    assert register_bit(ValueSpec("b", T.BOOLEAN, F.BADC, bit=3, byte_swap16=True)) == 11
    assert register_bit(ValueSpec("b", T.BOOLEAN, bit=12, byte_swap16=True)) == 4
    assert register_bit(ValueSpec("b", T.BOOLEAN, F.DCBA, bit=12)) == 12
    with pytest.raises(ValueError, match="not a bit"):
        register_bit(ValueSpec("b", T.BOOLEAN))
    assert encode(ValueSpec("c", T.BOOLEAN), "false") == [0]


def test_byte_sbyte_char_take_the_low_byte_after_swap() -> None:
    assert one(ValueSpec("x", T.BYTE), 0x12FE) == 0xFE
    assert one(ValueSpec("x", T.SBYTE), 0x12FE) == -2
    assert one(ValueSpec("x", T.SBYTE, byte_swap16=True), 0xFE12) == -2
    assert one(ValueSpec("x", T.SBYTE, F.BADC), 0x12FE) == -2
    assert one(ValueSpec("x", T.CHAR), 0x0041) == "A"
    assert one(ValueSpec("x", T.CHAR, byte_swap16=True), 0x4100) == "A"
    assert one(ValueSpec("x", T.CHAR, F.BADC), 0x0041) == "A"
    assert encode(ValueSpec("x", T.CHAR), "A") == [0x41]
    assert encode(ValueSpec("x", T.CHAR, F.DCBA, byte_swap16=True), "A") == [0x4100]
    assert encode(ValueSpec("x", T.CHAR, F.DCBA), "A") == [0x41]
    assert encode(ValueSpec("x", T.SBYTE), -2) == [0xFE]


# -- strings and binary ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("fmt", "registers"),
    [
        (F.ABCD, (0x4865, 0x6C6C, 0x6F00, 0x0000)),
        (F.BADC, (0x6548, 0x6C6C, 0x006F, 0x0000)),
        (F.CDAB, (0x0000, 0x6F00, 0x6C6C, 0x4865)),
        (F.DCBA, (0x0000, 0x006F, 0x6C6C, 0x6548)),
    ],
)
def test_string_in_format_order(fmt: DataFormat, registers: tuple[int, ...]) -> None:
    spec = ValueSpec("s", T.STRING, fmt, quantity=4)
    assert one(spec, *registers) == "Hello"
    assert encode(spec, "Hello") == list(registers)


def test_strings_in_utf8_gbk_and_ascii() -> None:
    assert one(ValueSpec("s", T.STRING, quantity=2), 0xE4B8, 0xAD00) == "中"
    gbk = ValueSpec("s", T.STRING, quantity=3, encoding="gbk")
    assert one(gbk, 0xD6D0, 0xCEC4, 0x0000) == "中文"
    assert encode(gbk, "中文") == [0xD6D0, 0xCEC4, 0x0000]
    ascii_ = ValueSpec("s", T.STRING, quantity=1, encoding="ascii")
    assert one(ascii_, 0x4F4B) == "OK"


def test_invalid_bytes_are_replaced_and_only_trailing_nuls_stripped() -> None:
    assert one(ValueSpec("s", T.STRING, quantity=2), 0x41FF, 0x0000) == "A\ufffd"
    assert one(ValueSpec("s", T.STRING, quantity=2, encoding="ascii"), 0x41C3, 0x0000) == "A\ufffd"
    assert one(ValueSpec("s", T.STRING, quantity=2), 0x4100, 0x4200) == "A\x00B"
    assert one(ValueSpec("s", T.STRING, quantity=2), 0, 0) == ""


def test_binary_is_raw_bytes() -> None:
    spec = ValueSpec("b", T.BINARY, F.BADC, quantity=2)
    assert one(spec, 0x0201, 0x0004) == b"\x01\x02\x04\x00"
    assert encode(spec, b"\x01\x02\x04") == [0x0201, 0x0004]


# -- time, BCD ----------------------------------------------------------------------------------


def test_datetime_and_timestamp() -> None:
    # 1700000000 s = 0x6553F100 = 2023-11-14T22:13:20Z
    when = dt.datetime(2023, 11, 14, 22, 13, 20, tzinfo=UTC)
    assert one(ValueSpec("t", T.DATETIME), 0x6553, 0xF100) == when
    assert one(ValueSpec("t", T.TIMESTAMP), 0x6553, 0xF100) == 1_700_000_000_000
    ms = 1_700_000_000_123  # 0x18BCFE5687B
    assert one(ValueSpec("t", T.TIMESTAMP, quantity=4), 0, 0x018B, 0xCFE5, 0x687B) == ms
    value = one(ValueSpec("t", T.DATETIME, quantity=4), 0, 0x018B, 0xCFE5, 0x687B)
    assert value == when + dt.timedelta(milliseconds=123)
    assert isinstance(value, dt.datetime) and value.tzinfo is not None
    assert encode(ValueSpec("t", T.DATETIME, F.CDAB), when) == [0xF100, 0x6553]
    assert encode(ValueSpec("t", T.TIMESTAMP, quantity=4), ms) == [0, 0x018B, 0xCFE5, 0x687B]
    assert encode(ValueSpec("t", T.DATETIME), when.replace(tzinfo=None)) == [0x6553, 0xF100]


def test_datetime_out_of_python_range_is_an_item_error() -> None:
    why = reason(ValueSpec("t", T.DATETIME, quantity=4), 0x7FFF, 0xFFFF, 0xFFFF, 0xFFFF)
    assert why is not None and "9999" in why


def test_bcd() -> None:
    assert one(ValueSpec("b", T.BCD16), 0x1234) == 1234
    assert one(ValueSpec("b", T.BCD32), 0x1234, 0x5678) == 12345678
    assert one(ValueSpec("b", T.BCD32, F.CDAB), 0x5678, 0x1234) == 12345678
    assert encode(ValueSpec("b", T.BCD32), 12345678) == [0x1234, 0x5678]
    assert encode(ValueSpec("b", T.BCD16, F.BADC), 1234) == [0x1234]
    assert encode(ValueSpec("b", T.BCD16, byte_swap16=True), 1234) == [0x3412]
    why = reason(ValueSpec("b", T.BCD16), 0x12A4)
    assert why is not None and "0x12A4" in why and "BCD" in why


# -- converted types and multiplier ------------------------------------------------------------


def test_conversion_to_integer_rounds_half_to_even() -> None:
    spec = ValueSpec("x", T.INT16, multiplier=0.1, converted_type=T.INT32)
    assert [one(spec, r) for r in (25, 35, 0xFFE7, 26)] == [2, 4, -2, 3]
    assert one(ValueSpec("x", T.FLOAT, converted_type=T.INT16), 0x3FC0, 0) == 2  # 1.5 -> 2


def test_conversion_out_of_range_is_an_item_error_not_a_wrap() -> None:
    why = reason(ValueSpec("x", T.UINT16, converted_type=T.SBYTE), 200)
    assert why == "value 200 is out of range for Sbyte (-128..127)"
    why = reason(ValueSpec("x", T.INT16, converted_type=T.UINT16), 0xFFFF)
    assert why == "value -1 is out of range for UInt16 (0..65535)"
    why = reason(ValueSpec("x", T.FLOAT, converted_type=T.INT32), 0x7FC0, 0)  # NaN
    assert why == "NaN cannot be converted to Int32"
    why = reason(ValueSpec("x", T.DOUBLE, converted_type=T.FLOAT), 0x47F0, 0, 0, 0)  # 2**128
    assert why is not None and "out of range for Float" in why
    why = reason(ValueSpec("x", T.UINT64, converted_type=T.INT64), 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF)
    assert why is not None and "out of range for Int64" in why


def test_conversion_to_boolean_string_and_float() -> None:
    assert one(ValueSpec("x", T.INT16, converted_type=T.BOOLEAN), 7) is True
    assert one(ValueSpec("x", T.INT16, converted_type=T.BOOLEAN), 0) is False
    assert one(ValueSpec("x", T.INT16, multiplier=0.5, converted_type=T.STRING), 5) == "2.5"
    assert one(ValueSpec("x", T.INT16, converted_type=T.STRING), 0xFFFF) == "-1"
    assert one(ValueSpec("x", T.BOOLEAN, converted_type=T.INT16), 4) == 1
    value = one(ValueSpec("x", T.INT32, converted_type=T.DOUBLE), 0, 3)
    assert value == 3.0 and isinstance(value, float)


# -- encode: inverse of multiplier and conversion, and its errors ------------------------------


def test_encode_divides_by_the_multiplier_in_decimal() -> None:
    spec = ValueSpec("x", T.INT16, multiplier=0.1)
    assert encode(spec, 12.5) == [125]
    assert encode(spec, 0.35) == [4]  # 3.5 rounds half to even -> 4, not 3.4999... -> 3
    assert encode(spec, 0.25) == [2]  # 2.5 -> 2
    assert encode(spec, -0.1) == [0xFFFF]
    assert encode(ValueSpec("x", T.INT16, multiplier=0.1, converted_type=T.STRING), "12.5") == [125]
    assert encode(ValueSpec("x", T.UINT16, multiplier=0.01), 655.35) == [65535]
    assert encode(ValueSpec("x", T.FLOAT, multiplier=0.1), 2.5) == [0x41C8, 0]  # 25.0
    assert encode(ValueSpec("x", T.INT16), True) == [1]


@pytest.mark.parametrize(
    ("spec", "value", "fragment"),
    [
        (ValueSpec("PumpSpeed", T.INT16, multiplier=0.1), 3276.8, "-3276.8..3276.7"),
        (ValueSpec("Count", T.UINT16), -1, "0..65535"),
        (ValueSpec("Count", T.UINT32), 2**32, "0..4294967295"),
        (ValueSpec("Level", T.INT32), math.nan, "-2147483648..2147483647"),
        (ValueSpec("Level", T.INT16, multiplier=0.1), math.inf, "-3276.8..3276.7"),
        (ValueSpec("Tag", T.STRING, quantity=2), "hello", "at most 4 bytes"),
        (ValueSpec("Tag", T.STRING, quantity=2, encoding="ascii"), "中", "ascii"),
        (ValueSpec("Blob", T.BINARY, quantity=1), b"abc", "at most 2 bytes"),
        (ValueSpec("Bcd", T.BCD16), 10000, "0..9999"),
        (ValueSpec("Bcd", T.BCD32), -1, "0..99999999"),
        (ValueSpec("Temp", T.FLOAT), 1e39, "Float"),
        (ValueSpec("Small", T.INT64, quantity=2), 2**31, "-2147483648..2147483647"),
        (ValueSpec("Letter", T.CHAR), "AB", "one character"),
        (ValueSpec("When", T.DATETIME), 5, "datetime"),
        (ValueSpec("When", T.DATETIME), dt.datetime(1969, 1, 1, tzinfo=UTC), "uint32 seconds"),
        (ValueSpec("Count", T.INT16), "12", "a number"),
        (ValueSpec("Flag", T.BOOLEAN), "maybe", "true/false"),
    ],
)
def test_encode_errors_name_item_value_and_range(
    spec: ValueSpec, value: object, fragment: str
) -> None:
    with pytest.raises(ValueError) as info:
        encode(spec, value)
    text = str(info.value)
    assert repr(spec.name) in text and repr(value) in text and fragment in text


def test_coil_encode() -> None:
    assert encode(ValueSpec("c", T.BOOLEAN), True) == [1]
    assert encode(ValueSpec("c", T.BOOLEAN), 0) == [0]


# -- spec validation ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "area", "fragment"),
    [
        (ValueSpec("a", T.INT16), Area.COIL, "Boolean"),
        (ValueSpec("a", T.BOOLEAN, quantity=2), Area.DISCRETE_INPUT, "quantity"),
        (ValueSpec("a", T.BOOLEAN, bit=1), Area.COIL, "bit"),
        (ValueSpec("a", T.STRING), HR, "quantity"),
        (ValueSpec("a", T.BINARY), HR, "quantity"),
        (ValueSpec("a", T.INT16, bit=3), HR, "Boolean"),
        (ValueSpec("a", T.BOOLEAN, bit=16), HR, "0..15"),
        (ValueSpec("a", T.INT16, quantity=0), HR, "1..125"),
        (ValueSpec("a", T.STRING, quantity=126), HR, "1..125"),
        (ValueSpec("a", T.DATETIME, quantity=1), HR, "2 (seconds) or 4"),
        (ValueSpec("a", T.INT16, multiplier=0), HR, "dataMultiplier"),
        (ValueSpec("a", T.INT16, multiplier=math.nan), HR, "dataMultiplier"),
        (ValueSpec("a", T.STRING, quantity=2, multiplier=2), HR, "multiplier"),
        (ValueSpec("a", T.STRING, quantity=2, converted_type=T.INT16), HR, "convertedDataType"),
        (ValueSpec("a", T.INT16, converted_type=T.DATETIME), HR, "convertedDataType"),
        (ValueSpec("a", T.INT16, deadband=-1), HR, "deadband"),
        (ValueSpec("a", T.STRING, quantity=2, encoding="klingon"), HR, "encoding"),
        (ValueSpec("a", T.STRING, quantity=2, encoding="base64"), HR, "text encoding"),
    ],
)
def test_check_spec_rejects(spec: ValueSpec, area: Area, fragment: str) -> None:
    with pytest.raises(ValueError) as info:
        check_spec(spec, area)
    assert "'a'" in str(info.value) and fragment in str(info.value)


def test_decoder_rejects_items_outside_the_planned_block() -> None:
    with pytest.raises(ValueError, match=r"'late'.*outside the block of 4 registers"):
        BlockDecoder(HR, 4, [(3, ValueSpec("late", T.INT32))])
    with pytest.raises(ValueError, match="expects registers"):
        BlockDecoder(HR, 1, [(0, ValueSpec("x", T.INT16))]).decode_values(
            Block.from_values([1], bits=True)
        )


def test_registers_property() -> None:
    assert ValueSpec("a", T.DOUBLE).registers == 4
    assert ValueSpec("a", T.DOUBLE, quantity=2).registers == 2
    assert ValueSpec("a", T.BOOLEAN, bit=4).registers == 1
    assert ValueSpec("a", T.STRING, quantity=7).registers == 7
    assert ValueSpec("a", T.DATETIME).registers == 2


# -- change detection, deadband, short responses -------------------------------------------------


def _decoder() -> BlockDecoder:
    return BlockDecoder(
        HR,
        6,
        [
            (0, ValueSpec("t", T.INT16, multiplier=0.1, deadband=0.5)),
            (1, ValueSpec("f", T.FLOAT)),
            (3, ValueSpec("s", T.STRING, quantity=2)),
            (5, ValueSpec("b", T.BOOLEAN, bit=0)),
        ],
    )


def test_first_decode_reports_everything_then_only_changes() -> None:
    d = _decoder()
    block = [100, 0x3F80, 0, 0x4142, 0, 1]
    assert d.decode(regs(*block)) == [
        (0, 10.0, None),
        (1, 1.0, None),
        (2, "AB", None),
        (3, True, None),
    ]
    assert d.decode(regs(*block)) == []
    block[4] = 0x4300
    assert d.decode(regs(*block)) == [(2, "ABC", None)]
    block[5] = 0
    block[2] = 1
    assert d.decode(regs(*block)) == [(1, 1.0000001192092896, None), (3, False, None)]
    assert d.decode(regs(*block), report_all=True) == [
        (0, 10.0, None),
        (1, 1.0000001192092896, None),
        (2, "ABC", None),
        (3, False, None),
    ]
    d.reset()
    assert len(d.decode(regs(*block))) == 4


def test_deadband_compares_with_the_last_reported_value() -> None:
    d = _decoder()
    base = [100, 0x3F80, 0, 0x4142, 0, 1]
    d.decode(regs(*base))
    for raw in (103, 105, 97):  # 10.3, 10.5, 9.7: within 0.5 of the reported 10.0
        assert d.decode(regs(raw, *base[1:])) == []
    assert d.decode(regs(106, *base[1:])) == [(0, 10.6, None)]  # creeping drift is caught
    assert d.decode(regs(102, *base[1:])) == []  # 0.4 from 10.6
    assert d.decode(regs(100, *base[1:])) == [(0, 10.0, None)]
    # report_all always carries the current value, even inside the deadband
    assert d.decode(regs(103, *base[1:]), report_all=True)[0] == (0, 10.3, None)
    assert d.decode(regs(103, *base[1:])) == []


def test_float_changes_compare_bits() -> None:
    d = BlockDecoder(HR, 2, [(0, ValueSpec("f", T.FLOAT))])
    nan = (0x7FC0, 0x0000)
    assert d.decode(regs(*nan))[0][0] == 0
    assert d.decode(regs(*nan)) == []  # NaN -> NaN is no change
    assert d.decode(regs(0, 0)) == [(0, 0.0, None)]
    negative_zero = d.decode(regs(0x8000, 0))
    assert len(negative_zero) == 1 and math.copysign(1.0, negative_zero[0][1]) == -1.0


def test_items_past_the_end_of_a_short_response() -> None:
    d = _decoder()
    full = [100, 0x3F80, 0, 0x4142, 0, 1]
    d.decode(regs(*full))
    short = regs(*full[:4])
    assert d.decode_values(short) == [10.0, 1.0, None, None]
    assert d.errors() == {2: "not in response", 3: "not in response"}
    assert d.decode(short) == [(2, None, "not in response"), (3, None, "not in response")]
    assert d.decode(short) == []  # the same error again is no change
    assert d.decode(regs(*full)) == [(2, "AB", None), (3, True, None)]  # recovery is reported
    assert d.decode_values(regs()) == [None, None, None, None]


def test_decode_values_does_not_touch_change_tracking() -> None:
    d = _decoder()
    block = [100, 0x3F80, 0, 0x4142, 0, 1]
    d.decode(regs(*block))
    assert d.decode_values(regs(200, *block[1:]))[0] == 20.0
    assert d.decode(regs(*block)) == []


def test_many_items_changing_take_the_bulk_path() -> None:
    items = [(k, ValueSpec(f"r{k}", T.UINT16, deadband=2)) for k in range(40)]
    d = BlockDecoder(HR, 40, items)
    assert len(d.decode(regs(*range(40)))) == 40
    moved = [k + (5 if k % 3 == 0 else 1) for k in range(40)]  # every 3rd moves past the deadband
    got = d.decode(regs(*moved))
    assert got == [(k, k + 5, None) for k in range(0, 40, 3)]
    everything = d.decode(regs(*moved), report_all=True)
    assert everything == [(k, moved[k], None) for k in range(40)]
    assert d.decode(regs(*moved)) == []


def test_coil_change_detection_and_returned_lists_are_copies() -> None:
    d = BlockDecoder(
        Area.DISCRETE_INPUT, 4, [(k, ValueSpec(f"di{k}", T.BOOLEAN)) for k in range(4)]
    )
    first = d.decode(Block.from_values([1, 0, 1, 0], bits=True), report_all=True)
    assert first == [(0, True, None), (1, False, None), (2, True, None), (3, False, None)]
    first.clear()  # the caller owns what it gets
    assert d.decode(Block.from_values([1, 1, 1, 0], bits=True)) == [(1, True, None)]
    assert d.decode(Block.from_values([1, 1, 1, 0], bits=True), report_all=True)[1] == (
        1,
        True,
        None,
    )


def test_block_from_values_checks_its_input() -> None:
    assert Block.from_values([0, 65535], bits=False).to_list() == [0, 65535]
    with pytest.raises(ValueError, match="register value 65536 at index 1"):
        Block.from_values([0, 65536], bits=False)
    with pytest.raises(ValueError, match="bit value 2 at index 0"):
        Block.from_values([2], bits=True)


# -- many items of one output kind: how a decoder finds one item's value -------------------


@pytest.mark.parametrize("changed", [0, 255, 256, 257, 1999])
def test_one_change_among_2000_coils_reports_that_coil(changed: int) -> None:
    """A block of 2000 coils (the most one request reads): past 256 items of a kind the
    plan keeps an item's slot in an array instead of a list (see CodecPlan)."""
    decoder = BlockDecoder(Area.COIL, 2000, [(k, ValueSpec(f"c{k}", T.BOOLEAN))
                                             for k in range(2000)])
    bits = [k % 3 == 0 for k in range(2000)]
    first = decoder.decode(Block.from_values([int(b) for b in bits], bits=True))
    assert first == [(k, b, None) for k, b in enumerate(bits)]
    bits[changed] = not bits[changed]
    again = decoder.decode(Block.from_values([int(b) for b in bits], bits=True))
    assert again == [(changed, bits[changed], None)]


def test_one_change_among_interleaved_kinds_reports_its_value() -> None:
    """Items of every output kind in turn, one changing at a time: each report carries the
    changed item's own value (integers, floats, bools and post-processed strings)."""
    kinds = [ValueSpec("i", T.INT16), ValueSpec("u", T.UINT16), ValueSpec("f", T.FLOAT),
             ValueSpec("b", T.BOOLEAN, bit=2), ValueSpec("s", T.STRING, quantity=2)]
    specs: list[tuple[int, ValueSpec]] = []
    offset = 0
    for k in range(60):
        spec = kinds[k % len(kinds)]
        specs.append((offset, spec))
        offset += spec.registers
    decoder = BlockDecoder(HR, offset, specs)
    registers = [0x4142] * offset
    decoder.decode(Block.from_values(registers, bits=False))
    for index, (at, spec) in enumerate(specs):
        registers[at] ^= 0x0004
        [(k, value, error)] = decoder.decode(Block.from_values(registers, bits=False))
        expected = decoder.decode_values(Block.from_values(registers, bits=False))[index]
        assert (k, value, error) == (index, expected, None)
        assert value == one(spec, *registers[at:at + spec.registers])
        registers[at] ^= 0x0004
        decoder.decode(Block.from_values(registers, bits=False))


def test_decoder_specs_are_the_items_specs_in_order() -> None:
    items = [(0, ValueSpec("a", T.INT16)), (1, ValueSpec("b", T.FLOAT)),
             (3, ValueSpec("a", T.INT16)), (4, ValueSpec("c", T.INT16))]
    assert BlockDecoder(HR, 5, items).specs == [spec for _, spec in items]
