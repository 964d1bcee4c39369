"""The state of a configured item and how a result is stored in it.

:class:`ItemState` is an item with its codec spec; :class:`Slot` is a planned read
with the items it decodes; :class:`Assembly` gathers an item larger than one block from
its pieces; :func:`set_state` stores a result in the poller's store (store.py) and
:func:`is_news` / :func:`holds` tell whether a result is news to the host.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import TYPE_CHECKING, Any

from ..codec import BlockDecoder, ValueSpec
from ..config import ParsedItem
from ..datatypes import Area
from .planner import Piece, ReadBlock
from .store import ItemStore, shared_index

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


shared_offset = shared_index  # an offset (0..65535) as one shared int


class ItemState:
    """A configured item with what the poller needs to read, decode and write it.

    Small, as a gateway holds one per tag: the item, its offset, a :class:`Kind`
    shared by every item of the same area, bit, size and codec spec, and its index in
    the poller's items and store (store.py)."""

    __slots__ = ("index", "item", "kind", "offset")

    def __init__(self, parsed: ParsedItem, index: int = 0) -> None:
        # the ParsedItem itself is not kept
        self.item: DeviceAddressItem = parsed.item
        self.index: int = shared_index(index)
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


@dataclass(eq=False, slots=True)
class Slot:
    """One planned read and how to decode it: its whole items through one decoder, and
    the pieces of larger items into their assemblies; when it is read next (see
    schedule.py)."""

    block: ReadBlock
    whole: list[ItemState]
    decoder: BlockDecoder | None
    partial: list[tuple[Piece, Assembly]]
    # the decoder was reset because an item was set from outside it (a write, a report):
    # its next reports are filtered by what the items hold (is_news)
    recheck: bool = field(default=False, init=False)
    # the store index of whole[0] when the whole items' indices run on from it
    # (whole[k].index == first + k), else -1: a read that changed every item is then
    # stored by slices (ItemStore.apply_run), not item by item
    first: int = field(default=-1, init=False)
    period: float = field(init=False)  # the block's scan rate, in seconds
    due: float = field(default=0.0, init=False)  # monotonic time of its next read

    def __post_init__(self) -> None:
        self.period = self.block.rate / 1000
        whole = self.whole
        if whole and all(state.index == whole[0].index + k for k, state in enumerate(whole)):
            self.first = whole[0].index


def store_changes(store: ItemStore[ItemState], slot: Slot, decoder: BlockDecoder, n: int,
                  now: datetime, reported: list[DeviceAddressItem]) -> None:
    """Store the changes of the usual read of ``slot`` (change mode, no pieces, no
    recheck) whose decode returned ``n``, stamped ``now``; the items set are appended
    to ``reported``.  A read that changed every item, all good, is stored by slices
    when the items' indices run on (Slot.first): no tuple per item."""
    whole = slot.whole  # the decoder's items, in its order
    values = decoder.finish_every(n) if n == len(whole) and slot.first >= 0 else None
    if values is not None:
        store.apply_run(slot.first, values, now, whole, reported)
    else:
        store.apply(whole, decoder.finish(n, False), now, reported)


def set_state(store: ItemStore[ItemState], state: ItemState, value: Any, error: str | None,
              now: datetime) -> DeviceAddressItem:
    """Store a result of ``state``'s item: the value and Ok, or Invalid with the reason
    (the last good value stays); its item back."""
    store.set(state.index, value, error, now)
    return state.item


def holds(store: ItemStore[ItemState], state: ItemState, value: Any) -> bool:
    """Whether the item is already Ok with ``value``: a change the decoder sees against
    its own last report (e.g. after a confirmed write) that is no news to the host."""
    return store.holds(state.index, value)


def is_news(store: ItemStore[ItemState], state: ItemState, value: Any, error: str | None) -> bool:
    """Whether a decoded result differs from what the item holds (ItemStore.is_news,
    with the item's deadband)."""
    return store.is_news(state.index, value, error, state.kind.spec.deadband)


def owner_of(state: ItemState, slots: Sequence[Slot],
             assemblies: Mapping[ItemState, Assembly]) -> Slot | Assembly | None:
    """What decodes ``state`` in the plan of ``slots`` (its assembly, for an item read
    in pieces; None: none).  A search, as only writes and reports ask: a dict would be a
    tag's largest part."""
    asm = assemblies.get(state)
    if asm is not None:
        return asm
    area, offset = state.area, state.offset
    for slot in slots:
        block = slot.block
        if block.area is area and block.start <= offset < block.start + block.count \
                and any(s is state for s in slot.whole):
            return slot
    return None
