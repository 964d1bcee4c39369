"""Property test of change detection: a change-mode decoder fed a random sequence of
blocks reports, for each block, exactly the items whose (value, status, reason) differs
from what it last reported for them (past the deadband for numbers), and each report is
what a fresh cycle-mode decode of the same block gives.  Reports in cycle mode and
resets (the driver resets after a failed read) are mixed in: they must leave the change
tracking in step with what was reported."""

from __future__ import annotations

import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, Change, ValueSpec, check_spec
from edgemodbus.datatypes import Area, DataFormat, DataType

T = DataType
HR = Area.HOLDING_REGISTER

# registers near the edges the codec rejects or rounds: bad BCD nibbles, NaN and infinity
# high words of floats and doubles (also byte-swapped), sign bits, undecodable bytes
EDGES = [0, 1, 9, 0x0099, 0x1234, 0x12AB, 0x34CD, 0x9999, 0x7FC0, 0x7F80, 0xFF80,
         0xC07F, 0x807F, 0x7FF8, 0x7FF0, 0xF87F, 0x7FFF, 0x8000, 0xFFFF, 0x4142, 0xFF41,
         0x00C8]  # fmt: skip
REGISTER = st.one_of(st.sampled_from(EDGES), st.integers(0, 0xFFFF))
NUMERIC = [T.INT16, T.UINT16, T.INT32, T.UINT32, T.INT64, T.UINT64, T.FLOAT, T.DOUBLE,
           T.BYTE, T.SBYTE, T.BCD16, T.BCD32]  # fmt: skip


def valid(spec: ValueSpec) -> bool:
    try:
        check_spec(spec, HR)
    except ValueError:
        return False
    return True


NUMBER_SPECS = st.builds(
    ValueSpec,
    name=st.just("n"),
    data_type=st.sampled_from([*NUMERIC, T.BOOLEAN]),
    data_format=st.sampled_from(list(DataFormat)),
    quantity=st.one_of(st.none(), st.integers(1, 5)),
    multiplier=st.sampled_from([1.0, 1.0, 0.1, 0.001, 10.0, 1000.0, -1.0, 2.5, 1e300]),
    converted_type=st.one_of(st.none(), st.sampled_from([*NUMERIC, T.BOOLEAN, T.STRING])),
    deadband=st.sampled_from([0.0, 0.0, 0.5, 1.0, 100.0, 1e6]),
)
OTHER_SPECS = st.builds(
    ValueSpec,
    name=st.just("o"),
    data_type=st.sampled_from([T.STRING, T.BINARY, T.CHAR, T.DATETIME, T.TIMESTAMP]),
    data_format=st.sampled_from(list(DataFormat)),
    quantity=st.one_of(st.none(), st.integers(1, 4)),
    deadband=st.sampled_from([0.0, 0.5, 1000.0]),
    encoding=st.sampled_from(["utf-8", "gbk", "ascii"]),
)
# short strings: two different undecodable byte strings often give the same text
TEXT_SPECS = st.builds(
    lambda q, f, e: ValueSpec("s", T.STRING, f, quantity=q, encoding=e),
    st.integers(1, 2),
    st.sampled_from(list(DataFormat)),
    st.sampled_from(["utf-8", "gbk", "ascii"]),
)
# floats as they are read: NaNs with another payload, infinities, -0.0
FLOAT_SPECS = st.builds(
    lambda t, f, c, d: ValueSpec("f", t, f, converted_type=c, deadband=d),
    st.sampled_from([T.FLOAT, T.DOUBLE]),
    st.sampled_from(list(DataFormat)),
    st.sampled_from([None, T.STRING, T.DOUBLE, T.INT32]),
    st.sampled_from([0.0, 1.0]),
)
# 64-bit integers with a deadband: far from 0 a double cannot tell neighbours apart
WIDE_SPECS = st.builds(
    lambda t, f, d: ValueSpec("w", t, f, quantity=4, deadband=d),
    st.sampled_from([T.INT64, T.UINT64, T.TIMESTAMP]),
    st.sampled_from(list(DataFormat)),
    st.sampled_from([0.5, 1.0, 100.0]),
)
BIT_SPECS = st.builds(lambda b: ValueSpec("bit", T.BOOLEAN, bit=b), st.integers(0, 15))
SPECS = st.one_of(
    NUMBER_SPECS, FLOAT_SPECS, WIDE_SPECS, OTHER_SPECS, TEXT_SPECS, BIT_SPECS
).filter(valid)


def same(a: object, b: object) -> bool:
    """One value: floats by their bits, with every NaN alike; others by type and ==."""
    if isinstance(a, float) and isinstance(b, float):
        return struct.pack(">d", a) == struct.pack(">d", b) or (math.isnan(a) and math.isnan(b))
    return type(a) is type(b) and a == b


def is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def differs(last: Change | None, now: Change, deadband: float) -> bool:
    """Whether ``now`` must be reported after ``last`` was (the contract of reportMode
    "change": another status or reason, or another value, past the deadband for numbers)."""
    if last is None:
        return True
    _, was, was_reason = last
    _, value, reason = now
    if reason != was_reason:
        return True
    if reason is not None or same(value, was):
        return False
    if deadband > 0 and is_number(value) and is_number(was):
        assert isinstance(value, (int, float)) and isinstance(was, (int, float))
        if math.isnan(value) or math.isnan(was):
            return True
        return abs(value - was) > deadband
    return True


def equal_reports(a: Change, b: Change) -> bool:
    return a[0] == b[0] and a[2] == b[2] and same(a[1], b[1])


Items = list[tuple[int, ValueSpec]]
Steps = list[tuple[str, list[int]]]


@st.composite
def scenarios(draw: st.DrawFn) -> tuple[Items, int, Steps]:
    """Items laid out in a block (with constant filler items after them, so that one
    change among many takes the decoder's per-item path), then the steps: a mode and the
    registers of the reply (sometimes shorter than the block)."""
    specs = draw(st.lists(SPECS, min_size=1, max_size=4))
    items: Items = []
    offset = 0
    for k, spec in enumerate(specs):
        items.append((offset, ValueSpec(f"i{k}", spec.data_type, spec.data_format, spec.quantity,
                                        spec.bit, spec.multiplier, spec.converted_type,
                                        spec.deadband, spec.encoding)))
        offset += spec.registers
    moving = offset
    fillers = draw(st.integers(0, 12))
    items += [(moving + k, ValueSpec(f"f{k}", T.UINT16)) for k in range(fillers)]
    count = moving + fillers
    filler_regs = draw(st.lists(REGISTER, min_size=fillers, max_size=fillers))
    steps: Steps = []
    current = draw(st.lists(REGISTER, min_size=moving, max_size=moving))
    for _ in range(draw(st.integers(1, 8))):
        # change a few registers, often by one bit: a small move keeps an item Invalid
        # (another bad digit, another out-of-range value, another undecodable byte)
        for _ in range(draw(st.integers(0, 3))):
            if moving:
                at = draw(st.integers(0, moving - 1))
                if draw(st.booleans()):
                    current[at] ^= 1 << draw(st.integers(0, 15))
                else:
                    current[at] = draw(REGISTER)
        block = current + filler_regs
        if draw(st.integers(0, 5)) == 0:
            block = block[: draw(st.integers(0, count))]
        mode = draw(st.sampled_from(["change"] * 6 + ["cycle", "reset"]))
        steps.append((mode, block))
    return items, count, steps


@settings(max_examples=700, deadline=None)
@given(scenario=scenarios())
def test_change_mode_reports_exactly_the_changed_results(
    scenario: tuple[Items, int, Steps],
) -> None:
    items, count, steps = scenario
    decoder = BlockDecoder(HR, count, items)
    last: list[Change | None] = [None] * len(items)
    for mode, registers in steps:
        block = Block.from_values(registers, bits=False)
        fresh = BlockDecoder(HR, count, items).decode(block, report_all=True)
        if mode == "reset":
            decoder.reset()
            last = [None] * len(items)
        got = decoder.decode(block, report_all=mode == "cycle")
        if mode == "cycle":
            expected = list(range(len(items)))
        else:
            expected = [
                k for k in range(len(items)) if differs(last[k], fresh[k], items[k][1].deadband)
            ]
        assert [k for k, _, _ in got] == expected, (mode, registers, got, fresh, last)
        for report in got:
            k = report[0]
            assert equal_reports(report, fresh[k]), (report, fresh[k])
            last[k] = report


@settings(max_examples=400, deadline=None)
@given(scenario=scenarios())
def test_finish_every_gives_the_values_of_a_report_of_every_item(
    scenario: tuple[Items, int, Steps],
) -> None:
    """BlockDecoder.finish_every (the poller's store by slices) against finish() of a
    second decoder fed the same blocks: it returns the values exactly when finish()
    would report every item, all good (String texts already reported left out by
    finish), those values in item order; otherwise None, leaving the tracking as
    finish() then leaves it."""
    items, count, steps = scenario
    fast = BlockDecoder(HR, count, items)
    reference = BlockDecoder(HR, count, items)
    for mode, registers in steps:
        block = Block.from_values(registers, bits=False)
        if mode == "reset":
            fast.reset()
            reference.reset()
        if mode == "cycle":
            fast.decode(block, report_all=True)
            reference.decode(block, report_all=True)
            continue
        want = reference.decode(block)
        plan, plan_mode = fast.begin(False)
        n = plan.decode(block, plan_mode)
        values = fast.finish_every(n)
        every = len(want) == len(items) and all(e is None for _, _, e in want)
        if values is None:
            assert not every, (registers, want)
            got = fast.finish(n, False)
            assert len(got) == len(want)
            assert all(equal_reports(a, b) for a, b in zip(got, want, strict=True))
        else:
            assert every, (registers, want, values)
            assert len(values) == len(items)
            assert all(same(v, w[1]) for v, w in zip(values, want, strict=True))


@settings(max_examples=400, deadline=None)
@given(specs=st.lists(SPECS, min_size=1, max_size=12), data=st.data())
def test_the_values_list_is_each_items_value(specs: list[ValueSpec],
                                             data: st.DataObject) -> None:
    """CodecPlan.values() (the special items of one group and post step converted a run
    at a time when no item failed, _ffi/codec.py CodecLayout._group_special) and
    value(k) against a decoder of each item alone (nothing to group), for interleaved
    item types."""
    items: Items = []
    offset = 0
    for k, spec in enumerate(specs):
        items.append((offset, ValueSpec(f"i{k}", spec.data_type, spec.data_format,
                                        spec.quantity, spec.bit, spec.multiplier,
                                        spec.converted_type, spec.deadband, spec.encoding)))
        offset += spec.registers
    registers = data.draw(st.lists(REGISTER, min_size=offset, max_size=offset))
    decoder = BlockDecoder(HR, offset, items)
    plan, mode = decoder.begin(False)
    plan.decode(Block.from_values(registers, bits=False), mode)
    values = plan.values()
    assert len(values) == len(items)
    block = Block.from_values(registers, bits=False)
    for k, value in enumerate(values):
        alone = BlockDecoder(HR, offset, [items[k]]).decode(block, report_all=True)[0]
        if plan.status(k):
            assert value is None and alone[2] is not None
        else:
            assert alone[2] is None
            assert same(value, alone[1]), (k, value, alone)
            assert same(plan.value(k), alone[1]), (k, plan.value(k), alone)


def test_finish_every_leaves_a_text_already_reported_to_finish() -> None:
    """Other bytes, the same text (undecodable bytes read as U+FFFD): C reports the item,
    finish() leaves it out, so finish_every must give way (None), not report it."""
    items = [(0, ValueSpec("s", T.STRING, quantity=1, encoding="utf-8"))]
    decoder = BlockDecoder(HR, 1, items)
    for registers, want in (([0xFF41], ["\ufffdA"]), ([0xFE41], None)):
        plan, mode = decoder.begin(False)
        n = plan.decode(Block.from_values(registers, bits=False), mode)
        assert n == 1  # C compares bytes: both reads changed
        assert decoder.finish_every(n) == want
    assert decoder.finish(1, False) == []  # the text was reported already
