"""The state of a configured item and how a result is stored in it.

:class:`ItemState` is an item with its codec spec; :class:`Slot` is a planned read
with the items it decodes; :class:`Assembly` gathers an item larger than one block from
its pieces; :func:`set_item` stores a read result and
:func:`is_news` / :func:`holds` tell whether a result is news to the host.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Any

from ..codec import BlockDecoder, ValueSpec
from ..codec import jsonable as _jsonable
from ..config import ParsedItem
from ..datatypes import Area, ItemStatus, enum_value
from .planner import Piece, ReadBlock

if TYPE_CHECKING:
    from ..config import DeviceAddressItem


class ItemState:
    """A configured item with what the poller needs to read, decode and write it."""

    __slots__ = ("area", "bit", "item", "offset", "size", "spec")

    def __init__(self, parsed: ParsedItem) -> None:
        # the ParsedItem itself is not kept: a gateway holds tens of thousands of these
        self.item: DeviceAddressItem = parsed.item
        self.area: Area = parsed.address.area
        self.offset: int = parsed.address.offset
        self.bit: int | None = parsed.address.bit
        self.size: int = 1 if self.area.is_bit else parsed.registers
        self.spec = ValueSpec(
            name=parsed.item.name,
            data_type=parsed.data_type,
            data_format=parsed.data_format,
            quantity=parsed.quantity,
            bit=parsed.address.bit,
            multiplier=parsed.multiplier,
            converted_type=parsed.converted_type,
            deadband=parsed.deadband or 0.0,
            encoding=parsed.encoding,
        )

    def same_definition(self, other: ItemState) -> bool:
        return (self.item.name, self.area, self.offset, self.spec) == (
            other.item.name, other.area, other.offset, other.spec
        )

    def snapshot(self) -> dict[str, Any]:
        item = self.item
        return {
            "address": item.address,
            "value": _jsonable(item.value),
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
        self.decoder = BlockDecoder(state.area, state.size, [(0, state.spec)])

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
    value stays).  Writes the item's ``__dict__`` directly: these runtime fields are not
    validated on assignment, and pydantic's ``__setattr__`` (with its fields-set
    bookkeeping) costs several times more on the hot path and memory per item."""
    fields = item.__dict__
    if error is None:
        fields["value"] = value
        if fields["status"] is not _OK:
            fields["status"] = _OK
        if fields["error_reason"] is not None:
            fields["error_reason"] = None
    else:
        fields["status"] = _INVALID
        fields["error_reason"] = error
    fields["update_ts"] = now
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
    deadband = state.spec.deadband
    if deadband and _is_number(held) and _is_number(value):
        return not abs(value - held) <= deadband
    return True


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def copy_runtime(src: DeviceAddressItem, dst: DeviceAddressItem) -> None:
    for name in _RUNTIME_FIELDS:
        dst.__dict__[name] = src.__dict__[name]

