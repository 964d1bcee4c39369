"""Engineering units in the C codec against an independent reference in exact
arithmetic (fractions): offset with multiplier and scale factor, range scaling with
Invalid and clamp, scale factors stored by one block's plan and used by another's;
writes invert the decode (decimal, round half to even) and read back."""

from __future__ import annotations

import math
import struct
from fractions import Fraction

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ScaleFactors, ValueSpec, encode
from edgemodbus.datatypes import Area, DataType

HR = Area.HOLDING_REGISTER
# (type, registers, raw values it holds)
TYPES = {
    DataType.INT16: (1, st.integers(-(2**15), 2**15 - 1)),
    DataType.UINT16: (1, st.integers(0, 2**16 - 1)),
    DataType.INT32: (2, st.integers(-(2**31), 2**31 - 1)),
    DataType.UINT32: (2, st.integers(0, 2**32 - 1)),
}
MULTIPLIERS = [1.0, 0.1, 0.01, 2.5, -3.0, 0.001]
# no subnormal results: a double's relative precision holds (an engineering value near
# 1e-308 is no unit anyone configures)
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False).filter(
    lambda x: x == 0 or abs(x) > 1e-200)


def regs_of(dtype: DataType, raw: int) -> list[int]:
    n = TYPES[dtype][0]
    return [(raw >> (16 * (n - 1 - k))) & 0xFFFF for k in range(n)]


def close(got: float, exact: Fraction, scale: Fraction) -> bool:
    """Within a few double roundings of the exact value (each step rounds once)."""
    return abs(Fraction(got) - exact) <= (abs(exact) + abs(scale)) * Fraction(1, 2**48)


@st.composite
def linear_cases(draw: st.DrawFn) -> tuple[DataType, int, float, float, int | None]:
    dtype = draw(st.sampled_from(list(TYPES)))
    raw = draw(TYPES[dtype][1])
    return (dtype, raw, draw(st.sampled_from(MULTIPLIERS)), draw(finite),
            draw(st.none() | st.integers(-10, 10)))


@settings(max_examples=300, deadline=None)
@given(linear_cases())
def test_offset_multiplier_and_factor_equal_exact_arithmetic(
    case: tuple[DataType, int, float, float, int | None],
) -> None:
    dtype, raw, m, offset, sf = case
    factors = ScaleFactors(["SF"]) if sf is not None else None
    spec = ValueSpec("x", dtype, multiplier=m, offset=offset,
                     scale_factor="SF" if sf is not None else None, factors=factors)
    items: list[tuple[int, ValueSpec]] = [(0, spec)]
    data = regs_of(dtype, raw)
    if sf is not None:
        items.append((len(data), ValueSpec("SF", DataType.INT16, holds_factor="SF",
                                           factors=factors)))
        data.append(sf & 0xFFFF)
    [(_, value, error), *_] = BlockDecoder(HR, len(data), items).decode(
        Block.from_values(data, bits=False))
    exact = Fraction(raw) * Fraction(10) ** (sf or 0) * Fraction(m) + Fraction(offset)
    assert error is None
    scaled = m != 1 or offset != 0 or sf is not None
    assert isinstance(value, float if scaled else int)  # unscaled: the raw int as before
    assert close(value, exact, Fraction(offset)), (value, exact)


@st.composite
def range_cases(draw: st.DrawFn) -> tuple[DataType, int, tuple[int, int], tuple[float, float],
                                         bool]:
    dtype = draw(st.sampled_from(list(TYPES)))
    values = TYPES[dtype][1]
    r0, r1 = draw(values), draw(values)
    assume(r0 != r1)
    e0, e1 = draw(finite), draw(finite)
    assume(e0 != e1)
    return dtype, draw(values), (r0, r1), (e0, e1), draw(st.booleans())


@settings(max_examples=300, deadline=None)
@given(range_cases())
def test_range_scaling_equals_exact_arithmetic(
    case: tuple[DataType, int, tuple[int, int], tuple[float, float], bool],
) -> None:
    dtype, raw, (r0, r1), (e0, e1), clamp = case
    spec = ValueSpec("x", dtype, raw_range=(r0, r1), eng_range=(e0, e1), clamp=clamp)
    decoder = BlockDecoder(HR, TYPES[dtype][0], [(0, spec)])
    [(_, value, error)] = decoder.decode(Block.from_values(regs_of(dtype, raw), bits=False))
    inside = min(r0, r1) <= raw <= max(r0, r1)
    if not inside and not clamp:
        assert value is None
        assert error == f"raw value {raw} outside rawMin..rawMax ({r0}..{r1})"
        return
    exact = Fraction(e0) + (Fraction(raw) - r0) * (Fraction(e1) - Fraction(e0)) / (r1 - r0)
    if clamp:
        exact = min(max(exact, Fraction(min(e0, e1))), Fraction(max(e0, e1)))
    assert error is None and isinstance(value, float)
    assert close(value, exact, abs(Fraction(e0)) + abs(Fraction(e1))), (value, exact)
    if clamp:
        assert min(e0, e1) <= value <= max(e0, e1)


@st.composite
def inside_range_cases(draw: st.DrawFn) -> tuple[DataType, int, tuple[int, int],
                                                tuple[float, float], bool]:
    """A range case whose raw value lies inside rawMin..rawMax, drawn there (filtering
    it out of range_cases() left too few inputs on some runs)."""
    dtype, _, (r0, r1), eng, clamp = draw(range_cases())
    return dtype, draw(st.integers(min(r0, r1), max(r0, r1))), (r0, r1), eng, clamp


@settings(max_examples=300, deadline=None)
@given(inside_range_cases())
def test_a_write_reads_back_as_the_value_written(
    case: tuple[DataType, int, tuple[int, int], tuple[float, float], bool],
) -> None:
    """The inverse is exact: the raw value written is the exact raw value of the
    engineering value, rounded half to even (decimal), and reads back as it."""
    dtype, raw, (r0, r1), (e0, e1), clamp = case
    # one raw count is far above a double's resolution of the values (else no inverse
    # can name the raw value: many read as one)
    assume(abs(e1 - e0) / abs(r1 - r0) > 1e-6 * max(1.0, abs(e0), abs(e1)))
    spec = ValueSpec("x", dtype, raw_range=(r0, r1), eng_range=(e0, e1), clamp=clamp)
    decoder = BlockDecoder(HR, TYPES[dtype][0], [(0, spec)])
    [(_, value, _)] = decoder.decode(Block.from_values(regs_of(dtype, raw), bits=False))
    assert isinstance(value, float)
    assume(min(e0, e1) <= value <= max(e0, e1))
    registers = encode(spec, value)
    exact_raw = Fraction(r0) + (Fraction(repr(value)) - Fraction(repr(e0))) * (r1 - r0) / (
        Fraction(repr(e1)) - Fraction(repr(e0)))
    written = decoder.decode_values(Block.from_values(registers, bits=False))[0]
    raw_written = BlockDecoder(HR, len(registers), [(0, ValueSpec("r", dtype))]).decode_values(
        Block.from_values(registers, bits=False))[0]
    assert isinstance(raw_written, int)
    assert abs(raw_written - exact_raw) <= Fraction(1, 2)
    assert abs(raw_written - raw) <= 1  # the value read names the raw value within rounding
    assert isinstance(written, float) and math.isfinite(written)


def test_offset_write_rounds_half_to_even_and_checks_the_device_range() -> None:
    spec = ValueSpec("t", DataType.INT16, multiplier=0.1, offset=-40)
    assert encode(spec, 25.5) == [655]
    assert encode(spec, -40.05) == [0]  # -0.5 raw rounds to even 0
    assert encode(spec, -39.95) == [0]  # +0.5 raw rounds to even 0
    assert encode(spec, -39.85) == [2]  # 1.5 rounds to 2
    with pytest.raises(ValueError, match=r"item 't': cannot write 3300: allowed "
                                         r"-3316\.8\.\.3236\.7 \(Int16 on the device\)"):
        encode(spec, 3300)
    f = ValueSpec("f", DataType.FLOAT, offset=1.5)
    assert encode(f, 2.5) == list(struct.unpack(">2H", struct.pack(">f", 1.0)))


def test_a_factor_is_shared_by_the_blocks_of_one_device() -> None:
    """One block's plan stores the factor; another block's plan uses it (later in the
    pass or in a later pass); a write's decode (VALUES) never stores one."""
    factors = ScaleFactors(["SF"])
    source = BlockDecoder(HR, 1, [(0, ValueSpec("", DataType.INT16, holds_factor="SF",
                                                  factors=factors))])
    user = BlockDecoder(HR, 1, [(0, ValueSpec("", DataType.UINT16, scale_factor="SF",
                                                factors=factors))])
    block = Block.from_values([500], bits=False)
    assert user.decode(block) == [(0, None, "scale factor item 'SF' not read yet")]
    source.decode_values(Block.from_values([3], bits=False))  # a write's check
    assert factors.get("SF") is None
    source.decode(Block.from_values([0xFFFD], bits=False))
    assert factors.get("SF") == -3
    assert user.decode(block) == [(0, 0.5, None)]
    source.decode(Block.from_values([0xFFFE], bits=False))
    assert user.decode(block) == [(0, 5.0, None)]  # same raw, new factor: reported
    assert user.decode(block) == []


def test_a_write_needs_a_usable_factor() -> None:
    factors = ScaleFactors(["SF"])
    spec = ValueSpec("W", DataType.INT16, scale_factor="SF", factors=factors)
    source = BlockDecoder(HR, 1, [(0, ValueSpec("", DataType.INT16, holds_factor="SF",
                                                  factors=factors))])
    with pytest.raises(ValueError, match="item 'W': cannot write: its scale factor item 'SF' "
                                         r"has not been read yet"):
        encode(spec, 1)
    for raw, why in ((0x8000, r"is 0x8000 \(SunSpec: not implemented\)"),
                     (11, r"holds 11, outside -10\.\.10")):
        source.decode(Block.from_values([raw], bits=False))
        with pytest.raises(ValueError, match=f"scale factor item 'SF' {why}"):
            encode(spec, 1)
    source.decode(Block.from_values([0xFFFF], bits=False))
    assert encode(spec, 12.3) == [123]
    assert encode(spec, -12.35) == [0xFF84]  # -123.5 rounds half to even: -124


def test_items_without_scaling_get_no_step() -> None:
    """An unscaled item's C item has no EMB_F_EXT: it takes the path it took before."""
    from edgemodbus.codec.scaling import scale_step

    assert scale_step(ValueSpec("a", DataType.INT16, multiplier=0.1)) is None
    assert scale_step(ValueSpec("a", DataType.INT16, offset=1)) is not None


@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize(("dtype", "registers"), [
    (DataType.FLOAT, [0x7FC0, 0x0000]),  # the quiet NaN a sensor fault often reads
    (DataType.FLOAT, [0xFFFF, 0x0000]),
    (DataType.DOUBLE, [0x7FF8, 0, 0, 0]),
])
def test_a_nan_raw_value_is_invalid_clamped_or_not(dtype: DataType, registers: list[int],
                                                   clamp: bool) -> None:
    """NaN is outside rawMin..rawMax, and has no nearest bound to be clamped to: Invalid
    in both modes (it was a NaN with status Ok under clamp, outside engMin..engMax)."""
    spec = ValueSpec("x", dtype, raw_range=(0, 27648), eng_range=(0, 100), clamp=clamp)
    decoder = BlockDecoder(HR, len(registers), [(0, spec)])
    [(_, value, error)] = decoder.decode(Block.from_values(registers, bits=False))
    assert value is None
    assert error == "raw value nan outside rawMin..rawMax (0..27648)"
