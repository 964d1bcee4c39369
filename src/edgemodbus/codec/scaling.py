"""Engineering units (docs/engineering-units.md): an item's ``offset``, its range
scaling (``rawMin/rawMax -> engMin/engMax``, optionally clamped) and its scale factor
read from another item (SunSpec ``*_SF``: value x 10^sf).

The decode runs in C (csrc/emb_codec.c, ``scale_ext``): :func:`scale_step` compiles a
spec's step once per plan.  Writes invert it here exactly, in decimal
(:func:`to_raw`), and :func:`to_eng` maps a raw bound for error messages.

Composition: a range maps the raw value alone (no multiplier, offset or scale factor
with it); otherwise value = raw x 10^sf x dataMultiplier + offset.
"""

from __future__ import annotations

import math
from decimal import Decimal, localcontext
from typing import Protocol

from .. import _ffi
from .._ffi import CodecScale, ScaleFactors
from ..datatypes import DataType


class ValueSpec(Protocol):
    """What this module reads of a spec (codec/spec.py's ValueSpec, which imports it)."""

    @property
    def name(self) -> str: ...
    @property
    def data_type(self) -> DataType: ...
    @property
    def quantity(self) -> int | None: ...
    @property
    def bit(self) -> int | None: ...
    @property
    def multiplier(self) -> float: ...
    @property
    def offset(self) -> float: ...
    @property
    def raw_range(self) -> tuple[float, float] | None: ...
    @property
    def eng_range(self) -> tuple[float, float] | None: ...
    @property
    def clamp(self) -> bool: ...
    @property
    def scale_factor(self) -> str | None: ...
    @property
    def holds_factor(self) -> str | None: ...
    @property
    def factors(self) -> ScaleFactors | None: ...
    @property
    def scaled(self) -> bool: ...

__all__ = ["SF_MAX", "ScaleFactors", "check_scaling", "scale_step", "to_eng", "to_raw"]

SF_MAX: int = _ffi.codec_constants("SF")["MAX"]
"""A scale factor's allowed magnitude: -SF_MAX..SF_MAX (10^10 is exact in a double)."""
SF_NOT_IMPLEMENTED = -32768
"""0x8000, SunSpec's "not implemented" value of an Int16 (sunssf) point."""

_R = _ffi.codec_constants("R")


def _finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_scaling(spec: ValueSpec) -> tuple[str, object, str] | None:
    """(field, value, what is allowed) of the first scaling key ``spec`` may not have,
    or None.  Field names are the device file's keys."""
    t = spec.data_type
    if not _finite(spec.offset):
        return "offset", spec.offset, "a finite number"
    rr, er = spec.raw_range, spec.eng_range
    given = dict(zip(("rawMin", "rawMax", "engMin", "engMax"),
                     (*(rr or (None, None)), *(er or (None, None))), strict=True))
    missing = [key for key, v in given.items() if v is None]
    if 0 < len(missing) < 4:
        return (missing[0], None, "rawMin, rawMax, engMin and engMax all four, or none "
                f"(missing: {', '.join(missing)})")
    if rr is not None and er is not None:
        for key, v in zip(("rawMin", "rawMax", "engMin", "engMax"), (*rr, *er), strict=True):
            if not _finite(v):
                return key, v, "a finite number"
        if rr[0] == rr[1]:
            return "rawMax", rr[1], f"a number other than rawMin ({rr[0]})"
        if er[0] == er[1]:
            return "engMax", er[1], f"a number other than engMin ({er[0]})"
        others: tuple[tuple[str, object, object], ...] = (
            ("dataMultiplier", spec.multiplier, 1), ("offset", spec.offset, 0),
            ("scaleFactor", spec.scale_factor, None))
        for key, other, off in others:
            if other != off:
                return key, other, ("a range (rawMin..engMax) maps the raw value alone: "
                                f"leave {key} out, or fold it into engMin/engMax")
    elif spec.clamp:
        return "clamp", True, "clamp needs rawMin, rawMax, engMin and engMax"
    if spec.scaled and not t.is_numeric:
        why = f"{t.value} values are not scaled (numeric types only)"
        if spec.scale_factor is not None:
            return "scaleFactor", spec.scale_factor, why
        if spec.offset:
            return "offset", spec.offset, why
        return "rawMin", rr and rr[0], why
    if spec.scale_factor is not None:
        f = spec.factors
        if f is None or spec.scale_factor not in f.names:
            return ("scaleFactor", spec.scale_factor,
                    "the name of an Int16 item of the same device")
    if spec.holds_factor is not None:
        if spec.factors is None or spec.holds_factor not in spec.factors.names:
            return "scaleFactor", spec.holds_factor, "a factor of the device's table"
        if t is not DataType.INT16 or spec.quantity not in (None, 1) or spec.bit is not None:
            return ("deviceDataType", t.value,
                    "a scale factor item is Int16 (one register; SunSpec sunssf)")
        if spec.scaled or spec.multiplier != 1:
            return "scaleFactor", spec.holds_factor, "a scale factor item is not scaled itself"
    return None


def scale_step(spec: ValueSpec) -> CodecScale | None:
    """The C step of a scaled spec (None: not scaled, the item pays nothing)."""
    if not spec.scaled:
        return None
    sf = -1
    if spec.scale_factor is not None:
        assert spec.factors is not None  # check_scaling
        sf = spec.factors.index(spec.scale_factor)
    if spec.raw_range is None or spec.eng_range is None:
        return CodecScale(add=float(spec.offset), sf=sf)
    (r0, r1), (e0, e1) = spec.raw_range, spec.eng_range
    return CodecScale(
        sub=float(r0),
        mul=(float(e1) - float(e0)) / (float(r1) - float(r0)),
        add=float(e0),
        raw_lo=float(min(r0, r1)),
        raw_hi=float(max(r0, r1)),
        eng_lo=float(min(e0, e1)),
        eng_hi=float(max(e0, e1)),
        sf=sf,
        range=_R["CLAMP"] if spec.clamp else _R["INVALID"],
    )


def _dec(x: float) -> Decimal:
    return Decimal(repr(x)) if isinstance(x, float) else Decimal(x)


def factor_of(spec: ValueSpec) -> int:
    """The scale factor a write of ``spec`` is inverted with (0 without one): the last
    one read; ValueError naming both items when it is unknown or unusable."""
    if spec.scale_factor is None:
        return 0
    assert spec.factors is not None  # check_scaling
    sf = spec.factors.get(spec.scale_factor)
    head = f"item {spec.name!r}: cannot write: its scale factor item {spec.scale_factor!r}"
    if sf is None:
        raise ValueError(f"{head} has not been read yet (write after the first poll)")
    if sf == SF_NOT_IMPLEMENTED:
        raise ValueError(f"{head} is 0x8000 (SunSpec: not implemented)")
    if not -SF_MAX <= sf <= SF_MAX:
        raise ValueError(f"{head} holds {sf}, outside -{SF_MAX}..{SF_MAX}")
    return sf


def to_raw(spec: ValueSpec, value: Decimal, sf: int) -> Decimal:
    """The exact inverse of the decode: the raw value (before rounding to the wire type)
    whose engineering value is ``value``; ValueError naming the item when ``value`` is
    outside engMin..engMax."""
    with localcontext() as ctx:
        ctx.prec = 60
        if spec.raw_range is not None and spec.eng_range is not None:
            (r0, r1), (e0, e1) = map(_dec, spec.raw_range), map(_dec, spec.eng_range)
            if not min(e0, e1) <= value <= max(e0, e1):
                raise ValueError(
                    f"item {spec.name!r}: cannot write {value}: allowed "
                    f"{_text(min(e0, e1))}..{_text(max(e0, e1))} (engMin..engMax)")
            return r0 + (value - e0) * (r1 - r0) / (e1 - e0)
        x = (value - _dec(spec.offset)) / _dec(spec.multiplier)
        return x.scaleb(-sf)


def to_eng(spec: ValueSpec, raw: int | float, sf: int) -> Decimal:
    """The engineering value of a raw bound (exact, for messages)."""
    with localcontext() as ctx:
        ctx.prec = 60
        r = _dec(raw)
        if spec.raw_range is not None and spec.eng_range is not None:
            (r0, r1), (e0, e1) = map(_dec, spec.raw_range), map(_dec, spec.eng_range)
            return e0 + (r - r0) * (e1 - e0) / (r1 - r0)
        return r.scaleb(sf) * _dec(spec.multiplier) + _dec(spec.offset)


def _text(d: Decimal) -> str:
    d = d.normalize()
    return format(d, "f") if d == d.to_integral_value() else str(d)
