"""Reads on demand: items (or a whole device) read now, as a job on the line's queue.

A read job (``driver.read_now``, the MQTT and Sparkplug read commands) runs on the line
worker like a write (line/jobs.py; ``reads=True``: it changes nothing on the slave, so
forwarded-read coalescing keeps its data).  It reads the blocks that hold the items
asked for: their polled blocks, or for on-demand items (``readCycle: "demand"``) the
blocks planned for them (schedule.build_plan ``demand=True``), which nothing else reads.
Each block goes through its own decoder, reporting every item (a fresh value is
reported even when unchanged: it answers a request); the decoder remembers what it
reported, so the next poll of that block reports only what changed since.  The items
asked for are reported in one batch through the normal delivery (poll/sink.py), so
callbacks, MQTT and Sparkplug publish them; other items of the same blocks are
reported only when they changed.  A failed read sets the items Invalid with the reason,
as a failed poll does, and the job still answers with them.

Reads are commands from a broker too, so a storm of them is bounded here before the line
(which bounds its jobs) sees it: a read of items that a queued read (not started yet) of
the same device will read anyway joins that one (:class:`DemandReads`): a thousand
``$read`` of one item cost the line one job, and each joined read answers with the
values of that job, read after it was asked for.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from .._ffi import Block
from ..codec import Change
from ..errors import ModbusConnectionError, ModbusError
from .items import Assembly, ItemState, Slot, is_news, set_state

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..line import Link
    from ..stats import DeviceStats
    from .store import ItemStore


def slots_holding(slots: Sequence[Slot], wanted: set[ItemState]) -> list[Slot]:
    """The slots that read any of ``wanted`` (whole, or a piece of it), in plan order."""
    return [slot for slot in slots
            if any(s in wanted for s in slot.whole)
            or any(asm.state in wanted for _, asm in slot.partial)]


def read_slots(link: Link, slave: int, store: ItemStore[ItemState], slots: Sequence[Slot],
               wanted: set[ItemState], counters: DeviceStats,
               token: int) -> list[DeviceAddressItem]:
    """Read ``slots`` now and store what they hold: the items of ``wanted`` always,
    the others when they changed; returns the items set, for one report.  ``token``
    numbers this read for the assemblies of large items (pieces of one read only).
    A link that is down raises ModbusConnectionError; other failures make the items
    of the failed block Invalid."""
    now = datetime.now(timezone.utc)
    reported: list[DeviceAddressItem] = []
    for slot in slots:
        block = slot.block
        counters.requests += 1
        changes: list[Change] = []
        try:
            data = link.read(slave, block.area, block.start, block.count)
            if slot.decoder is not None:
                changes = slot.decoder.decode(data, True)  # every item: it answers a request
        except ModbusConnectionError:
            raise
        except ModbusError as exc:
            _failed(store, slot, str(exc), wanted, now, token, reported)
            continue
        counters.responses += 1
        for index, value, error in changes:
            state = slot.whole[index]
            if state in wanted or is_news(store, state, value, error):
                reported.append(set_state(store, state, value, error, now))
        if slot.partial:
            values = data.to_list()
            for piece, asm in slot.partial:
                if asm.add(piece, values, token):
                    _assembled(store, asm, wanted, now, reported)
        _forget(slot)
    return reported


def _forget(slot: Slot) -> None:
    """The decoders of ``slot`` remember this read, also the values of items it did not
    set (within their deadband of what they hold): make the next poll compare with what
    the items hold instead, as after a write (the poller's ``_recheck``), so a slow drift
    past a deadband is not hidden by a read on demand."""
    if slot.decoder is not None:
        slot.decoder.reset()
        slot.recheck = True
    for _, asm in slot.partial:
        asm.decoder.reset()


def _assembled(store: ItemStore[ItemState], asm: Assembly, wanted: set[ItemState],
               now: datetime, reported: list[DeviceAddressItem]) -> None:
    state = asm.state
    block = Block.from_values(asm.registers, bits=False)
    for _, value, error in asm.decoder.decode(block, True):
        if state in wanted or is_news(store, state, value, error):
            reported.append(set_state(store, state, value, error, now))


def _failed(store: ItemStore[ItemState], slot: Slot, reason: str, wanted: set[ItemState],
            now: datetime, token: int, reported: list[DeviceAddressItem]) -> None:
    """A block of the read failed: its items Invalid with ``reason`` (reported when
    asked for or when that is news), its decoder told to report them again."""
    states = slot.whole + [asm.state for _, asm in slot.partial if asm.fail(token)]
    for state in states:
        if state in wanted or is_news(store, state, None, reason):
            reported.append(set_state(store, state, None, reason, now))
    if slot.decoder is not None:
        slot.decoder.reset()


def answer(store: ItemStore[ItemState],
           states: Sequence[ItemState]) -> dict[str, dict[str, Any]]:
    """What a read job answers: each item's snapshot entry (value, status, updateTs,
    errorReason), by name, read at one moment."""
    return store.snapshot(states)



Answer = dict[str, dict[str, Any]]
"""What a read answers: each item's snapshot entry by name."""


class DemandReads:
    """One device's reads on demand that wait on its line, not started yet, by the items
    they read (None: every item).  A new read joins a waiting read of the same items or
    of every item (its future answers with its own items only), counted in the
    device's ``readsCoalesced``; else it queues a job.  ``token`` numbers the reads for
    the assemblies of large items (read_slots)."""

    def __init__(self, counters: DeviceStats) -> None:
        self._counters = counters
        self._lock = threading.RLock()  # (an RLock: queueing never waits for the worker)
        self._waiting: dict[frozenset[str] | None, Future[Answer]] = {}
        self.token = 0

    def submit(self, names: Sequence[str] | None,
               queue: Callable[[Callable[[], None]], Future[Answer]]) -> Future[Answer]:
        """A future of the read of ``names``: a waiting read's, or the one ``queue``
        makes (``queue(started)`` queues the job, which calls ``started()`` first: from
        then on a new read needs a new job, its values read after it was asked)."""
        key = None if names is None else frozenset(names)
        with self._lock:
            for held in (key, None):
                base = self._waiting.get(held)
                if base is not None and not base.done():
                    self._counters.reads_coalesced += 1
                    return _part(base, names)
            base = queue(lambda: self._started(key))
            if not base.done():
                self._waiting[key] = base
            return _part(base, names)

    def _started(self, key: frozenset[str] | None) -> None:
        with self._lock:
            self._waiting.pop(key, None)


def _part(base: Future[Answer], names: Sequence[str] | None) -> Future[Answer]:
    """A future of ``base``'s answer for ``names`` (None: all of it), its own (a caller
    that cancels it cancels no other's)."""
    part: Future[Answer] = Future()

    def done(finished: Future[Answer]) -> None:
        if not part.set_running_or_notify_cancel():
            return
        if finished.cancelled():
            part.set_exception(ModbusError("the read was cancelled"))
        elif (exc := finished.exception()) is not None:
            part.set_exception(exc)
        else:
            result = finished.result()
            part.set_result(result if names is None else
                            {n: result[n] for n in dict.fromkeys(names) if n in result})

    base.add_done_callback(done)
    return part
