"""Read plans shared between devices with the same address list and planner options.

:func:`shared_plan` is :func:`~edgemodbus.poll.planner.plan_reads` behind a bounded
cache (codec/shared.py), keyed by its whole input: every planned item (its key, area,
offset, size and rate) and the four planner options.  A template used by 5,000 DTUs is
planned once; the :class:`~edgemodbus.poll.planner.ReadBlock` objects are immutable, so
the devices share them (docs/scale.md, "Starting thousands of devices").  The cache
holds the ``keep`` most recently used plans (a list of blocks has no weak reference):
the key is as large as the plan, so the bound is its memory.  The poller's items (keys
that are ints: item indexes) are keyed by their fields packed in arrays, 17 bytes an
item, not by the PlanItem objects (about 100 bytes an item, held by the 64 kept keys:
docs/item-store.md, "Memory").
"""

from __future__ import annotations

from array import array
from collections.abc import Hashable, Sequence
from typing import cast

from ..codec.shared import SharedCache
from .planner import PlanItem, ReadBlock, plan_reads

PLANS: SharedCache[tuple[ReadBlock, ...]] = SharedCache(keep=64, weak=False)


def plan_key(items: Sequence[PlanItem]) -> Hashable:
    """What identifies a list of planned items: their fields packed (keys, offsets,
    sizes, rates and areas as arrays of ints, compared exactly), or, if a key is not an
    int or a field does not fit, the items themselves."""
    if not all(type(it.key) is int for it in items):
        return tuple(items)
    try:
        return (
            array("I", [cast(int, it.key) for it in items]).tobytes(),
            array("H", [it.offset for it in items]).tobytes(),
            array("H", [it.size for it in items]).tobytes(),
            array("q", [it.rate for it in items]).tobytes(),
            bytes(it.area.value for it in items),
        )
    except (OverflowError, TypeError, ValueError):
        return tuple(items)


def shared_plan(items: Sequence[PlanItem], *, max_registers: int, max_bits: int,
                max_gap: int, continuous: bool) -> list[ReadBlock]:
    """``plan_reads`` of these arguments, from the cache when planned before."""
    key = (plan_key(items), max_registers, max_bits, max_gap, continuous)
    blocks = PLANS.get(key, lambda: tuple(plan_reads(
        items, max_registers=max_registers, max_bits=max_bits, max_gap=max_gap,
        continuous=continuous)))
    return list(blocks)
