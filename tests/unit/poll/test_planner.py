"""Read planner: merge rules, limits, pieces, split/bisect, and properties (hypothesis)."""

from __future__ import annotations

import copy
import gc
import itertools
import pickle
import tracemalloc
from collections import Counter, defaultdict
from collections.abc import Hashable, Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.datatypes import Area
from edgemodbus.poll.planner import (
    Piece,
    PlanItem,
    ReadBlock,
    bisect_block,
    plan_reads,
    split_block,
)

HR, IR, CO, DI = Area.HOLDING_REGISTER, Area.INPUT_REGISTER, Area.COIL, Area.DISCRETE_INPUT


def hr(key: Hashable, offset: int, size: int = 1) -> PlanItem:
    return PlanItem(key, HR, offset, size)


def spans(blocks: Sequence[ReadBlock]) -> list[tuple[Area, int, int]]:
    return [(b.area, b.start, b.count) for b in blocks]


# ----------------------------------------------------------------------------- ReadBlock


@pytest.mark.parametrize("keys", [[0, 1, 70000, -3], ["a", ("b", 1), 2, None]])
def test_a_block_gives_back_its_pieces_and_compares_by_value(keys: list[Hashable]) -> None:
    pieces = tuple(Piece(key, 0 if k else 5, 2 * k, 2) for k, key in enumerate(keys))
    block = ReadBlock(HR, 100, 8, pieces, 250)
    assert (block.area, block.start, block.count, block.rate) == (HR, 100, 8, 250)
    assert block.pieces == pieces and block.keys == tuple(keys) and block.end == 108
    same = ReadBlock(HR, 100, 8, list(pieces), 250)
    assert same == block and hash(same) == hash(block)
    assert copy.deepcopy(block) == block and pickle.loads(pickle.dumps(block)) == block
    assert block != ReadBlock(HR, 100, 8, pieces, 500)
    assert block != ReadBlock(HR, 100, 8, pieces[:-1], 250)
    assert "pieces=(Piece(" in repr(block)
    with pytest.raises(AttributeError):
        block.start = 5  # type: ignore[misc]


def test_a_block_keeps_its_pieces_in_a_few_bytes_each() -> None:
    """A gateway holds one piece per tag: a block keeps them as small ints in arrays
    (keys that are item indexes too), not as a Piece object (64 bytes) each."""
    items = [hr(k, 300 + k) for k in range(120)]
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        blocks = plan_reads(items, max_registers=120)
        gc.collect()
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert [len(b.pieces) for b in blocks] == [120]
    assert held / 120 < 16  # was 74: a Piece object and its place in a tuple per item


# ----------------------------------------------------------------------------- examples


def test_contiguous_items_merge_into_one_block() -> None:
    blocks = plan_reads([hr("a", 0), hr("b", 1, 2), hr("c", 3)])
    assert spans(blocks) == [(HR, 0, 4)]
    assert blocks[0].pieces == (Piece("a", 0, 0, 1), Piece("b", 0, 1, 2), Piece("c", 0, 3, 1))
    assert blocks[0].keys == ("a", "b", "c")
    assert blocks[0].end == 4


def test_gap_equal_to_setting_merges_and_one_more_splits() -> None:
    # a ends at 1 (exclusive): b at 11 leaves gap 10.
    assert spans(plan_reads([hr("a", 0), hr("b", 11)], max_gap=10)) == [(HR, 0, 12)]
    assert spans(plan_reads([hr("a", 0), hr("b", 12)], max_gap=10)) == [(HR, 0, 1), (HR, 12, 1)]


def test_continuous_forces_gap_zero() -> None:
    items = [hr("a", 0), hr("b", 1), hr("c", 3)]
    assert spans(plan_reads(items, max_gap=10, continuous=True)) == [(HR, 0, 2), (HR, 3, 1)]
    assert spans(plan_reads(items, max_gap=0)) == [(HR, 0, 2), (HR, 3, 1)]


def test_span_limit_is_exact() -> None:
    items = [hr("a", 0, 2), hr("b", 118, 2)]
    assert spans(plan_reads(items, max_registers=120, max_gap=200)) == [(HR, 0, 120)]
    assert spans(plan_reads(items, max_registers=119, max_gap=200)) == [(HR, 0, 2), (HR, 118, 2)]


def test_register_and_bit_caps_apply_whatever_the_settings() -> None:
    items = [hr(i, i) for i in range(300)]
    assert [b.count for b in plan_reads(items, max_registers=1000, max_gap=0)] == [125, 125, 50]
    coils = [PlanItem(i, CO, i, 1) for i in range(4500)]
    assert [b.count for b in plan_reads(coils, max_bits=99999)] == [2000, 2000, 500]
    assert [b.count for b in plan_reads(coils, max_bits=1000)][:2] == [1000, 1000]


def test_areas_never_merge_and_output_is_ordered() -> None:
    items = [
        PlanItem("ir", IR, 0, 1),
        PlanItem("hr", HR, 0, 1),
        PlanItem("di", DI, 0, 1),
        PlanItem("co", CO, 1, 1),
        PlanItem("co0", CO, 0, 1),
    ]
    blocks = plan_reads(items)
    assert [(b.area, b.keys) for b in blocks] == [
        (CO, ("co0", "co")),
        (DI, ("di",)),
        (HR, ("hr",)),
        (IR, ("ir",)),
    ]


def test_overlapping_items_share_registers() -> None:
    items = [hr("float", 10, 2), hr("hi_word", 10), hr("bit3", 11), hr("bit4", 11)]
    (block,) = plan_reads(items)
    assert (block.start, block.count) == (10, 2)
    assert [(p.key, p.block_offset, p.size) for p in block.pieces] == [
        ("float", 0, 2),
        ("hi_word", 0, 1),
        ("bit3", 1, 1),
        ("bit4", 1, 1),
    ]


def test_item_larger_than_a_block_is_read_in_pieces() -> None:
    items = [hr("before", 0), hr("big", 5, 300), hr("after", 306)]
    blocks = plan_reads(items, max_registers=120)
    big = [(b.start, b.count, b.pieces) for b in blocks if "big" in b.keys]
    assert big == [
        (5, 120, (Piece("big", 0, 0, 120),)),
        (125, 120, (Piece("big", 120, 0, 120),)),
        (245, 60, (Piece("big", 240, 0, 60),)),
    ]
    assert spans(blocks) == [(HR, 0, 1), (HR, 5, 120), (HR, 125, 120), (HR, 245, 60), (HR, 306, 1)]


def test_ties_keep_input_order_and_output_is_deterministic() -> None:
    items = [hr("z", 5), hr("a", 5), hr("m", 4)]
    assert plan_reads(items)[0].keys == ("m", "z", "a")
    assert plan_reads(items) == plan_reads(list(items))


def test_bad_items_and_settings_are_rejected() -> None:
    with pytest.raises(ValueError, match="duplicate key"):
        plan_reads([hr("a", 0), hr("a", 5)])
    with pytest.raises(ValueError, match="plan item 'x'"):
        plan_reads([hr("x", 65535, 2)])
    with pytest.raises(ValueError, match="plan item 'y'"):
        plan_reads([hr("y", 0, 0)])
    with pytest.raises(ValueError, match="max_registers 0"):
        plan_reads([], max_registers=0)
    with pytest.raises(ValueError, match="max_gap -1"):
        plan_reads([], max_gap=-1)
    assert plan_reads([]) == []


def test_split_block_isolates_bad_keys_and_replans_the_rest() -> None:
    (block,) = plan_reads([hr("a", 0), hr("b", 2), hr("bad", 4, 2), hr("c", 6)], max_gap=5)
    parts = split_block(block, {"bad", "not-there"}, max_gap=5)
    assert [(b.start, b.count, b.keys) for b in parts] == [
        (0, 7, ("a", "b", "c")),
        (4, 2, ("bad",)),
    ]
    # With gap 0 the rest cannot bridge the hole left by the bad item.
    parts = split_block(block, {"bad"}, max_gap=0)
    assert [(b.start, b.count, b.keys) for b in parts] == [
        (0, 1, ("a",)),
        (2, 1, ("b",)),
        (4, 2, ("bad",)),
        (6, 1, ("c",)),
    ]


def test_split_block_keeps_piece_offsets_of_large_items() -> None:
    blocks = plan_reads([hr("big", 0, 300), hr("x", 241)], max_registers=120)
    # An item larger than a block gets blocks of its own; the others are planned apart.
    assert [(b.start, b.count, b.keys) for b in blocks] == [
        (0, 120, ("big",)),
        (120, 120, ("big",)),
        (240, 60, ("big",)),
        (241, 1, ("x",)),
    ]
    # split_block accepts any block, pieces of large items included.
    block = ReadBlock(HR, 240, 60, (Piece("big", 240, 0, 60), Piece("x", 0, 1, 1)))
    parts = split_block(block, {"x"})
    assert [(b.start, b.count, b.pieces) for b in parts] == [
        (240, 60, (Piece("big", 240, 0, 60),)),
        (241, 1, (Piece("x", 0, 0, 1),)),
    ]


def test_bisect_block_halves_and_shrinks() -> None:
    (block,) = plan_reads([hr("a", 0), hr("b", 3, 2), hr("c", 9), hr("d", 20)], max_gap=20)
    first, second = bisect_block(block)
    assert (first.start, first.count, first.keys) == (0, 5, ("a", "b"))
    assert (second.start, second.count, second.keys) == (9, 12, ("c", "d"))
    assert second.pieces == (Piece("c", 0, 0, 1), Piece("d", 0, 11, 1))
    (odd,) = plan_reads([hr("a", 0), hr("b", 1), hr("c", 2)])
    assert [b.keys for b in bisect_block(odd)] == [("a", "b"), ("c",)]
    single = plan_reads([hr("a", 7)])[0]
    assert bisect_block(single) == [single]


# ----------------------------------------------------------------------------- properties


def check_plan(
    items: Sequence[PlanItem],
    blocks: Sequence[ReadBlock],
    *,
    max_registers: int,
    max_bits: int,
    max_gap: int,
) -> None:
    """Every register of every item is in exactly one piece; limits and gaps hold."""
    by_key = {it.key: it for it in items}
    covered: dict[Hashable, Counter[int]] = defaultdict(Counter)
    for block in blocks:
        limit = min(max_bits, 2000) if block.area.is_bit else min(max_registers, 125)
        assert 1 <= block.count <= limit
        assert block.start >= 0 and block.end <= 65536
        used: set[int] = set()
        for p in block.pieces:
            item = by_key[p.key]
            assert item.area is block.area
            assert item.rate == block.rate  # items of different rates never share a block
            assert p.block_offset >= 0 and p.block_offset + p.size <= block.count
            assert p.item_offset >= 0 and p.item_offset + p.size <= item.size
            # The piece's registers really are the item's registers.
            assert block.start + p.block_offset == item.offset + p.item_offset
            covered[p.key].update(range(p.item_offset, p.item_offset + p.size))
            used.update(range(p.block_offset, p.block_offset + p.size))
        # Block shrunk to its pieces; no unused run longer than the gap setting.
        assert 0 in used and block.count - 1 in used
        run = 0
        for r in range(block.count):
            run = 0 if r in used else run + 1
            assert run <= max_gap
    for item in items:
        assert covered[item.key] == Counter(range(item.size)), item


def reference_greedy(items: Sequence[PlanItem], span: int, gap: int) -> int:
    """Block count of the textbook greedy for one area; oversized items alone."""
    count = 0
    end = start = None
    for it in sorted(items, key=lambda i: i.offset):
        if it.size > span:
            count += -(-it.size // span)
            continue
        if start is not None and end is not None:
            new_end = max(end, it.offset + it.size)
            if it.offset - end <= gap and new_end - start <= span:
                end = new_end
                continue
        count += 1
        start, end = it.offset, it.offset + it.size
    return count


def optimum_for_disjoint(items: Sequence[PlanItem], span: int, gap: int) -> int:
    """Fewest blocks (dynamic programming) for disjoint items that each fit a block."""
    xs = sorted(items, key=lambda i: i.offset)
    best = [0] + [10**9] * len(xs)
    for j in range(1, len(xs) + 1):
        for i in range(j, 0, -1):  # block = xs[i-1 .. j-1]
            run = xs[i - 1 : j]
            ok = all(b.offset - (a.offset + a.size) <= gap for a, b in itertools.pairwise(run))
            if run[-1].offset + run[-1].size - run[0].offset > span:
                break
            if ok:
                best[j] = min(best[j], best[i - 1] + 1)
    return best[-1]


def item_lists(max_offset: int = 600, max_size: int = 300) -> st.SearchStrategy[list[PlanItem]]:
    one = st.tuples(
        st.sampled_from(list(Area)),
        st.integers(0, max_offset),
        st.integers(1, max_size) | st.integers(1, 4),
    )
    return st.lists(one, max_size=40).map(
        lambda raw: [
            PlanItem(f"k{i}", a, o, 1 if a.is_bit and s > 3 else s)
            for i, (a, o, s) in enumerate(raw)
        ]
    )


@settings(max_examples=200, deadline=None)
@given(
    items=item_lists(),
    max_registers=st.integers(1, 200),
    max_bits=st.integers(1, 50),
    max_gap=st.integers(0, 30),
    continuous=st.booleans(),
)
def test_plan_covers_every_item_within_limits(
    items: list[PlanItem], max_registers: int, max_bits: int, max_gap: int, continuous: bool
) -> None:
    blocks = plan_reads(
        items,
        max_registers=max_registers,
        max_bits=max_bits,
        max_gap=max_gap,
        continuous=continuous,
    )
    gap = 0 if continuous else max_gap
    check_plan(items, blocks, max_registers=max_registers, max_bits=max_bits, max_gap=gap)
    order = [(b.area.value, b.start) for b in blocks]
    assert order == sorted(order)


@settings(max_examples=200, deadline=None)
@given(
    items=item_lists(),
    max_registers=st.integers(1, 130),
    max_gap=st.integers(0, 30),
)
def test_block_count_equals_reference_greedy(
    items: list[PlanItem], max_registers: int, max_gap: int
) -> None:
    hr_items = [PlanItem(i.key, HR, i.offset, i.size) for i in items]
    blocks = plan_reads(hr_items, max_registers=max_registers, max_gap=max_gap)
    assert len(blocks) == reference_greedy(hr_items, min(max_registers, 125), max_gap)


@settings(max_examples=200, deadline=None)
@given(
    gaps_sizes=st.lists(st.tuples(st.integers(0, 15), st.integers(1, 10)), max_size=25),
    max_registers=st.integers(10, 40),
    max_gap=st.integers(0, 12),
)
def test_greedy_is_optimal_for_disjoint_items(
    gaps_sizes: list[tuple[int, int]], max_registers: int, max_gap: int
) -> None:
    items, offset = [], 0
    for i, (gap, size) in enumerate(gaps_sizes):
        offset += gap
        items.append(hr(i, offset, size))
        offset += size
    blocks = plan_reads(items, max_registers=max_registers, max_gap=max_gap)
    assert len(blocks) == optimum_for_disjoint(items, max_registers, max_gap)


@settings(max_examples=150, deadline=None)
@given(
    items=item_lists(max_offset=200, max_size=150),
    max_gap=st.integers(0, 20),
    data=st.data(),
)
def test_split_block_isolates_bad_keys(
    items: list[PlanItem], max_gap: int, data: st.DataObject
) -> None:
    for block in plan_reads(items, max_gap=max_gap):
        bad = set(data.draw(st.sets(st.sampled_from(block.keys))))
        parts = split_block(block, bad, max_gap=max_gap)
        for part in parts:
            assert part.area is block.area
            keys = set(part.keys)
            assert not (keys & bad) or len(part.pieces) == 1
        sub_items = pieces_as_items(block)
        check_plan(sub_items, relabel(parts), max_registers=120, max_bits=2000, max_gap=max_gap)
        assert len([p for p in parts if set(p.keys) <= bad]) == len(bad)


@settings(max_examples=150, deadline=None)
@given(items=item_lists(max_offset=200, max_size=150), max_gap=st.integers(0, 20))
def test_bisect_recursion_finds_single_items(items: list[PlanItem], max_gap: int) -> None:
    for block in plan_reads(items, max_gap=max_gap):
        leaves, todo, rounds = [], [block], 0
        while todo:
            current = todo.pop()
            halves = bisect_block(current)
            if len(halves) == 1:
                assert halves == [current] and len(current.pieces) == 1
                leaves.append(current)
                continue
            rounds += 1
            assert all(1 <= len(h.pieces) < len(current.pieces) for h in halves)
            assert abs(len(halves[0].pieces) - len(halves[1].pieces)) <= 1
            for h in halves:
                assert block.start <= h.start and h.end <= block.end
            todo.extend(halves)
        assert rounds == len(block.pieces) - 1
        check_plan(
            pieces_as_items(block), relabel(leaves), max_registers=120, max_bits=2000, max_gap=0
        )


def pieces_as_items(block: ReadBlock) -> list[PlanItem]:
    """The block's pieces as stand-alone items keyed (key, item_offset)."""
    return [
        PlanItem((p.key, p.item_offset), block.area, block.start + p.block_offset, p.size)
        for p in block.pieces
    ]


def relabel(blocks: Sequence[ReadBlock]) -> list[ReadBlock]:
    """Blocks whose pieces are keyed like :func:`pieces_as_items` (item offsets rebased)."""
    return [
        ReadBlock(
            b.area,
            b.start,
            b.count,
            tuple(Piece((p.key, p.item_offset), 0, p.block_offset, p.size) for p in b.pieces),
        )
        for b in blocks
    ]


# ----------------------------------------------------------------------------- scan rates


def test_items_of_different_rates_never_merge() -> None:
    fast, slow = 50, 1000
    items = [PlanItem("a", HR, 0, 1, fast), PlanItem("b", HR, 1, 1, slow),
             PlanItem("c", HR, 2, 2, fast), PlanItem("d", HR, 4, 1, slow)]
    blocks = plan_reads(items, max_gap=10)
    assert [(b.start, b.count, b.rate, b.keys) for b in blocks] == [
        (0, 4, fast, ("a", "c")),  # spans may overlap across rates: still two requests
        (1, 4, slow, ("b", "d")),
    ]
    # one rate: one block, as before
    same = [PlanItem(i.key, i.area, i.offset, i.size, fast) for i in items]
    assert [(b.start, b.count, b.rate) for b in plan_reads(same)] == [(0, 5, fast)]


def test_large_items_split_and_bisect_keep_the_rate() -> None:
    big = plan_reads([PlanItem("big", HR, 0, 300, 250)], max_registers=120)
    assert [(b.start, b.count, b.rate) for b in big] == [(0, 120, 250), (120, 120, 250),
                                                         (240, 60, 250)]
    (block,) = plan_reads([PlanItem(k, IR, o, 1, 70) for k, o in (("a", 0), ("b", 5), ("c", 9))])
    assert {b.rate for b in split_block(block, {"b"})} == {70}
    assert {b.rate for b in bisect_block(block)} == {70}


def rated_item_lists() -> st.SearchStrategy[list[PlanItem]]:
    return item_lists().flatmap(
        lambda items: st.lists(
            st.sampled_from([0, 50, 100, 1000, 60_000]), min_size=len(items), max_size=len(items)
        ).map(lambda rates: [PlanItem(i.key, i.area, i.offset, i.size, r)
                             for i, r in zip(items, rates, strict=True)])
    )


@settings(max_examples=200, deadline=None)
@given(
    items=rated_item_lists(),
    max_registers=st.integers(1, 200),
    max_bits=st.integers(1, 50),
    max_gap=st.integers(0, 30),
)
def test_rated_plan_is_the_plans_of_each_rate_within_limits(
    items: list[PlanItem], max_registers: int, max_bits: int, max_gap: int
) -> None:
    limits = {"max_registers": max_registers, "max_bits": max_bits, "max_gap": max_gap}
    blocks = plan_reads(items, **limits)
    # every block's items share its rate; every item is covered once; limits hold
    check_plan(items, blocks, max_registers=max_registers, max_bits=max_bits, max_gap=max_gap)
    # the rates are planned apart and as tightly as alone: the union of each rate's plan
    alone = [b for rate in {i.rate for i in items}
             for b in plan_reads([i for i in items if i.rate == rate], **limits)]
    order = [(b.area.value, b.start, b.rate) for b in blocks]
    assert order == sorted(order)
    assert sorted(blocks, key=repr) == sorted(alone, key=repr)
