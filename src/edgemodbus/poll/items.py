"""The state of a configured item and how a result is stored in it.

:class:`ItemState` is an item with its codec spec; :class:`Slot` is a planned read
with the items it decodes; :class:`Assembly` gathers an item larger than one block from
its pieces; :func:`set_item` stores a read result and
:func:`is_news` / :func:`holds` tell whether a result is news to the host.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import TYPE_CHECKING, Any

from ..codec import BlockDecoder, ValueSpec
from ..config import ParsedItem
from ..datatypes import Area, ItemStatus, enum_value
from .planner import Piece, ReadBlock

if TYPE_CHECKING:
    from ..config import DeviceAddressItem


@dataclass(frozen=True, slots=True)
class Kind:
    """What items of one area, bit, size and codec spec share (see ItemState)."""

    area: Area
    bit: int | None
    size: int
    spec: ValueSpec

    @staticmethod
    def of(area: Area, bit: int | None, size: int, spec: ValueSpec) -> Kind:
        kind = Kind(area, bit, size, spec)
        shared = _KINDS.get(kind)
        if shared is None:
            if len(_KINDS) >= _MAX_KINDS:  # sharing is an economy, not a registry
                _KINDS.clear()
            shared = _KINDS[kind] = kind
        return shared


_KINDS: dict[Kind, Kind] = {}
_MAX_KINDS = 4096


def shared_offset(offset: int) -> int:
    """``offset`` (0..65535) as one int object shared by every item at that offset.

    An int above 256 is 32 bytes of its own per item, and the items of a gateway's
    devices repeat the same offsets (devices of one kind, maps that start at 0): the
    first item at an offset lends its int to the others, kept in lists of 256 made on
    first use (2 KB each).  Other values come back as they are."""
    chunk_no, index = divmod(offset, _CHUNK)
    if not 0 <= chunk_no < len(_OFFSETS):
        return offset
    chunk = _OFFSETS[chunk_no]
    if chunk is None:
        chunk = _OFFSETS[chunk_no] = [None] * _CHUNK
    shared = chunk[index]
    if shared is None:
        shared = chunk[index] = offset
    return shared


_CHUNK = 256
_OFFSETS: list[list[int | None] | None] = [None] * (0x10000 // _CHUNK)


class ItemState:
    """A configured item with what the poller needs to read, decode and write it.

    Small, as a gateway holds one per tag: the item, its offset and a :class:`Kind`
    shared by every item of the same area, bit, size and codec spec."""

    __slots__ = ("item", "kind", "offset")

    def __init__(self, parsed: ParsedItem) -> None:
        # the ParsedItem itself is not kept
        self.item: DeviceAddressItem = parsed.item
        self.offset: int = shared_offset(parsed.address.offset)
        area = parsed.address.area
        self.kind = Kind.of(
            area,
            parsed.address.bit,
            1 if area.is_bit else parsed.registers,
            parsed.value_spec(name=""),
        )

    @property
    def area(self) -> Area:
        return self.kind.area

    @property
    def bit(self) -> int | None:
        return self.kind.bit

    @property
    def size(self) -> int:
        return self.kind.size

    @property
    def shape(self) -> ValueSpec:
        """The codec spec without the item's name, shared: what decoders are built
        from (a decoder names no item)."""
        return self.kind.spec

    @property
    def spec(self) -> ValueSpec:
        """The codec spec with the item's name (for writes, whose errors name it)."""
        return replace(self.kind.spec, name=self.item.name)

    def same_definition(self, other: ItemState) -> bool:
        return (self.item.name, self.offset, self.kind) == (
            other.item.name, other.offset, other.kind
        )

    def snapshot(self) -> dict[str, Any]:
        """The item's entry in ``driver.snapshot()``: Python values, as the item holds
        them (NaN, bytes, a datetime); JSON writers convert (codec/jsonable.py)."""
        item = self.item
        return {
            "address": item.address,
            "value": item.value,
            "status": str(enum_value(item.status)),
            "updateTs": item.update_ts.isoformat() if item.update_ts else None,
            "errorReason": item.error_reason,
        }


class Assembly:
    """Registers of an item larger than one block, gathered over several blocks.  One
    per item, shared by the slots of all its pieces; the item is decoded only when every
    piece arrived in the same cycle (``pieces``: item offset -> size, of ``cycle``)."""

    __slots__ = ("cycle", "decoder", "failed", "pieces", "registers", "state")

    def __init__(self, state: ItemState) -> None:
        self.state = state
        self.registers = [0] * state.size
        self.cycle = -1
        self.failed = -1  # the last cycle in which a piece failed
        self.pieces: dict[int, int] = {}
        self.decoder = BlockDecoder(state.area, state.size, [(0, state.shape)])

    def add(self, piece: Piece, values: list[int], cycle: int) -> bool:
        """Store a piece read in ``cycle``; True once all pieces of that cycle are in."""
        if cycle != self.cycle:
            self.cycle = cycle
            self.pieces.clear()
        start = piece.block_offset
        self.registers[piece.item_offset:piece.item_offset + piece.size] = values[
            start:start + piece.size
        ]
        self.pieces[piece.item_offset] = piece.size
        return sum(self.pieces.values()) == len(self.registers)  # pieces never overlap

    def fail(self, cycle: int) -> bool:
        """A piece failed in ``cycle``: what arrived in it cannot complete the item.
        False if another piece already failed in that cycle (the item is Invalid)."""
        first = self.failed != cycle
        self.failed = self.cycle = cycle
        self.pieces.clear()
        self.decoder.reset()  # the next complete read reports the item again
        return first


@dataclass(eq=False)
class Slot:
    """One planned read and how to decode it: its whole items through one decoder, and
    the pieces of larger items into their assemblies; when it is read next (see
    schedule.py)."""

    block: ReadBlock
    whole: list[ItemState]
    decoder: BlockDecoder | None
    partial: list[tuple[Piece, Assembly]]
    items: list[DeviceAddressItem] = field(init=False)  # whole[i].item, for the hot loop
    # the decoder was reset because an item was set from outside it (a write, a report):
    # its next reports are filtered by what the items hold (is_news)
    recheck: bool = field(default=False, init=False)
    period: float = field(init=False)  # the block's scan rate, in seconds
    due: float = field(default=0.0, init=False)  # monotonic time of its next read

    def __post_init__(self) -> None:
        self.items = [state.item for state in self.whole]
        self.period = self.block.rate / 1000


_OK = ItemStatus.OK
_INVALID = ItemStatus.INVALID
_RUNTIME_FIELDS = ("value", "status", "update_ts", "error_reason")


def set_item(
    item: DeviceAddressItem, value: Any, error: str | None, now: datetime
) -> DeviceAddressItem:
    """Store a read result: the value and Ok, or Invalid with the reason (the last good
    value stays).  Plain attribute writes: these runtime fields are not validated on
    assignment."""
    if error is None:
        item.value = value
        if item.status is not _OK:
            item.status = _OK
        if item.error_reason is not None:
            item.error_reason = None
    else:
        item.status = _INVALID
        item.error_reason = error
    item.update_ts = now
    return item


def _same(held: Any, value: Any) -> bool:
    """Whether an item's value is exactly ``value`` (same type; NaN matches NaN)."""
    return type(held) is type(value) and (held == value or (held != held and value != value))


def holds(item: DeviceAddressItem, value: Any, error: str | None) -> bool:
    """Whether ``item`` is already Ok with ``value``: a change the decoder sees against
    its own last report (e.g. after a confirmed write) that is no news to the host."""
    return error is None and item.status is _OK and _same(item.value, value)


def is_news(state: ItemState, value: Any, error: str | None) -> bool:
    """Whether a decoded result differs from what the item holds, as the change mode
    reports it: another error reason, or a value not exactly the held one and, for
    numbers with a deadband, more than the deadband away from it."""
    item = state.item
    if error is not None:
        return item.status is not _INVALID or item.error_reason != error
    if item.status is not _OK:
        return True
    held = item.value
    if _same(held, value):
        return False
    deadband = state.kind.spec.deadband
    if deadband and _is_number(held) and _is_number(value):
        return not abs(value - held) <= deadband
    return True


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def copy_runtime(src: DeviceAddressItem, dst: DeviceAddressItem) -> None:
    for name in _RUNTIME_FIELDS:
        setattr(dst, name, getattr(src, name))

