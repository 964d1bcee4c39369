"""The runtime state of a device's items: one :class:`ItemStore` per poller.

Parallel arrays indexed like the poller's items (``Poller.items[i]`` is index ``i``):
values (a list), statuses (a bytearray of codes) and marks (a list of ``(update time,
error reason)`` pairs, shared: every item a block read set holds the one pair of that
read, so the two fields cost one list entry per item, not two).  The line worker writes
them (one call per block read: :meth:`ItemStore.apply`); a bound
:class:`DeviceAddressItem` reads its fields here (config/item_model.py), so the
configuration is never written by the worker and nothing is copied per start.

Consistency: every write of an item's four fields, and every read of more than one field
(:meth:`ItemStore.reading`, :meth:`ItemStore.snapshot`), holds the store's lock, so a
reader on any thread never sees the value of one read with the status of another.  A
single field is one list or bytearray read (atomic under the GIL).  The lock is never
held while a callback runs.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from datetime import datetime
from operator import attrgetter
from typing import Any, Generic, Protocol, TypeVar

from ..config import MOVING, STATUSES, DeviceAddressItem, ItemReading
from ..datatypes import ItemStatus, enum_value


class StateLike(Protocol):
    """What the store needs of an item's state (poll/items.py's ItemState)."""

    @property
    def index(self) -> int: ...
    @property
    def item(self) -> DeviceAddressItem: ...

_CODE = {status: code for code, status in enumerate(STATUSES)}
UNKNOWN, OK, INVALID = 0, 1, 2  # codes of STATUSES
_ITEM = attrgetter("item")  # a state's DeviceAddressItem
_OKS = bytes((OK,)) * 2000  # the status of a block's items all Ok (a block's most: 2000 bits)
_new = tuple.__new__  # a NamedTuple without its Python-level __new__
Mark = tuple[datetime | None, str | None]
"""An item's update time and error reason, one pair shared by the items set together."""
_UNMARKED: Mark = (None, None)


class ItemInUseError(ValueError):
    """An item object is already polled by another running driver."""


S = TypeVar("S", bound=StateLike)


class ItemStore(Generic[S]):
    """The values, statuses, times and reasons of one device's items (see above)."""

    __slots__ = ("_names", "active", "lock", "marks", "states", "status", "values")

    def __init__(self, states: Sequence[S]) -> None:
        n = len(states)
        self.states = states  # the poller's items: states[i].index == i
        self.lock = threading.Lock()
        self.values: list[Any] = [None] * n
        self.status = bytearray(n)  # codes into STATUSES
        self.marks: list[Mark] = [_UNMARKED] * n  # (update time, error reason)
        self.active = False  # a running poller writes it
        self._names: dict[str, S] | None = None

    def __len__(self) -> int:
        return len(self.values)

    def by_name(self) -> dict[str, S]:
        """Name -> item state, made on first use (a write, an action): a device that is
        only read never pays for it (a dict entry per tag).  Any thread."""
        names = self._names
        if names is None:
            names = self._names = {state.item.name: state for state in self.states}
        return names

    def owns(self, state: S) -> bool:
        """Whether ``state`` is this store's (not one of a plan replaced since)."""
        index = state.index
        return index < len(self.states) and self.states[index] is state

    # -- reads (any thread) ---------------------------------------------------------------
    def reading(self, index: int) -> ItemReading:
        with self.lock:
            return _new(ItemReading, (self.values[index], STATUSES[self.status[index]],
                                      *self.marks[index]))

    def snapshot(self, states: Sequence[S] | None = None) -> dict[str, dict[str, Any]]:
        """Each item's entry of ``driver.snapshot()`` (Python values, as held: NaN,
        bytes, a datetime; JSON writers convert, codec/jsonable.py), all read at one
        moment; ``states``: only these (of this store)."""
        if states is None:
            states = self.states
        with self.lock:
            values, status, marks = self.values, self.status, self.marks
            entries = [(values[i], status[i], *marks[i])
                       for i in (state.index for state in states)]
        texts = [str(enum_value(s)) for s in STATUSES]
        return {
            state.item.name: {
                "address": state.item.address,
                "value": value,
                "status": texts[code],
                "updateTs": stamp.isoformat() if stamp else None,
                "errorReason": reason,
            }
            for state, (value, code, stamp, reason) in zip(states, entries, strict=True)
        }

    # -- writes ---------------------------------------------------------------------------
    def assign(self, index: int, which: int, value: Any) -> None:
        """A host's assignment to a runtime field (the compatibility path)."""
        with self.lock:
            if which == 0:
                self.values[index] = value
            elif which == 1:
                self.status[index] = _CODE[ItemStatus(value)]
            elif which == 2:
                self.marks[index] = (value, self.marks[index][1])
            else:
                self.marks[index] = (self.marks[index][0], value)

    def set(self, index: int, value: Any, error: str | None, now: datetime) -> None:
        """Store a result: the value and Ok, or Invalid with the reason (the last good
        value stays)."""
        with self.lock:
            if error is None:
                self.values[index] = value
                self.status[index] = OK
            else:
                self.status[index] = INVALID
            self.marks[index] = (now, error)

    def apply(self, whole: Sequence[S],
              changes: Sequence[tuple[int, Any, str | None]], now: datetime,
              reported: list[DeviceAddressItem]) -> None:
        """Store a block's change records (``(k, value, error)``: of its k-th whole
        item), stamped ``now``; the items set are appended to ``reported``.  The hot
        loop of a poll: the items set share one mark per reason (``(now, None)``)."""
        values, status, marks = self.values, self.status, self.marks
        ok: Mark = (now, None)
        failed: dict[str, Mark] = {}
        with self.lock:
            for k, value, error in changes:
                state = whole[k]
                i = state.index
                if error is None:
                    values[i] = value
                    status[i] = OK
                    marks[i] = ok
                else:
                    status[i] = INVALID
                    mark = failed.get(error)
                    if mark is None:
                        mark = failed[error] = (now, error)
                    marks[i] = mark
                reported.append(state.item)

    def apply_run(self, first: int, values: list[Any], now: datetime, whole: Sequence[S],
                  reported: list[DeviceAddressItem]) -> None:
        """Store good values of the items ``first``, ``first + 1``, ... (``whole``: a
        block read that changed every item, whose items' indices run on: Slot.first),
        stamped ``now``; their items are appended to ``reported``.  What :meth:`apply`
        does with ``(k, values[k], None)`` for every k, by slices (at C speed, one
        shared mark)."""
        end = first + len(values)
        if first < 0 or end > len(self.values):
            raise IndexError(f"items {first}..{end - 1} are outside the store of "
                             f"{len(self.values)} items")
        with self.lock:
            self.values[first:end] = values
            self.status[first:end] = _OKS[:len(values)] if len(values) <= len(_OKS) \
                else bytes((OK,)) * len(values)
            self.marks[first:end] = [(now, None)] * len(values)
        reported.extend(map(_ITEM, whole))

    # -- change tests (worker) ------------------------------------------------------------
    def holds(self, index: int, value: Any) -> bool:
        """Whether item ``index`` is already Ok with exactly ``value``."""
        return self.status[index] == OK and _same(self.values[index], value)

    def is_news(self, index: int, value: Any, error: str | None, deadband: float) -> bool:
        """Whether a decoded result differs from what item ``index`` holds, as the change
        mode reports it: another error reason, or a value not exactly the held one and,
        for numbers with a deadband, more than the deadband away from it."""
        code = self.status[index]
        if error is not None:
            return code != INVALID or self.marks[index][1] != error
        if code != OK:
            return True
        held = self.values[index]
        if _same(held, value):
            return False
        if deadband and _is_number(held) and _is_number(value):
            return not abs(value - held) <= deadband
        return True

    # -- binding --------------------------------------------------------------------------
    def bind(self, carry: Mapping[int, ItemReading] | None = None,
             previous: ItemStore[Any] | None = None) -> None:
        """Make each item read from this store, starting with what it held (or
        ``carry[i]``: the state of the item it replaces); ``previous`` is the store this
        one replaces (its items may move).  Raises :class:`ItemInUseError` when an item
        is polled by another running driver: nothing is bound then."""
        items = [state.item for state in self.states]
        check_free(items, (self, previous))
        readings = [item.reading for item in items]
        for i, reading in (carry or {}).items():
            readings[i] = reading
        # one pair per distinct time and reason (the very objects: ``readings`` holds them)
        shared: dict[tuple[int, int], Mark] = {(id(None), id(None)): _UNMARKED}
        with self.lock:
            for i, (value, status, stamp, reason) in enumerate(readings):
                self.values[i] = value
                self.status[i] = _CODE[status]
                mark = shared.get((id(stamp), id(reason)))
                if mark is None:
                    mark = shared[id(stamp), id(reason)] = (stamp, reason)
                self.marks[i] = mark
        for i, item in enumerate(items):  # the order a reader relies on (item.bound())
            item._store = MOVING
            item._index = shared_index(i)
            item._store = self
        self.active = True


def check_free(items: Sequence[DeviceAddressItem], mine: Sequence[object] = ()) -> None:
    """Raise :class:`ItemInUseError` for the first enabled item (``addressList[k]``) that
    a running driver's store other than ``mine`` holds (one item object is polled by one
    driver at a time)."""
    for k, item in enumerate(items):
        other = item._store
        if not item.is_enable:
            continue
        if isinstance(other, ItemStore) and other.active and not any(
                other is m for m in mine):
            raise ItemInUseError(
                f"addressList[{k}] {item.name!r}: this item object is polled by another "
                "running driver; give each driver its own items (item.model_copy())")


def _same(held: Any, value: Any) -> bool:
    """Whether ``held`` is exactly ``value`` (same type; NaN matches NaN)."""
    return type(held) is type(value) and (held == value or (held != held and value != value))


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def shared_index(i: int) -> int:
    """``i`` (0..65535) as one int object shared by every user of that number.

    An int above 256 is 32 bytes of its own, and the same numbers recur by the
    thousands (offsets of devices of one kind, store indices): the first user lends its
    int to the others, kept in lists of 256 made on first use (2 KB each).  Other values
    come back as they are."""
    chunk_no, at = divmod(i, _CHUNK)
    if not 0 <= chunk_no < len(_SHARED):
        return i
    chunk = _SHARED[chunk_no]
    if chunk is None:
        chunk = _SHARED[chunk_no] = [None] * _CHUNK
    shared = chunk[at]
    if shared is None:
        shared = chunk[at] = i
    return shared


_CHUNK = 256
_SHARED: list[list[int | None] | None] = [None] * (0x10000 // _CHUNK)
