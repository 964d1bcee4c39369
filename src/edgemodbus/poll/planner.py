"""Read planner: items -> as few read requests (blocks) as the merge rules allow.

Pure and I/O-free.  Each slave has its own poller, whose ``build_plan`` filters out
disabled items before calling :func:`plan_reads`; the planner only knows areas, offsets
and sizes.

Rules: per area and scan rate, items sorted by offset (ties keep input order); a block grows while
``next.offset - block.end <= max_gap`` (end exclusive, so contiguous items have gap 0
and overlapping items share registers) and its span stays within the limit
(``max_registers`` capped at 125, ``max_bits`` capped at 2000: protocol/limits.py).
``continuous`` forces gap 0.  Areas never merge (FC03 and FC04 are different areas), nor do items of
different scan rates (``rate``, the item's readCycle in ms): each block carries its
rate, and the poller keeps a due time per block.  An item larger than the limit gets
blocks of its own and is read in pieces; its :class:`Piece` entries say how to
reassemble it.  Output order: by area value, then start, then rate.
"""

from __future__ import annotations

from array import array
from collections.abc import Collection, Hashable, Iterable
from dataclasses import dataclass
from operator import itemgetter
from typing import cast

from ..datatypes import Area
from ..protocol.limits import MAX_ADDRESS, MAX_READ_BITS, MAX_READ_REGISTERS

_ADDRESS_SPACE = MAX_ADDRESS + 1


@dataclass(frozen=True, slots=True)
class PlanItem:
    """One thing to read: ``size`` registers (register areas) or bits from ``offset``,
    every ``rate`` ms (its scan rate; the planner only compares rates)."""

    key: Hashable
    area: Area
    offset: int
    size: int
    rate: int = 0


@dataclass(frozen=True, slots=True)
class Piece:
    """Registers ``[item_offset, item_offset + size)`` of item ``key`` are at
    ``block_offset`` inside the block.  A whole item is one piece with item_offset 0."""

    key: Hashable
    item_offset: int
    block_offset: int
    size: int


class ReadBlock:
    """One read request: ``count`` registers/bits of ``area`` from ``start``, made every
    ``rate`` ms (the scan rate shared by all its items).  Immutable, compared by value.

    A gateway holds one :class:`Piece` per configured tag, read only when a plan is
    installed or a block is split: the pieces are kept as compact int arrays (the keys
    too when they are ints, the poller's case) and :attr:`pieces` builds the
    :class:`Piece` objects on demand."""

    __slots__ = ("_keys", "_layout", "area", "count", "rate", "start")

    area: Area
    start: int
    count: int
    rate: int
    _keys: array[int] | tuple[Hashable, ...]
    _layout: array[int]  # item_offset, block_offset, size of each piece, in turn

    def __init__(
        self, area: Area, start: int, count: int, pieces: Iterable[Piece], rate: int = 0
    ) -> None:
        keys: list[Hashable] = []
        layout: list[int] = []
        for p in pieces:
            keys.append(p.key)
            layout += (p.item_offset, p.block_offset, p.size)
        init = object.__setattr__
        init(self, "area", area)
        init(self, "start", start)
        init(self, "count", count)
        init(self, "rate", rate)
        init(self, "_keys", _compact_keys(keys))
        init(self, "_layout", _compact(layout))

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"ReadBlock is immutable: cannot set {name!r}")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"ReadBlock is immutable: cannot delete {name!r}")

    @property
    def pieces(self) -> tuple[Piece, ...]:
        """Where each item (or piece of a large item) lies in the block, in plan order."""
        it = iter(self._layout)
        return tuple(Piece(key, item_offset, block_offset, size)
                     for key, item_offset, block_offset, size in zip(self._keys, it, it, it,
                                                                     strict=True))

    @property
    def keys(self) -> tuple[Hashable, ...]:
        return tuple(self._keys)

    @property
    def end(self) -> int:
        """First address after the block (exclusive)."""
        return self.start + self.count

    def _fields(self) -> tuple[Area, int, int, tuple[Piece, ...], int]:
        return self.area, self.start, self.count, self.pieces, self.rate

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ReadBlock):
            return NotImplemented
        return self._fields() == other._fields()

    def __hash__(self) -> int:
        return hash(self._fields())

    def __reduce__(self) -> tuple[type[ReadBlock], tuple[Area, int, int, tuple[Piece, ...], int]]:
        return ReadBlock, self._fields()  # copy and pickle through __init__

    def __repr__(self) -> str:
        return (f"ReadBlock(area={self.area!r}, start={self.start!r}, count={self.count!r}, "
                f"pieces={self.pieces!r}, rate={self.rate!r})")


def _compact_keys(keys: list[Hashable]) -> array[int] | tuple[Hashable, ...]:
    """The keys as an int array when they are all plain ints (no int object per piece
    kept alive), else as a tuple."""
    if all(type(k) is int for k in keys):
        try:
            return _compact(cast(list[int], keys))
        except OverflowError:
            pass
    return tuple(keys)


def _compact(values: list[int]) -> array[int]:
    """``values`` in the narrowest of a 16- or 64-bit array (offsets and item indices of
    a device fit 16 bits); OverflowError if they fit neither."""
    try:
        return array("H", values)
    except OverflowError:
        return array("q", values)


@dataclass(frozen=True, slots=True)
class Limits:
    """Effective merge limits: span caps per kind of area and the allowed gap."""

    registers: int
    bits: int
    gap: int

    def span(self, area: Area) -> int:
        return self.bits if area.is_bit else self.registers


def make_limits(
    max_registers: int = 120,
    max_bits: int = MAX_READ_BITS,
    max_gap: int = 10,
    continuous: bool = False,
) -> Limits:
    """Validate the settings and apply the protocol caps (125 registers, 2000 bits)."""
    if max_registers < 1:
        raise ValueError(f"max_registers {max_registers}: must be at least 1")
    if max_bits < 1:
        raise ValueError(f"max_bits {max_bits}: must be at least 1")
    if max_gap < 0:
        raise ValueError(f"max_gap {max_gap}: must be 0 or more")
    return Limits(
        min(max_registers, MAX_READ_REGISTERS),
        min(max_bits, MAX_READ_BITS),
        0 if continuous else max_gap,
    )


# A run of (key, item_offset, absolute start, size) segments, sorted by start.
_Segment = tuple[Hashable, int, int, int]


def _merge(
    area: Area, segments: list[_Segment], span: int, gap: int, rate: int
) -> list[ReadBlock]:
    """Greedy merge of segments sorted by start; every segment fits within ``span``."""
    blocks: list[ReadBlock] = []
    append = blocks.append
    start = end = -_ADDRESS_SPACE - 1  # no open block: any segment fails the gap test
    pieces: list[Piece] = []
    for key, item_offset, seg_start, size in segments:
        seg_end = seg_start + size
        new_end = seg_end if seg_end > end else end
        if seg_start - end <= gap and new_end - start <= span:
            end = new_end
        else:
            if pieces:
                append(ReadBlock(area, start, end - start, tuple(pieces), rate))
            start, end, pieces = seg_start, seg_end, []
        pieces.append(Piece(key, item_offset, seg_start - start, size))
    if pieces:
        append(ReadBlock(area, start, end - start, tuple(pieces), rate))
    return blocks


def _oversized(
    area: Area, key: Hashable, offset: int, size: int, span: int, rate: int
) -> list[ReadBlock]:
    """Blocks of their own for an item larger than one block, in pieces of ``span``."""
    return [
        ReadBlock(area, offset + done, n, (Piece(key, done, 0, n),), rate)
        for done in range(0, size, span)
        for n in (min(span, size - done),)
    ]


def plan_reads(
    items: Iterable[PlanItem],
    *,
    max_registers: int = 120,
    max_bits: int = MAX_READ_BITS,
    max_gap: int = 10,
    continuous: bool = False,
) -> list[ReadBlock]:
    """Plan the read requests that cover every item exactly once (see module doc).

    ``items`` must have distinct keys and lie within 0..65535; the poller passes only
    enabled items.  Raises ValueError for a bad item or setting.
    """
    limits = make_limits(max_registers, max_bits, max_gap, continuous)
    span_of = {area: limits.span(area) for area in Area}
    groups: dict[tuple[Area, int], list[_Segment]] = {}  # (area, rate) -> segments
    blocks: list[ReadBlock] = []
    seen: set[Hashable] = set()
    for item in items:
        key, area, offset, size, rate = item.key, item.area, item.offset, item.size, item.rate
        if key in seen:
            raise ValueError(f"plan item {key!r}: duplicate key")
        seen.add(key)
        if size < 1 or offset < 0 or offset + size > _ADDRESS_SPACE:
            raise ValueError(
                f"plan item {key!r}: offset {offset} size {size} must lie within 0..65535"
            )
        span = span_of[area]
        if size > span:
            blocks.extend(_oversized(area, key, offset, size, span, rate))
        else:
            group = groups.get((area, rate))
            if group is None:
                group = groups[(area, rate)] = []
            group.append((key, 0, offset, size))
    for (area, rate), segments in groups.items():
        segments.sort(key=_segment_start)  # stable: ties keep input order
        blocks.extend(_merge(area, segments, span_of[area], limits.gap, rate))
    blocks.sort(key=_block_order)
    return blocks


_segment_start = itemgetter(2)


def _block_order(block: ReadBlock) -> tuple[int, int, int]:
    return block.area.value, block.start, block.rate


def split_block(
    block: ReadBlock,
    bad_keys: Collection[Hashable],
    *,
    max_registers: int = 120,
    max_bits: int = MAX_READ_BITS,
    max_gap: int = 10,
    continuous: bool = False,
) -> list[ReadBlock]:
    """Give each bad key's piece a block of its own and re-plan the block's other pieces
    (same limits) in as few blocks as possible.  Keys not in the block are ignored; the
    blocks keep the block's rate."""
    limits = make_limits(max_registers, max_bits, max_gap, continuous)
    isolated: list[ReadBlock] = []
    rest: list[_Segment] = []
    for p in block.pieces:
        start = block.start + p.block_offset
        if p.key in bad_keys:
            isolated.append(ReadBlock(block.area, start, p.size,
                                      (Piece(p.key, p.item_offset, 0, p.size),), block.rate))
        else:
            rest.append((p.key, p.item_offset, start, p.size))
    rest.sort(key=_segment_start)
    blocks = isolated + _merge(block.area, rest, limits.span(block.area), limits.gap,
                               block.rate)
    blocks.sort(key=_block_order)
    return blocks


def _shrink(block: ReadBlock, indexes: list[int]) -> ReadBlock:
    """A block over exactly the span of the given pieces of ``block`` (kept in order)."""
    pieces = [block.pieces[i] for i in sorted(indexes)]
    first = min(p.block_offset for p in pieces)
    last = max(p.block_offset + p.size for p in pieces)
    return ReadBlock(
        block.area,
        block.start + first,
        last - first,
        tuple(Piece(p.key, p.item_offset, p.block_offset - first, p.size) for p in pieces),
        block.rate,
    )


def bisect_block(block: ReadBlock) -> list[ReadBlock]:
    """Split a block of several pieces into two blocks of about half the pieces each
    (by position), each shrunk to its pieces' span.  The poller recurses on a block
    answered with exception 02 until the bad single items are found.  A block of one
    piece comes back alone, unchanged."""
    pieces = block.pieces
    if len(pieces) < 2:
        return [block]
    by_position = sorted(range(len(pieces)), key=lambda i: (pieces[i].block_offset, i))
    half = (len(by_position) + 1) // 2
    return [_shrink(block, by_position[:half]), _shrink(block, by_position[half:])]
