"""poll/plan_cache.py: shared read plans, keyed compactly.

Differential: a plan from the cache is always ``plan_reads`` of the very items asked for
(never the plan of a list that differs in one field), whatever was planned before; and
the key the cache keeps for the poller's items (int keys) holds no PlanItem, only packed
fields (the 64 keys kept are a gateway's memory: docs/item-store.md, "Memory")."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.datatypes import Area
from edgemodbus.poll.plan_cache import PLANS, plan_key, shared_plan
from edgemodbus.poll.planner import PlanItem, plan_reads

OPTIONS = {"max_registers": 120, "max_bits": 2000, "max_gap": 4, "continuous": False}


@pytest.fixture(autouse=True)
def _fresh_cache() -> Iterator[None]:
    PLANS.clear()
    yield
    PLANS.clear()


@st.composite
def plan_items(draw: st.DrawFn) -> list[PlanItem]:
    items = []
    for key in range(draw(st.integers(1, 30))):
        area = draw(st.sampled_from(list(Area)))
        size = 1 if area.is_bit else draw(st.integers(1, 4))
        items.append(PlanItem(key, area, draw(st.integers(0, 300)), size,
                              draw(st.sampled_from([1000, 1000, 500]))))
    return items


@st.composite
def one_field_changed(draw: st.DrawFn) -> tuple[list[PlanItem], list[PlanItem]]:
    """A list, and the same list with one field of one item changed."""
    items = draw(plan_items())
    at = draw(st.integers(0, len(items) - 1))
    item = items[at]
    field = draw(st.sampled_from(["key", "offset", "size", "rate", "area"]))
    if field == "key":
        new = replace(item, key=len(items) + draw(st.integers(0, 3)))
    elif field == "offset":
        new = replace(item, offset=(item.offset + draw(st.integers(1, 5))) % 301)
    elif field == "size":
        new = replace(item, area=Area.HOLDING_REGISTER, size=item.size % 4 + 1)
    elif field == "rate":
        new = replace(item, rate=item.rate + 1)
    else:
        area = Area.INPUT_REGISTER if item.area is Area.HOLDING_REGISTER else Area.HOLDING_REGISTER
        new = replace(item, area=area)
    changed = [*items[:at], new, *items[at + 1:]]
    return items, changed


@settings(max_examples=200, deadline=None)
@given(one_field_changed())
def test_a_cached_plan_is_the_plan_of_the_items_asked_for(
        pair: tuple[list[PlanItem], list[PlanItem]]) -> None:
    first, second = pair
    assert shared_plan(first, **OPTIONS) == plan_reads(first, **OPTIONS)
    assert shared_plan(second, **OPTIONS) == plan_reads(second, **OPTIONS)
    assert shared_plan(first, **OPTIONS) == plan_reads(first, **OPTIONS)  # a hit
    assert plan_key(first) != plan_key(second)


def test_the_key_of_the_pollers_items_holds_no_plan_item() -> None:
    items = [PlanItem(k, Area.HOLDING_REGISTER, 1000 + 2 * k, 2, 1000) for k in range(500)]
    key = plan_key(items)
    assert isinstance(key, tuple) and all(isinstance(part, bytes) for part in key)
    assert sum(len(part) for part in key) == 17 * len(items)  # bytes an item
    again = [PlanItem(k, Area.HOLDING_REGISTER, 1000 + 2 * k, 2, 1000) for k in range(500)]
    assert plan_key(again) == key
    first = shared_plan(items, **OPTIONS)
    hits = PLANS.hits
    assert shared_plan(again, **OPTIONS) == first
    assert PLANS.hits == hits + 1


def test_other_keys_and_fields_that_do_not_fit_are_keyed_by_the_items() -> None:
    named = [PlanItem("a", Area.COIL, 0, 1), PlanItem("b", Area.COIL, 1, 1)]
    assert plan_key(named) == tuple(named)
    huge = [PlanItem(0, Area.HOLDING_REGISTER, 0, 1, rate=2**70)]
    assert plan_key(huge) == tuple(huge)
    negative = [PlanItem(-1, Area.HOLDING_REGISTER, 0, 1)]
    assert plan_key(negative) == tuple(negative)
    assert shared_plan(named, **OPTIONS) == plan_reads(named, **OPTIONS)
