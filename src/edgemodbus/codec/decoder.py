"""Block decoding: every item of a read block in one C call, with change detection."""

from __future__ import annotations

import bisect
import itertools
import math
import operator
from array import array
from collections.abc import Hashable, Sequence

from .. import _ffi
from .._ffi import Block, CodecPlan
from ..datatypes import Area, DataType
from .scaling import SF_MAX, scale_step
from .shared import SharedCache
from .spec import ValueSpec, _compile, _Compiled, check_spec

__all__ = ["BlockDecoder", "Change"]

_E = _ffi.codec_constants("E")

Change = tuple[int, object, "str | None"]  # (item index, value or None, error reason or None)


def _fmt_number(v: float) -> str:
    if isinstance(v, int):
        return str(v)
    if math.isfinite(v) and v == int(v) and abs(v) < 2**53:
        return str(int(v))
    return repr(v)


_NO_TEXT = object()  # a String item whose last report was not a text
_INDEX = operator.itemgetter(0)


def _small_ints(values: list[int]) -> array[int]:
    """Non-negative ints in the narrowest array that holds them (16 or 32 bits)."""
    return array("H" if max(values, default=0) <= 0xFFFF else "I", values)


def _shared_indexes(n: int) -> tuple[int, ...]:
    """At least ``n`` item indexes 0, 1, ...: one tuple shared by every decoder, so that
    a decoder keeps no list of indexes of its own (and zips over a tuple, which is
    cheaper than over a range)."""
    global _INDEXES
    if len(_INDEXES) < n:
        _INDEXES = tuple(range(max(n, 2 * len(_INDEXES))))
    return _INDEXES


_INDEXES: tuple[int, ...] = tuple(range(257))  # the ints Python keeps anyway


_SCALING_CODES = frozenset((_E["RAW_RANGE"], _E["SF_UNKNOWN"], _E["SF_NI"], _E["SF_RANGE"]))


def _scaling(
    items: Sequence[tuple[int, ValueSpec]],
) -> tuple[list[_ffi.CodecScale | None], _ffi.ScaleFactors | None, list[tuple[int, int]]]:
    """The engineering units of a block's items for its C plan: each item's step (an
    empty list when none has one), the device's scale factors and the block's items
    that hold one (codec/scaling.py)."""
    steps = [scale_step(spec) for _, spec in items]
    if not any(steps):
        steps = []
    factors = None
    sources: list[tuple[int, int]] = []
    for k, (_, spec) in enumerate(items):
        if spec.factors is None:
            continue
        if factors is not None and spec.factors is not factors:
            raise ValueError(f"item {spec.name!r}: its scale factors are another device's")
        factors = spec.factors
        if spec.holds_factor is not None:
            sources.append((k, factors.index(spec.holds_factor)))
    return steps, factors, sources


class _Shape:
    """The immutable part of a :class:`BlockDecoder`: the checked, compiled items of a
    block (their C layout), their specs and offsets.  Shared by every decoder of the
    same area, count and items (:data:`_SHAPES`)."""

    __slots__ = ("__weakref__", "layout", "offsets", "spec_of", "specs", "strings")

    def __init__(self, area: Area, count: int, items: Sequence[tuple[int, ValueSpec]]) -> None:
        if not (isinstance(count, int) and count >= 0):
            raise ValueError(f"block count {count!r} is not allowed (an int >= 0)")
        compiled: list[_Compiled] = []
        for offset, spec in items:
            check_spec(spec, area)
            size = 1 if area.is_bit else spec.registers
            if not (isinstance(offset, int) and offset >= 0 and offset + size <= count):
                raise ValueError(
                    f"item {spec.name!r}: offset {offset!r} (+{size}) is outside the block "
                    f"of {count} {'bits' if area.is_bit else 'registers'}"
                )
            compiled.append(_compile(spec, area, offset))
        # Each item's spec and offset, for error reasons (rare) only: as small ints in
        # arrays (a gateway holds one decoder entry per tag), the specs an index into
        # the distinct ones (the items of a block share a few specs).
        distinct: dict[ValueSpec, int] = {}
        spec_of = [distinct.setdefault(spec, len(distinct)) for _, spec in items]
        self.specs = tuple(distinct)
        self.spec_of = _small_ints(spec_of)
        self.offsets = _small_ints([offset for offset, _ in items])
        # the compiled items live on in the C layout only: error reasons, which are rare,
        # compile their item again (see _reason), which keeps a decoder small per tag
        self.layout = _ffi.CodecLayout(area.is_bit, [c.item for c in compiled],
                                       [c.post for c in compiled], *_scaling(items))
        self.strings = tuple(k for k, (_, spec) in enumerate(items)
                             if spec.data_type is DataType.STRING)


# Compiled blocks by (area, count, items): the devices of one template share them.  A
# spec with scale factors holds its device's own ScaleFactors (compared by identity),
# so such blocks are shared only within their device.
_SHAPES: SharedCache[_Shape] = SharedCache(keep=256)


def _shape_key(area: Area, count: int, items: Sequence[tuple[int, ValueSpec]]) -> Hashable:
    """The cache key of a block: its offsets and each item's spec (an index into the
    block's distinct specs) packed in int arrays, not an (offset, spec) tuple per item,
    which a key held for every distinct block costs (64 bytes an item:
    docs/item-store.md, "Memory").  Offsets that do not fit (the block is refused as it
    is built) key it as given."""
    distinct: dict[ValueSpec, int] = {}
    try:
        offsets = array("I", [offset for offset, _ in items]).tobytes()
        spec_of = array("I", [distinct.setdefault(spec, len(distinct)) for _, spec in items])
    except (OverflowError, TypeError):
        return (area, count, tuple(items))
    return (area, count, offsets, tuple(distinct), spec_of.tobytes())


class BlockDecoder:
    """Decodes every item of one read block in one C call, reporting only what changed.

    Compiled once per plan; each decode reuses the same arrays.  Use from one thread at a
    time (the worker of the line that reads the block).
    """

    __slots__ = (
        "_indexes",
        "_offsets",
        "_plan",
        "_reported",
        "_shape",
        "_spec_of",
        "_specs",
        "_texts",
        "area",
        "count",
    )

    def __init__(self, area: Area, count: int, items: Sequence[tuple[int, ValueSpec]]) -> None:
        # the compiled block is shared by every decoder of the same items (a template's
        # devices): only the state below is this decoder's own
        shape = _SHAPES.get(_shape_key(area, count, items),
                            lambda: _Shape(area, count, items))
        self._shape = shape
        self.area = area
        self.count = count
        self._specs = shape.specs
        self._spec_of = shape.spec_of
        self._offsets = shape.offsets
        self._plan = CodecPlan.of(shape.layout)
        self._indexes = _shared_indexes(shape.layout.n_items)
        # The tuple last reported for each item: mirrors the C state, so that a report of
        # every item rebuilds only the tuples whose value or status moved.
        self._reported: list[Change] = []
        # String items decode bytes that are not valid text to U+FFFD, so different
        # bytes (which C compares) can give the text already reported: the last text
        # reported for each String item (_NO_TEXT after an error or a reset).
        self._texts: dict[int, object] = dict.fromkeys(shape.strings, _NO_TEXT)

    @property
    def specs(self) -> list[ValueSpec]:
        """The spec of each item, in order."""
        specs = self._specs
        return [specs[i] for i in self._spec_of]

    def _reason(self, index: int, code: int) -> str:
        if code == _E["MISSING"]:
            return "not in response"
        spec = self._specs[self._spec_of[index]]
        if code in _SCALING_CODES:
            return self._scaling_reason(spec, index, code)
        c = _compile(spec, self.area, self._offsets[index])
        if code == _E["NAN"]:
            return f"NaN cannot be converted to {c.target_label}"
        v = self._plan.errval(index)
        if v is None:  # the C codec gives every status but MISSING a value
            raise AssertionError(f"codec: item {index} failed (status {code}) without a value")
        if code == _E["BCD"]:
            digits = 4 if c.wire == "BCD16" else 8
            return f"invalid BCD value 0x{v:0{digits}X} (a digit above 9)"
        if c.target_label == "DateTime":
            return f"{_fmt_number(v)} ms is outside the dates Python can hold (years 1..9999)"
        if c.target_range is not None:
            lo, hi = c.target_range
            return f"value {_fmt_number(v)} is out of range for {c.target_label} ({lo}..{hi})"
        return f"value {_fmt_number(v)} is out of range for {c.target_label}"

    def _scaling_reason(self, spec: ValueSpec, index: int, code: int) -> str:
        v = self._plan.errval(index)
        if code == _E["RAW_RANGE"]:
            lo, hi = spec.raw_range or (math.nan, math.nan)
            return (f"raw value {_fmt_number(v) if v is not None else v} outside "
                    f"rawMin..rawMax ({_fmt_number(lo)}..{_fmt_number(hi)})")
        which = f"scale factor item {spec.scale_factor!r}"
        if code == _E["SF_UNKNOWN"]:
            return f"{which} not read yet"
        if code == _E["SF_NI"]:
            return f"{which} is 0x8000 (SunSpec: not implemented)"
        return f"{which} holds {v}, outside -{SF_MAX}..{SF_MAX}"

    def decode(self, block: Block, report_all: bool = False) -> list[Change]:
        """(index, value or None, error reason or None) of every item whose value, status
        or error reason changed since it was last reported (all of them when
        ``report_all``)."""
        plan, mode = self.begin(report_all)
        return self.finish(plan.decode(block, mode), report_all)

    def begin(self, report_all: bool) -> tuple[CodecPlan, int]:
        """The C plan and mode of the next decode, for a caller that runs it itself (the
        line's worker reads and decodes a block in one C call); then call :meth:`finish`."""
        if report_all:
            if not self._reported:
                self._plan.reset()  # no tuples cached: have C report every item
            return self._plan, _ffi.CODEC_MODE_ALL
        if self._reported:
            self._reported = []  # the report-all cache no longer mirrors the C state
        return self._plan, _ffi.CODEC_MODE_TRACK

    def finish(self, n: int, report_all: bool) -> list[Change]:
        """The reports of a decode that returned ``n`` (see :meth:`decode`)."""
        if report_all:
            return self._finish_all(n)
        if not n:
            return []
        plan = self._plan
        changed = plan.changed(n)
        if n * 8 >= plan.n_items:  # many changed: convert the arrays in one go
            values = plan.values()
            if plan.n_errors:
                errors = {k: self._reason(k, plan.status(k)) for k in plan.errors()}
                reports = [(k, values[k], errors.get(k)) for k in changed]
            elif n == plan.n_items:  # every item, in order
                reports = list(zip(changed, values, itertools.repeat(None)))
            else:
                reports = list(zip(changed, map(values.__getitem__, changed),
                                   itertools.repeat(None)))
        else:
            status = plan.status_view
            reports = [
                (k, None, self._reason(k, status[k])) if status[k] else (k, plan.value(k), None)
                for k in changed
            ]
        return self._new_texts_only(reports) if self._texts else reports

    def finish_every(self, n: int) -> list[object] | None:
        """Every item's value, in item order, when a TRACK decode returned ``n`` and that
        is every item, all good, each one news (a String item's text too): the same
        reports as ``finish(n, False)`` without a tuple per item.  None otherwise, and
        then nothing is changed: call :meth:`finish`."""
        plan = self._plan
        if n != plan.n_items or plan.n_errors:
            return None
        values = plan.values()
        texts = self._texts
        if texts:
            if any(texts[k] == values[k] for k in texts):
                return None  # a text already reported: finish() leaves it out
            for k in texts:
                texts[k] = values[k]
        return values

    def _new_texts_only(self, reports: list[Change]) -> list[Change]:
        """``reports`` (in item order) without the String items whose text is the one
        last reported; only the String items are looked at."""
        texts = self._texts
        drop: list[int] = []
        if len(reports) < len(texts):  # few reports (1% change): look only at those
            for at, (k, value, error) in enumerate(reports):
                if k not in texts:
                    continue
                last = texts[k]
                texts[k] = _NO_TEXT if error is not None else value
                if error is None and last == value:
                    drop.append(at)
            for at in reversed(drop):
                del reports[at]
            return reports
        for k in texts:
            at = bisect.bisect_left(reports, k, key=_INDEX)
            if at == len(reports) or reports[at][0] != k:
                continue
            _, value, error = reports[at]
            last = texts[k]
            texts[k] = _NO_TEXT if error is not None else value
            if error is None and last == value:
                drop.append(at)
        if not drop:
            return reports
        for at in sorted(drop, reverse=True):
            del reports[at]
        return reports

    def _finish_all(self, n: int) -> list[Change]:
        """Report every item; keeps the last tuples so that only the items whose value
        or status moved are rebuilt (reportMode "cycle" reports everything each read)."""
        plan = self._plan
        total = plan.n_items
        reported = self._reported
        if n == total or 2 * n >= total or not reported:
            # Most items are new: build every tuple in one go (a report of all items
            # holds the current value of each, so the rebuilt cache still mirrors C).
            values = plan.values()
            reported = list(zip(self._indexes, values, itertools.repeat(None), strict=False))
            if plan.n_errors:
                for k in plan.errors():
                    reported[k] = (k, None, self._reason(k, plan.status(k)))
            self._reported = reported
        elif n:
            status = plan.status_view
            for k in plan.changed(n):
                code = status[k]
                reported[k] = (k, None, self._reason(k, code)) if code else (k, plan.value(k), None)
        texts = self._texts
        if texts:
            for k in texts:
                _, value, error = reported[k]
                texts[k] = _NO_TEXT if error is not None else value
        return reported[:]

    def decode_values(self, block: Block) -> list[object]:
        """Every item's value (None where it failed); change tracking is not touched."""
        plan = self._plan
        plan.decode(block, _ffi.CODEC_MODE_VALUES)
        return plan.values()

    def errors(self) -> dict[int, str]:
        """Reasons of the items that failed in the last decode, by index."""
        plan = self._plan
        return {k: self._reason(k, plan.status(k)) for k in plan.errors()}

    def reset(self) -> None:
        """Forget the last reported values: the next decode reports every item."""
        self._plan.reset()
        self._reported = []
        for k in self._texts:
            self._texts[k] = _NO_TEXT
