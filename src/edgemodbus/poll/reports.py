"""Wrapped reports (edge MCUs that push frames unasked, see protocol/wrapped.py): which
items of a slave lie inside a report, and their decoder, per report shape."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from .._ffi import Block
from ..codec import BlockDecoder, Change
from ..datatypes import Area
from .items import ItemState

if TYPE_CHECKING:
    from ..protocol.wrapped import Report

_REPORT_AREAS = {area.read_function: area for area in Area}  # FC01-04 of a report


class ReportDecoders:
    """Decodes the reports of one slave: one decoder per (function, address, count)
    seen, built on first use over the items the report covers."""

    def __init__(self, items: Sequence[ItemState]) -> None:
        self._items = items
        self._decoders: dict[tuple[int, int, int],
                             tuple[list[ItemState], BlockDecoder | None]] = {}

    def decode(self, report: Report) -> list[tuple[ItemState, Change]] | None:
        """Every item inside ``report`` with its decoded result (None: the report holds
        no item: an exception, a write's echo, registers nobody configured)."""
        area = _REPORT_AREAS.get(report.function)
        if area is None:
            return None
        values = report.bits if area.is_bit else report.registers
        key = (report.function, report.address, len(values))
        entry = self._decoders.get(key)
        if entry is None:
            start, end = report.address, report.address + len(values)
            states = [s for s in self._items
                      if s.area is area and start <= s.offset and s.offset + s.size <= end]
            decoder = BlockDecoder(area, len(values), [(s.offset - start, s.shape)
                                                       for s in states]) if states else None
            entry = self._decoders[key] = (states, decoder)
        states, decoder = entry
        if decoder is None:
            return None
        # every item of the report: the caller keeps what is news against the item (it
        # may have been set by a poll since), the decoder's own tracking knows reports only
        decoded = decoder.decode(Block.from_values(values, bits=area.is_bit), True)
        return [(states[c[0]], c) for c in decoded]
