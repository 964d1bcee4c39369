"""Change detection of the codec for items that stay Invalid, and for values that only
look different (NaN payloads, undecodable text) or that a double would round.

In reportMode "change" (BlockDecoder.decode without report_all) an item is reported when
its value, status or error reason changes; the reason names the value just read, as a
decode in reportMode "cycle" does.
"""

from __future__ import annotations

import datetime as dt
import math
import struct

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, Change, ValueSpec
from edgemodbus.datatypes import Area, DataType

HR = Area.HOLDING_REGISTER
T = DataType


def regs(*values: int) -> Block:
    return Block.from_values(list(values), bits=False)


def track(spec: ValueSpec, *steps: tuple[int, ...]) -> list[list[Change]]:
    """What a change-mode decoder of one item reports for each block of ``steps``."""
    decoder = BlockDecoder(HR, spec.registers, [(0, spec)])
    return [decoder.decode(regs(*step)) for step in steps]


def cycle_reason(spec: ValueSpec, *registers: int) -> str | None:
    decoder = BlockDecoder(HR, spec.registers, [(0, spec)])
    [(_, _, reason)] = decoder.decode(regs(*registers), report_all=True)
    return reason


def words(fmt: str, value: float) -> tuple[int, ...]:
    """``value`` packed big-endian with struct format ``fmt``, as registers (ABCD)."""
    data = struct.pack(fmt, value)
    return struct.unpack(f">{len(data) // 2}H", data)


# -- an item that stays Invalid: its reason follows the registers ---------------------------


def test_bcd16_reason_follows_the_register_and_is_reported() -> None:
    spec = ValueSpec("b", T.BCD16)
    first, second, same, fixed = track(spec, (0x12AB,), (0x34CD,), (0x34CD,), (0x1234,))
    assert first == [(0, None, "invalid BCD value 0x12AB (a digit above 9)")]
    assert second == [(0, None, "invalid BCD value 0x34CD (a digit above 9)")]
    assert second[0][2] == cycle_reason(spec, 0x34CD)
    assert same == []  # the same bad value again is no change
    assert fixed == [(0, 1234, None)]


def test_bcd32_reason_follows_both_registers() -> None:
    spec = ValueSpec("b", T.BCD32)
    _, low_word, high_word = track(spec, (0x1234, 0x567A), (0x1234, 0x567B), (0x1F34, 0x567B))
    assert low_word == [(0, None, "invalid BCD value 0x1234567B (a digit above 9)")]
    assert high_word == [(0, None, "invalid BCD value 0x1F34567B (a digit above 9)")]


def test_out_of_range_conversion_reason_follows_the_value() -> None:
    spec = ValueSpec("x", T.UINT16, converted_type=T.SBYTE)
    _, moved, same = track(spec, (200,), (201,), (201,))
    assert moved == [(0, None, "value 201 is out of range for Sbyte (-128..127)")]
    assert same == []


def test_multiplied_out_of_range_reason_follows_the_value() -> None:
    spec = ValueSpec("x", T.INT16, multiplier=10, converted_type=T.INT16)
    first, moved = track(spec, (5000,), (6000,))
    assert first == [(0, None, "value 50000 is out of range for Int16 (-32768..32767)")]
    assert moved == [(0, None, "value 60000 is out of range for Int16 (-32768..32767)")]


def test_infinities_are_out_of_range_and_each_is_named() -> None:
    spec = ValueSpec("x", T.FLOAT, converted_type=T.INT32)
    _, negative = track(spec, words(">f", math.inf), words(">f", -math.inf))
    assert negative == [(0, None, "value -inf is out of range for Int32 (-2147483648..2147483647)")]


def test_a_nan_is_one_reason_whatever_its_payload() -> None:
    spec = ValueSpec("x", T.FLOAT, converted_type=T.INT32)
    first, other_payload = track(spec, (0x7FC0, 0x0000), (0x7FC0, 0x0001))
    assert first == [(0, None, "NaN cannot be converted to Int32")]
    assert other_payload == []


def test_datetime_out_of_range_reason_follows_the_value() -> None:
    spec = ValueSpec("t", T.DATETIME, quantity=4)
    _, moved = track(spec, (0x7FFF, 0xFFFF, 0xFFFF, 0xFFFF), (0x7FFF, 0xFFFF, 0xFFFF, 0xFFFE))
    assert moved == [
        (0, None, "9223372036854775806 ms is outside the dates Python can hold (years 1..9999)")
    ]


def test_missing_registers_stay_one_reason() -> None:
    decoder = BlockDecoder(HR, 2, [(0, ValueSpec("a", T.UINT16)), (1, ValueSpec("b", T.BCD16))])
    assert decoder.decode(regs(1)) == [(0, 1, None), (1, None, "not in response")]
    assert decoder.decode(regs(2)) == [(0, 2, None)]


def test_many_items_one_reason_changes_takes_the_per_item_path() -> None:
    specs = [(k, ValueSpec(f"r{k}", T.UINT16)) for k in range(20)]
    decoder = BlockDecoder(HR, 21, [*specs, (20, ValueSpec("b", T.BCD16))])
    block = [*range(20), 0x12AB]
    assert len(decoder.decode(regs(*block))) == 21
    block[20] = 0x34CD
    assert decoder.decode(regs(*block)) == [
        (20, None, "invalid BCD value 0x34CD (a digit above 9)")
    ]


def test_cycle_mode_then_change_mode_keeps_the_reported_reason() -> None:
    decoder = BlockDecoder(HR, 1, [(0, ValueSpec("b", T.BCD16))])
    decoder.decode(regs(0x12AB), report_all=True)
    assert decoder.decode(regs(0x12AB)) == []
    assert decoder.decode(regs(0x34CD)) == [(0, None, "invalid BCD value 0x34CD (a digit above 9)")]


# -- reasons name the exact value, 64-bit integers included ----------------------------------


def test_64_bit_reasons_name_the_exact_integer() -> None:
    big = (1 << 53) + 1  # a double would say 9007199254740992
    spec = ValueSpec("x", T.INT64, converted_type=T.INT32)
    why = cycle_reason(spec, *words(">q", big))
    assert why == f"value {big} is out of range for Int32 (-2147483648..2147483647)"
    [_, moved] = track(spec, words(">q", big), words(">q", big + 2))
    int32 = "Int32 (-2147483648..2147483647)"
    assert moved == [(0, None, f"value {big + 2} is out of range for {int32}")]
    huge = (1 << 64) - 1
    why = cycle_reason(ValueSpec("x", T.UINT64, converted_type=T.INT64), *words(">Q", huge))
    assert why == f"value {huge} is out of range for Int64 ({-(1 << 63)}..{(1 << 63) - 1})"


# -- values: what counts as a change -----------------------------------------------------------


def test_64_bit_deadband_distance_is_exact() -> None:
    base = 1 << 60  # neighbours are one double apart only every 256
    spec = ValueSpec("x", T.UINT64, deadband=0.5)
    _, moved, back = track(spec, words(">Q", base), words(">Q", base + 1), words(">Q", base + 1))
    assert moved == [(0, base + 1, None)] and back == []
    spec = ValueSpec("x", T.INT64, deadband=1000)
    steps = [words(">q", v) for v in (-(1 << 62), -(1 << 62) + 1000, -(1 << 62) + 1001)]
    assert track(spec, *steps)[1:] == [[], [(0, -(1 << 62) + 1001, None)]]


def test_deadband_applies_to_numbers_only() -> None:
    _, moved = track(ValueSpec("c", T.CHAR, deadband=5), (0x41,), (0x42,))
    assert moved == [(0, "B", None)]
    _, moved = track(ValueSpec("s", T.INT16, converted_type=T.STRING, deadband=5), (1,), (2,))
    assert moved == [(0, "2", None)]
    _, moved = track(ValueSpec("t", T.DATETIME, deadband=5000), (0, 1), (0, 2))
    assert moved == [(0, dt.datetime(1970, 1, 1, 0, 0, 2, tzinfo=dt.timezone.utc), None)]
    _, within = track(ValueSpec("ts", T.TIMESTAMP, deadband=5000), (0, 1), (0, 2))
    assert within == []  # Timestamp is a number (ms): 1000 ms is inside the deadband


def test_nan_payloads_are_no_change() -> None:
    _, payload = track(ValueSpec("f", T.FLOAT), (0x7FC0, 0), (0x7FC0, 1))
    assert payload == []
    _, payload = track(ValueSpec("f", T.FLOAT, converted_type=T.STRING), (0x7FC0, 0), (0xFFC0, 5))
    assert payload == []
    _, number, nan = track(ValueSpec("f", T.FLOAT, deadband=1), (0x7FC0, 0), (0, 0), (0x7FC1, 0))
    assert number == [(0, 0.0, None)]
    [(_, value, _)] = nan
    assert isinstance(value, float) and math.isnan(value)


def test_undecodable_bytes_with_the_same_text_are_no_change() -> None:
    spec = ValueSpec("s", T.STRING, quantity=1)
    decoder = BlockDecoder(HR, 1, [(0, spec)])
    assert decoder.decode(regs(0xFF41)) == [(0, "\ufffdA", None)]
    assert decoder.decode(regs(0xFE41)) == []  # other bytes, the same text
    assert decoder.decode(regs(0xFE42)) == [(0, "\ufffdB", None)]
    assert decoder.decode(regs(0xFF42), report_all=True) == [(0, "\ufffdB", None)]
    assert decoder.decode(regs(0xFE42)) == []
    decoder.reset()  # a reset reports everything again, the same text included
    assert decoder.decode(regs(0xFE42)) == [(0, "\ufffdB", None)]
    assert decoder.decode(Block.from_values([], bits=False)) == [(0, None, "not in response")]
    assert decoder.decode(regs(0xFE42)) == [(0, "\ufffdB", None)]  # recovery with old text
