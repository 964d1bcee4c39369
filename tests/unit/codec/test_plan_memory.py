"""A compiled block is small: its per-device plan (src/edgemodbus/_ffi/codec.py CodecPlan)
is one allocation, the C plan and all of its arrays, with no instance dict (a gateway
holds one per read block); its layout and its cache key keep no object per item
(docs/item-store.md, "Memory")."""

from __future__ import annotations

import itertools
from array import array
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus._ffi import Block, codec
from edgemodbus._ffi.native import ffi
from edgemodbus.codec import BlockDecoder, ValueSpec
from edgemodbus.codec import decoder as decoder_module
from edgemodbus.datatypes import Area, DataType


def _items() -> list[tuple[int, ValueSpec]]:
    """Items of every output group: ints, unsigned, floats, a bool bit, a string."""
    return [
        (0, ValueSpec(name="a", data_type=DataType.INT16)),
        (1, ValueSpec(name="b", data_type=DataType.UINT64)),
        (5, ValueSpec(name="c", data_type=DataType.FLOAT)),
        (7, ValueSpec(name="d", data_type=DataType.BOOLEAN, bit=3)),
        (8, ValueSpec(name="e", data_type=DataType.STRING, quantity=3)),
        (11, ValueSpec(name="f", data_type=DataType.UINT16, multiplier=0.5)),
    ]


class _CountingFfi:
    """The codec module's ffi, counting the allocations (ffi.new) made through it."""

    def __init__(self) -> None:
        self.news = 0

    def new(self, *args: Any) -> Any:
        self.news += 1
        return ffi.new(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(ffi, name)


def test_a_plan_is_one_allocation(monkeypatch: pytest.MonkeyPatch) -> None:
    layout = BlockDecoder(Area.HOLDING_REGISTER, 12, _items())._plan.layout
    counting = _CountingFfi()
    monkeypatch.setattr(codec, "ffi", counting)
    plan = codec.CodecPlan.of(layout)
    assert counting.news == 1  # the emb_plan and its twelve arrays (13 allocations before)
    assert not hasattr(plan, "__dict__")


def test_a_plan_in_one_allocation_decodes_as_before() -> None:
    """Every output group and the state in the one buffer: values, a change, a
    failure, a reset."""
    dec = BlockDecoder(Area.HOLDING_REGISTER, 12, _items())
    regs = [0xFFFE, 0, 0, 0, 7, 0x3FC0, 0, 0b1000, 0x4142, 0x4344, 0x4500, 10]
    first = dec.decode(Block.from_values(regs, False))
    assert first == [(0, -2, None), (1, 7, None), (2, 1.5, None), (3, True, None),
                     (4, "ABCDE", None), (5, 5.0, None)]
    assert dec.decode(Block.from_values(regs, False)) == []
    regs[7] = 0
    regs[9] = 0x4345
    assert dec.decode(Block.from_values(regs, False)) == [(3, False, None), (4, "ABCEE", None)]
    assert dec.decode(Block.from_values(regs[:6], False)) == [
        (k, None, "not in response") for k in (2, 3, 4, 5)]
    dec.reset()
    assert [k for k, _, _ in dec.decode(Block.from_values(regs, False))] == [0, 1, 2, 3, 4, 5]


@given(st.lists(st.integers(0, 3000), min_size=len(codec._REGIONS),
                max_size=len(codec._REGIONS)))
def test_the_arrays_of_a_plan_are_aligned_apart_and_inside_it(counts: list[int]) -> None:
    sizes = dict(zip(codec._REGIONS, counts, strict=True))
    at, size = codec._regions(sizes)
    assert size % 8 == 0
    spans = []
    for name, (ctype, item) in codec._REGIONS.items():
        start = at[name]
        assert start % ffi.alignof(ctype) == 0, name
        assert item == ffi.sizeof(ctype)
        spans.append((start, start + max(sizes[name], 1) * item))
    spans.sort()
    assert spans[0][0] >= ffi.sizeof("emb_plan")  # the emb_plan comes first
    assert all(a_end <= b_start for (_, a_end), (b_start, _) in itertools.pairwise(spans))
    assert spans[-1][1] <= size


def test_a_layout_keeps_no_object_per_item() -> None:
    """Each item's group and slot are a byte and an int in arrays (a layout is one per
    distinct block: devices of distinct address lists hold one per tag); only the
    post-processed items (here the Float and the String) have a tuple each."""
    layout = BlockDecoder(Area.HOLDING_REGISTER, 12, _items())._plan.layout
    assert isinstance(layout.group, bytes) and len(layout.group) == 6
    assert isinstance(layout.slot, array) and len(layout.slot) == 6
    assert [k for k, *_ in layout.special] == [2, 4]


def test_the_cache_key_of_a_block_holds_no_tuple_per_item() -> None:
    items = _items()
    key = decoder_module._shape_key(Area.HOLDING_REGISTER, 12, items)
    assert key == (Area.HOLDING_REGISTER, 12, array("I", [0, 1, 5, 7, 8, 11]).tobytes(),
                   tuple(spec for _, spec in items), array("I", range(6)).tobytes())
    same_spec = [(0, items[0][1]), (1, items[1][1]), (2, items[0][1])]
    assert decoder_module._shape_key(Area.HOLDING_REGISTER, 3, same_spec)[3:] == (
        (items[0][1], items[1][1]), array("I", [0, 1, 0]).tobytes())
    a = BlockDecoder(Area.HOLDING_REGISTER, 12, items)
    b = BlockDecoder(Area.HOLDING_REGISTER, 12, list(items))
    moved = [(offset + 1 if k == 5 else offset, spec) for k, (offset, spec) in enumerate(items)]
    c = BlockDecoder(Area.HOLDING_REGISTER, 13, moved)
    d = BlockDecoder(Area.HOLDING_REGISTER, 13, [*moved[:5], (11, items[5][1])])
    assert a._shape is b._shape and c._shape is not d._shape
    assert c.decode(Block.from_values([0] * 12 + [9], False))[-1] == (5, 4.5, None)
    assert d.decode(Block.from_values([0] * 11 + [9, 0], False))[-1] == (5, 4.5, None)
