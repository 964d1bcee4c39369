"""Wrapped reports (edge MCUs that push frames unasked, see protocol/wrapped.py): which
items of a slave lie inside a report, and how a report sets them.

Two paths, one rule: a report sets the items of its slave whose registers (or bits) lie
wholly inside it, each to its decoded result when that is news against what the item
holds (with its deadband), in the order the frames came on the wire.

- In C (csrc/emb_report.c): a report inside one polled block whose range holds that
  block's items only (:meth:`ReportDecoders.spans`) is decoded by the engine into the
  block's own plan, with its change tracking, and the poller takes the items it changed
  with the pass's changes (:func:`store_taken`): no object per report.
- In Python (:meth:`ReportDecoders.decode`, Poller.on_report): every other report (across
  blocks, outside them, on a device that reports every item, or one the engine could not
  apply in order), the reference the C path is tested against.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from datetime import datetime
from typing import TYPE_CHECKING, Any

from .._ffi import Block
from ..codec import BlockDecoder, Change
from ..datatypes import Area
from .items import ItemState, Slot, is_news
from .store import ItemStore

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..protocol.wrapped import Report

_REPORT_AREAS = {area.read_function: area for area in Area}  # FC01-04 of a report


class ReportDecoders:
    """Decodes the reports of one slave: one decoder per (function, address, count)
    seen, built on first use over the items the report covers."""

    def __init__(self, items: Sequence[ItemState]) -> None:
        self._items = items
        self._decoders: dict[tuple[int, int, int],
                             tuple[list[ItemState], BlockDecoder | None]] = {}
        # per area: the items by offset, and their offsets (spans(), made on first use)
        self._by_offset: dict[Area, tuple[list[ItemState], list[int]]] | None = None

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

    def news(self, report: Report, store: ItemStore[ItemState], report_all: bool
             ) -> list[tuple[ItemState, Any, str | None]] | None:
        """The items of ``report`` to set, with their results: those whose result is
        news against what they hold (every one with ``report_all``); None: the report
        holds no item."""
        decoded = self.decode(report)
        if decoded is None:
            return None
        return [(state, value, error) for state, (_, value, error) in decoded
                if report_all or is_news(store, state, value, error)]

    def spans(self, slot: Slot) -> tuple[int, ...] | None:
        """What the engine needs to apply reports inside ``slot``'s block in C: per whole
        item of the block (its decoder's order), its offset in the block and its size,
        flat.  None when a report there would set other items too (the block's range
        holds items it does not decode whole: pieces of larger items, items of another
        scan rate, read on demand or only reported), or the block decodes nothing."""
        block = slot.block
        if slot.partial or slot.decoder is None:
            return None
        start, end = block.start, block.start + block.count
        states, offsets = self._sorted().get(block.area, ([], []))
        inside = {id(s) for s in states[bisect.bisect_left(offsets, start):
                                        bisect.bisect_left(offsets, end)]
                  if s.offset + s.size <= end}
        whole = slot.whole
        if len(inside) != len(whole) or any(id(s) not in inside for s in whole):
            return None
        return tuple(x for s in whole for x in (s.offset - start, s.size))

    def _sorted(self) -> dict[Area, tuple[list[ItemState], list[int]]]:
        by_offset = self._by_offset
        if by_offset is None:
            by_offset = {}
            for state in sorted(self._items, key=lambda s: s.offset):
                entry = by_offset.setdefault(state.area, ([], []))
                entry[0].append(state)
                entry[1].append(state.offset)
            self._by_offset = by_offset
        return by_offset


def store_taken(taken: Sequence[tuple[int, int]], slots: Sequence[Slot],
                store: ItemStore[ItemState], now: datetime,
                reported: list[DeviceAddressItem]) -> None:
    """Store what the engine's decodes of wrapped reports changed (``taken``: (block,
    the decode's count), from EngineDevice.take_reports), stamped ``now``: the items
    whose result is news against what they hold, as :meth:`Poller.on_report` keeps;
    the items set are appended to ``reported``.  A change the block's tracking saw
    that is no news to the item (its decoder had been reset, or the value moved within
    the deadband of what the item holds) leaves the decoder out of step with the
    item: it is reset, and its next reads filtered (``Slot.recheck``), as after a
    report applied in Python."""
    for k, n in taken:
        slot = slots[k]
        decoder = slot.decoder
        if decoder is None:  # (the engine applies reports to decoding blocks only)
            continue
        whole = slot.whole
        news: list[Change] = []
        stale = False
        for change in decoder.finish(n, False):
            state = whole[change[0]]
            if is_news(store, state, change[1], change[2]):
                news.append(change)
            elif change[2] is None and not store.holds(state.index, change[1]):
                stale = True
        if news:
            store.apply(whole, news, now, reported)
        if stale:
            decoder.reset()
            slot.recheck = True
