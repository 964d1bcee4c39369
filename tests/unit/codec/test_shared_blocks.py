"""Devices of one address list share their blocks' compiled codec layout
(codec/decoder.py, codec/shared.py); each keeps its own change-tracking state.

Differential: decoders that share a layout report exactly what decoders compiled on
their own report, block after block, while each decodes different registers."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block, ScaleFactors
from edgemodbus.codec import BlockDecoder, ValueSpec
from edgemodbus.codec import decoder as decoder_module
from edgemodbus.codec.shared import SharedCache
from edgemodbus.datatypes import Area, DataFormat, DataType

TYPES = [DataType.UINT16, DataType.INT16, DataType.INT32, DataType.UINT32, DataType.FLOAT,
         DataType.DOUBLE, DataType.STRING, DataType.BCD16, DataType.INT64]


@st.composite
def block_items(draw: st.DrawFn) -> tuple[int, list[tuple[int, ValueSpec]]]:
    """A register block and its items, laid out one after the other (gaps allowed)."""
    items: list[tuple[int, ValueSpec]] = []
    offset = 0
    for k in range(draw(st.integers(1, 12))):
        offset += draw(st.integers(0, 3))
        data_type = draw(st.sampled_from(TYPES))
        text = data_type is DataType.STRING
        spec = ValueSpec(name=f"t{k}", data_type=data_type,
                         data_format=draw(st.sampled_from(list(DataFormat))),
                         quantity=draw(st.integers(1, 4)) if text else None,
                         multiplier=1.0 if text else draw(st.sampled_from([1.0, 0.1, 2.0])),
                         deadband=draw(st.sampled_from([0.0, 0.0, 5.0])))
        items.append((offset, spec))
        offset += spec.registers
    return offset, items


def _own(count: int, items: list[tuple[int, ValueSpec]]) -> BlockDecoder:
    """A decoder with a layout of its own: compiled after the cache is emptied."""
    decoder_module._SHAPES.clear()
    return BlockDecoder(Area.HOLDING_REGISTER, count, items)


@settings(max_examples=60, deadline=None)
@given(layout=block_items(), data=st.data())
def test_shared_layouts_report_what_own_layouts_report(
        layout: tuple[int, list[tuple[int, ValueSpec]]], data: st.DataObject) -> None:
    count, items = layout
    decoder_module._SHAPES.clear()
    shared = [BlockDecoder(Area.HOLDING_REGISTER, count, items) for _ in range(3)]
    assert shared[0]._shape is shared[1]._shape is shared[2]._shape
    own = [_own(count, items) for _ in range(3)]
    assert own[0]._shape is not own[1]._shape
    words = st.lists(st.integers(0, 0xFFFF), min_size=count, max_size=count)
    for _ in range(4):
        for k in range(3):  # each device its own registers, and its own report mode
            block = Block.from_values(data.draw(words), False)
            report_all = data.draw(st.booleans())
            # repr: a NaN (a Float's registers can hold one) equals itself there
            assert repr(shared[k].decode(block, report_all)) == repr(
                own[k].decode(block, report_all))
            assert repr(shared[k].decode_values(block)) == repr(own[k].decode_values(block))


def test_a_decoder_reset_or_decode_leaves_the_others_sharing_its_layout_alone() -> None:
    spec = ValueSpec(name="x", data_type=DataType.UINT16)
    a, b = (BlockDecoder(Area.HOLDING_REGISTER, 1, [(0, spec)]) for _ in range(2))
    assert a._shape is b._shape
    assert a.decode(Block.from_values([7], False)) == [(0, 7, None)]
    assert b.decode(Block.from_values([7], False)) == [(0, 7, None)]  # b's first report
    assert a.decode(Block.from_values([7], False)) == []  # unchanged for a
    a.reset()
    assert b.decode(Block.from_values([7], False)) == []  # a's reset is a's only
    assert a.decode(Block.from_values([7], False)) == [(0, 7, None)]


def test_the_cache_is_bounded_and_keeps_what_is_in_use() -> None:
    class Value:
        def __init__(self, n: int) -> None:
            self.n = n

    cache: SharedCache[Value] = SharedCache(keep=2)
    held = cache.get("a", lambda: Value(1))
    for key in "bcd":
        cache.get(key, lambda: Value(0))
    assert cache.get("a", lambda: Value(2)) is held  # pushed out of the recent ones, alive
    del held
    cache.get("e", lambda: Value(0))
    cache.get("f", lambda: Value(0))
    assert cache.get("a", lambda: Value(3)).n == 3  # unused and not recent: made again
    assert len(cache) <= 3


def test_devices_with_scale_factors_never_share_a_block_or_its_factor() -> None:
    """A block whose items use a scale factor points at its device's factor table: two
    devices of one template compile a block each, and a factor read on one device is
    not the other's."""
    ours, theirs = ScaleFactors(["SF"]), ScaleFactors(["SF"])

    def block_of(factors: ScaleFactors) -> BlockDecoder:
        return BlockDecoder(Area.HOLDING_REGISTER, 2, [
            (0, ValueSpec("SF", DataType.INT16, holds_factor="SF", factors=factors)),
            (1, ValueSpec("W", DataType.UINT16, scale_factor="SF", factors=factors))])

    a, b = block_of(ours), block_of(theirs)
    assert a._shape is not b._shape
    assert a._shape is block_of(ours)._shape  # within one device: shared
    assert a.decode(Block.from_values([0xFFFF, 50], False)) == [(0, -1, None), (1, 5.0, None)]
    assert ours.get("SF") == -1 and theirs.get("SF") is None
    assert b.decode(Block.from_values([1, 50], False)) == [(0, 1, None), (1, 500, None)]
    assert ours.get("SF") == -1 and theirs.get("SF") == 1
