"""Float values as text: a 32-bit float is written as the shortest decimal that reads back
to the same float32 (``69.744957``, as mbpoll and HMIs show it), not as the widened double
(``69.74495697021484``).

:class:`Float32` is the value of an item whose type is Float (its deviceDataType with no
multiplier, or its convertedDataType): a ``float`` holding the exact value, whose ``repr``
and ``str`` are that shortest text and which the JSON writer (codec/jsonable.py) writes
the same way.  The rule is the one the Sparkplug writer uses for a metric's type
(northbound/sparkplug/payloads.py ``sparkplug_type``): what Sparkplug sends as Float, text
and JSON write as float32."""

from __future__ import annotations

import struct
from decimal import ROUND_CEILING, Context, Decimal

__all__ = ["Float32", "float32_short", "float32_text"]

_pack = struct.Struct("<f").pack
_unpack = struct.Struct("<f").unpack
_bits = struct.Struct("<I").unpack
# The texts of recent values: a device's analog values come back to the same float32s
# (an ADC's steps, a slowly moving level), and one costs ~1 us to find; a hit ~50 ns.
_MEMO: dict[float, float] = {}
_MEMO_SIZE = 4096


def float32_short(value: float) -> float:
    """The double nearest the shortest decimal that reads back to the float32 nearest
    ``value`` (the closest such decimal when several are as short): its ``repr`` is that
    decimal.  NaN, infinities and values beyond float32's range come back as they are
    (a plain float)."""
    known = _MEMO.get(value)  # never holds a zero (-0.0 == 0.0) nor NaN
    if known is not None:
        return known
    if value - value != 0.0:  # NaN or an infinity
        return float(value)
    try:
        want = _pack(value)
    except OverflowError:  # beyond float32's range: no float32 to write
        return float(value)
    x: float = _unpack(want)[0]
    bits = _bits(want)[0] & 0x7FFF_FFFF
    if bits & 0x7F_FFFF == 0 or bits < 0x0080_0000:
        return _careful(x, want, bits)
    short = _shortest_normal(x, want)
    if len(_MEMO) >= _MEMO_SIZE:  # an economy, not a registry: start over
        _MEMO.clear()
    _MEMO[value] = short
    return short


def _shortest_normal(x: float, want: bytes) -> float:
    """:func:`float32_short` of a normal float32 ``x`` (packed: ``want``) that is not a
    power of two."""
    # A normal float32's rounding interval (at most 2**-23 of it wide) is narrower than
    # the gap between two decimals of 6 digits, so at most one decimal of 6 digits or
    # fewer reads back to it, and then '%.6g' (the nearest, trailing zeros dropped) is
    # that one; past 6 digits '%.{p}g' is the nearest of p digits.  (printf-style: half
    # the cost of format() here, where every JSON float32 passes.)
    candidate = float("%.6g" % x)  # noqa: UP031
    if _pack(candidate) == want:
        return candidate
    candidate = float("%.7g" % x)  # noqa: UP031
    if _pack(candidate) == want:
        return candidate
    candidate = float("%.8g" % x)  # noqa: UP031
    if _pack(candidate) == want:
        return candidate
    return float("%.9g" % x)  # noqa: UP031  (9 digits always read back: IEEE 754-2008 5.12.2)


def _careful(x: float, want: bytes, bits: int) -> float:
    """:func:`float32_short` of a zero, a subnormal (fewer significant bits: several short
    decimals may read back to it) or a power of two (its gap below is half the gap
    above: the nearest decimal of p digits may lie just outside below while the next one
    up is inside), searched from 1 digit."""
    if bits == 0:
        return x
    lopsided = bits & 0x7F_FFFF == 0 and bits > 0x0080_0000
    sign = -1.0 if x < 0 else 1.0
    for p in range(1, 10):
        candidate = float(f"{x:.{p}g}")
        if _pack(candidate) == want:
            return candidate
        if lopsided:
            up = Context(prec=p, rounding=ROUND_CEILING).plus(Decimal(abs(x)))
            candidate = sign * float(up)
            if _pack(candidate) == want:
                return candidate
    return float(f"{x:.9g}")  # not reached: 9 digits always read back


def float32_text(value: float) -> str:
    """``value`` rounded to float32, as the shortest decimal that reads back to it
    (``repr`` style: ``69.74496``, ``1e-07``, ``100.0``, ``nan``, ``-inf``)."""
    return repr(float32_short(value))


class Float32(float):
    """A Float item's value: the exact value (a float, equal to the widened float32), whose
    text is the shortest decimal that reads back to the same float32 (``repr``, ``str``,
    f-strings, the CLI and every JSON output).  Arithmetic on it gives plain floats."""

    __slots__ = ()

    def __repr__(self) -> str:
        return float32_text(self)

    __str__ = __repr__
