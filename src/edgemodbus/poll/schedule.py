"""Scan rates: which items are read how often, and when each planned read is due.

Every item is read at its own rate (the item's readCycle, else the device's); the
planner never merges items of different rates, so every block has one rate and the
poller keeps a due time per block (:class:`~edgemodbus.poll.items.Slot`).  A device's
*pass* (what its counters call a cycle, and what the batch callback, the failed-cycle
count and the backoff count) is one pass over the blocks due when it begins.  With every
item at the device's rate every pass reads every block, as a cycle always did.

An item at rate 0 is not polled (updated by wrapped reports only), like a device at
readCycle 0.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..config import DriverModbusRtuParameter, ParsedItem
from .items import Slot
from .planner import PlanItem, ReadBlock, plan_reads

JOIN = 0.005
"""A block due at most this much (and a tenth of its period) after a pass begins is read
in that pass: blocks whose rates are multiples of each other stay in step instead of
drifting into passes of their own by the worker's latency."""


def item_rate(parsed: ParsedItem, params: DriverModbusRtuParameter) -> int:
    """The item's scan rate in ms: its own readCycle, else the device's (0 = not polled)."""
    own = parsed.item.read_cycle
    return params.read_cycle if own is None else own


def build_plan(items: Sequence[ParsedItem], params: DriverModbusRtuParameter) -> list[ReadBlock]:
    """The read blocks of a device's enabled, polled items; piece keys index ``items``."""
    plan_items = []
    for i, p in enumerate(items):
        rate = item_rate(p, params)
        if p.item.is_enable and rate > 0:
            size = 1 if p.address.area.is_bit else p.registers
            plan_items.append(PlanItem(i, p.address.area, p.address.offset, size, rate))
    return plan_reads(
        plan_items,
        max_registers=params.max_block_read_register_count,
        max_bits=params.max_block_read_bit_count,
        max_gap=params.max_merge_address_gap,
        continuous=params.is_block_read_require_address_continuous,
    )


def due_slots(slots: Sequence[Slot], now: float) -> list[Slot]:
    """The slots a pass beginning at ``now`` reads, in plan order."""
    return [s for s in slots if s.due - now <= min(s.period * 0.1, JOIN)]


def reschedule(done: Sequence[Slot], start: float, now: float) -> bool:
    """Set the next due time of the slots of a pass that began at ``start`` and ends at
    ``now``: one period after the start, or now if the pass took longer than a slot's
    period (no burst of catch-up reads).  True if any slot overran."""
    elapsed = now - start
    overran = False
    for slot in done:
        if elapsed > slot.period:
            overran = True
            slot.due = now
        else:
            slot.due = start + slot.period
    return overran


def next_due(slots: Sequence[Slot]) -> float:
    """When the first of ``slots`` (not empty) is due."""
    return min(s.due for s in slots)
