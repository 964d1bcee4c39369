"""Read plans shared between devices with the same address list and planner options.

:func:`shared_plan` is :func:`~edgemodbus.poll.planner.plan_reads` behind a bounded
cache (codec/shared.py), keyed by its whole input: every planned item (its key, area,
offset, size and rate) and the four planner options.  A template used by 5,000 DTUs is
planned once; the :class:`~edgemodbus.poll.planner.ReadBlock` objects are immutable, so
the devices share them (docs/scale.md, "Starting thousands of devices").  The cache
holds the ``keep`` most recently used plans (a list of blocks has no weak reference):
the key is as large as the plan, so the bound is its memory.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..codec.shared import SharedCache
from .planner import PlanItem, ReadBlock, plan_reads

PLANS: SharedCache[tuple[ReadBlock, ...]] = SharedCache(keep=64, weak=False)


def shared_plan(items: Sequence[PlanItem], *, max_registers: int, max_bits: int,
                max_gap: int, continuous: bool) -> list[ReadBlock]:
    """``plan_reads`` of these arguments, from the cache when planned before."""
    # plain tuples: hashed and compared in C (a PlanItem's are Python calls, and its
    # area's an Enum's); the area by its value, one per area
    key = (tuple([(p.key, p.area.value, p.offset, p.size, p.rate) for p in items]),
           max_registers, max_bits, max_gap, continuous)
    blocks = PLANS.get(key, lambda: tuple(plan_reads(
        items, max_registers=max_registers, max_bits=max_bits, max_gap=max_gap,
        continuous=continuous)))
    return list(blocks)
