"""edgemodbus.codec.float32: a float32 written as the shortest decimal that reads back to
it, checked against an independent search in exact rational arithmetic (the rounding
interval of the float32 and every decimal of 1..9 digits in it), for random bit patterns
and for the cases a shortcut gets wrong (powers of two, subnormals, the largest)."""

from __future__ import annotations

import math
import pickle
import struct
from decimal import Decimal
from fractions import Fraction

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block
from edgemodbus.codec import (
    BlockDecoder,
    Float32,
    ValueSpec,
    encode,
    float32_short,
    float32_text,
    json_text,
)
from edgemodbus.datatypes import Area, DataType

_MAX_BITS = 0x7F7F_FFFF  # FLT_MAX


def _f32(bits: int) -> float:
    return float(struct.unpack("<f", struct.pack("<I", bits))[0])


def _interval(bits: int) -> tuple[Fraction, Fraction, bool]:
    """The reals that round to the positive float32 ``bits`` (round half to even): (low,
    high, whether the ends are included)."""
    x = Fraction(_f32(bits))
    below = Fraction(_f32(bits - 1)) if bits > 0 else -Fraction(_f32(1))
    above = Fraction(_f32(bits + 1)) if bits < _MAX_BITS else 2 * x - below
    return (below + x) / 2, (x + above) / 2, bits % 2 == 0


def _reads_back(number: Fraction, bits: int) -> bool:
    """Whether ``number`` (>= 0) rounds to the float32 ``bits`` exactly (no double in
    between)."""
    low, high, closed = _interval(bits)
    return low <= number <= high if closed else low < number < high


def _shortest(bits: int) -> tuple[int, list[Fraction]]:
    """The fewest significant digits a decimal reading back to the positive float32
    ``bits`` needs, and the decimals of that many digits nearest to it (two on a tie)."""
    x = Fraction(_f32(bits))
    low, high, closed = _interval(bits)
    top = math.floor(math.log10(x))
    for digits in range(1, 10):
        found: list[Fraction] = []
        for exp in range(top - digits, top - digits + 3):  # log10 may be off by one
            unit = Fraction(10) ** exp
            first, last = math.ceil(low / unit), math.floor(high / unit)
            for n in range(first, last + 1):
                d = n * unit
                if n < 10**digits and (closed or low < d < high):
                    found.append(d)
        if found:
            best = min(abs(d - x) for d in found)
            return digits, sorted({d for d in found if abs(d - x) == best})
    raise AssertionError(f"no decimal of 9 digits reads back to {bits:#x}")


def _digits(text: str) -> int:
    """Significant digits of a decimal text (``1.5e-07`` -> 2, ``100.0`` -> 1)."""
    mantissa = Decimal(text).normalize().as_tuple().digits
    return len(mantissa)


@settings(max_examples=3000, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(0x428B_7D6B)  # 69.74495697021484, the value: 69.74496
@example(0x3F80_0000)  # 1.0, a power of two
@example(0x0080_0000)  # the smallest normal
@example(0x0000_0001)  # the smallest subnormal: 1e-45
@example(0x007F_FFFF)  # the largest subnormal
@example(_MAX_BITS)
@example(0x8000_0000)  # -0.0
def test_text_is_the_shortest_decimal_that_reads_back(bits: int) -> None:
    value = _f32(bits)
    if not math.isfinite(value):  # nan, inf, -inf as they are
        assert float32_text(value) == repr(Float32(value)) == str(Float32(value)) == repr(value)
        return
    text = float32_text(value)
    assert repr(Float32(value)) == str(Float32(value)) == f"{Float32(value)}" == text
    assert math.copysign(1, float(text)) == math.copysign(1, value)
    magnitude = bits & 0x7FFF_FFFF
    if magnitude == 0:
        assert float(text) == 0.0
        return
    number = abs(Fraction(Decimal(text)))
    assert _reads_back(number, magnitude), (hex(bits), text)  # exactly, not via a double
    digits, nearest = _shortest(magnitude)
    assert _digits(text) == digits, (hex(bits), text, digits)
    assert number in nearest, (hex(bits), text, nearest)
    # JSON writes the same decimal: float32_short is the double whose repr is the text,
    # and orjson writes a double's shortest form
    assert repr(float32_short(value)) == text
    assert Decimal(json_text(Float32(value))) == Decimal(text)


def test_every_power_of_two_and_the_edges_of_the_subnormals() -> None:
    """Powers of two have a narrower gap below (the lopsided rounding interval);
    subnormals have fewer significant bits: both need the careful search."""
    cases = [e << 23 for e in range(1, 255)] + list(range(1, 64)) + [
        0x007F_FFFF - k for k in range(64)] + [(e << 23) + d for e in (1, 2, 127, 254)
                                              for d in (-1, 1)]
    for bits in cases:
        text = float32_text(_f32(bits))
        digits, nearest = _shortest(bits)
        assert _digits(text) == digits and Fraction(Decimal(text)) in nearest, (hex(bits), text)


def test_examples() -> None:
    assert float32_text(69.74495697021484) == "69.74496"
    assert float32_text(0.10000000149011612) == "0.1"
    assert float32_text(0.1) == "0.1"  # a double is rounded to float32 first
    assert float32_text(1.401298464324817e-45) == "1e-45"
    assert float32_text(3.4028234663852886e38) == "3.4028235e+38"
    assert float32_text(16777216.0) == "16777216.0"
    assert float32_text(0.0) == "0.0" and float32_text(-0.0) == "-0.0"  # not one memo
    assert [float32_text(v) for v in (math.nan, math.inf, -math.inf)] == ["nan", "inf", "-inf"]
    assert float32_text(1e300) == "1e+300"  # beyond float32: no float32 text, the double's


def test_a_float32_is_the_exact_float() -> None:
    exact = 69.74495697021484
    value = Float32(exact)
    assert value == exact and hash(value) == hash(exact) and isinstance(value, float)
    assert float(value) == exact and float.__repr__(value) == "69.74495697021484"
    assert type(value + 1) is float and type(-value) is float
    copy = pickle.loads(pickle.dumps(value))
    assert type(copy) is Float32 and copy == exact


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e39, -1e39])
def test_what_float32_cannot_hold_comes_back_unchanged(value: float) -> None:
    for kind in (value, Float32(value)):
        short = float32_short(kind)
        assert type(short) is float
        assert short == value or (math.isnan(short) and math.isnan(value))
    assert repr(Float32(value)) == repr(value)


def test_the_text_of_the_largest_float32_writes_it_back() -> None:
    """FLT_MAX's shortest text, 3.4028235e+38, is a double just past FLT_MAX that rounds
    to it: a write of it (an MQTT command echoing a payload) wrote nothing: the C encoder
    refused it ("codec: cannot pack raw value"); what rounds past it still names the range."""
    spec = ValueSpec("x", DataType.FLOAT)
    assert float(float32_text(3.4028234663852886e38)) > 3.4028234663852886e38
    for sign in (1, -1):
        assert encode(spec, sign * float(float32_text(3.4028234663852886e38))) == \
            encode(spec, sign * 3.4028234663852886e38) == [0x7F7F if sign > 0 else 0xFF7F,
                                                          0xFFFF]
    with pytest.raises(ValueError, match=r"'x': cannot write 3\.5e\+38: allowed -3\.40282e"):
        encode(spec, 3.5e38)


def test_recent_texts_are_remembered_without_changing_them() -> None:
    """float32_short keeps the texts of recent values (a bounded memo, cleared when
    full): past its size, every value still gets its own text."""
    values = [_f32(0x4000_0000 + 7919 * k) for k in range(10_000)]
    first = [float32_short(v) for v in values]
    assert [float32_short(v) for v in reversed(values)] == first[::-1]
    assert [_digits(repr(s)) for s in first] == [_shortest(0x4000_0000 + 7919 * k)[0]
                                                 for k in range(10_000)]


def _decode(spec: ValueSpec, *registers: int) -> object:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, len(registers), [(0, spec)])
    return decoder.decode_values(Block.from_values(list(registers), bits=False))[0]


def test_which_values_are_float32() -> None:
    """The items Sparkplug sends as Float (northbound/sparkplug/payloads.py): Float
    without a multiplier, convertedDataType Float; a multiplier makes a double."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", 69.74495697021484))
    f = DataType.FLOAT
    got = _decode(ValueSpec("x", f), hi, lo)
    assert type(got) is Float32 and got == 69.74495697021484 and str(got) == "69.74496"
    scaled = _decode(ValueSpec("x", f, multiplier=0.1), hi, lo)
    assert type(scaled) is float and scaled == 6.974495697021484
    assert type(_decode(ValueSpec("x", f, multiplier=0.1, converted_type=f), hi, lo)) is Float32
    tenths = _decode(ValueSpec("x", DataType.INT16, multiplier=0.1, converted_type=f), 3)
    assert type(tenths) is Float32 and tenths == 0.3 and repr(tenths) == "0.3"
    assert _decode(ValueSpec("x", DataType.INT16, multiplier=0.1), 3) == 0.3  # raw / 10
    assert type(_decode(ValueSpec("x", DataType.DOUBLE, quantity=2), hi, lo)) is float
    assert _decode(ValueSpec("x", f, converted_type=DataType.STRING), hi, lo) == "69.74496"


def test_a_float_items_deadband_still_holds() -> None:
    spec = ValueSpec("x", DataType.FLOAT, deadband=0.5)
    decoder = BlockDecoder(Area.HOLDING_REGISTER, 2, [(0, spec)])

    def read(value: float) -> list[object]:
        block = Block.from_values(list(struct.unpack(">HH", struct.pack(">f", value))),
                                  bits=False)
        return [v for _, v, _ in decoder.decode(block)]

    assert read(10.0) == [10.0]
    assert read(10.25) == []  # within the deadband: no news
    (moved,) = read(10.75)
    assert type(moved) is Float32 and moved == 10.75
