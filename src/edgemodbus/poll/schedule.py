"""Scan rates: which items are read how often.

Every item is read at its own rate (the item's readCycle, else the device's); the
planner never merges items of different rates, so every block has one rate and a due
time of its own, which the line engine keeps (csrc/emb_engine.c: a block due within a
tenth of its period, and 5 ms, joins the pass that begins; after a pass each block is
due one period after the pass began, or at once when the pass overran it).  A device's
*pass* (what its counters call a cycle, and what the batch callback, the failed-cycle
count and the backoff count) is one pass over the blocks due when it begins.  With every
item at the device's rate every pass reads every block, as a cycle always did.

An item at rate 0 is not polled (updated by wrapped reports only), like a device at
readCycle 0.  An item at rate -1 (``readCycle: "demand"``) is not polled either: it is
planned into blocks of its own (:func:`build_plan` with ``demand=True``), which are read
only when asked (poll/on_demand.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from ..config import ON_DEMAND, DriverModbusRtuParameter, ParsedItem
from ..protocol.address import entity_lookalike, entity_notice
from .plan_cache import shared_plan
from .planner import PlanItem, ReadBlock

if TYPE_CHECKING:
    from .items import ItemState


def item_rate(parsed: ParsedItem, params: DriverModbusRtuParameter) -> int:
    """The item's scan rate in ms: its own readCycle, else the device's (0 = not polled)."""
    own = parsed.item.read_cycle
    return params.read_cycle if own is None else own


def build_plan(items: Sequence[ParsedItem], params: DriverModbusRtuParameter,
               demand: bool = False) -> list[ReadBlock]:
    """The read blocks of a device's enabled, polled items (``demand``: of its on-demand
    items instead, readCycle -1); piece keys index ``items``.  Planned once per distinct
    list of planned items and options (poll/plan_cache.py): a template's devices share it."""
    plan_items = []
    for i, p in enumerate(items):
        rate = item_rate(p, params)
        if p.item.is_enable and (rate == ON_DEMAND if demand else rate > 0):
            size = 1 if p.address.area.is_bit else p.registers
            plan_items.append(PlanItem(i, p.address.area, p.address.offset, size, rate))
    return shared_plan(
        plan_items,
        max_registers=params.max_block_read_register_count,
        max_bits=params.max_block_read_bit_count,
        max_gap=params.max_merge_address_gap,
        continuous=params.is_block_read_require_address_continuous,
    )


def entity_numbers_notice(items: Sequence[ParsedItem],
                          params: DriverModbusRtuParameter) -> str | None:
    """One notice for a device whose bare addresses look like Modicon entity numbers
    (``40001`` read as holding register 40001, not 0; docs/device-files.md, "Entity addresses"), or
    None.  Logged once per device start and shown by ``edgemodbus plan``."""
    found = [(p, e) for p in items
             if (e := entity_lookalike(p.item.address, params.address_prefix)) is not None]
    if not found:
        return None
    first, entity = found[0]
    more = f" (and {len(found) - 1} more such addresses)" if len(found) > 1 else ""
    return (f"item {first.item.name!r}: {entity_notice(first.item.address, first.address, entity)}"
            f"{more}; for Modicon numbering set addressPrefix: entity")


def block_dict(block: ReadBlock, items: Sequence[ItemState]) -> dict[str, Any]:
    """A block as ``driver.read_plan()`` lists it (piece keys index ``items``)."""
    names = [items[p.key].item.name for p in block.pieces if isinstance(p.key, int)]
    return {
        "area": block.area.short_name,
        "function": block.area.read_function,
        "start": block.start,
        "count": block.count,
        "readCycle": block.rate,
        "items": names,
    }
