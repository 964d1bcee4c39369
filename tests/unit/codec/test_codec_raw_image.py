"""The raw image of a plan (csrc/emb_codec.h ``raw_last``): a TRACK decode skips the items
whose registers are those of the last decode (and the whole block when none moved).

Differential: a plan with the image and the same plan without it (``raw_last`` NULL, every
item decoded every time) are fed the same random history of blocks (a few registers
moved, none, a shorter reply, a VALUES or ALL decode between, a reset); after each
decode both must return the same count, list the same items, and hold the same bytes in
every output and state array.  Run under ``make test-asan`` too.
"""

from __future__ import annotations

import math
import random
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus import _ffi
from edgemodbus._ffi import Block, CodecItem, CodecPlan
from edgemodbus._ffi.native import ffi

W = _ffi.codec_constants("W")
F = _ffi.codec_constants("F")
TRACK, ALL, VALUES = _ffi.CODEC_MODE_TRACK, _ffi.CODEC_MODE_ALL, _ffi.CODEC_MODE_VALUES
WIDTH = {"COIL": 1, "REGBOOL": 1, "REGBIT": 1, "U8": 1, "I8": 1, "U16": 1, "I16": 1,
         "BCD16": 1, "U32": 2, "I32": 2, "F32": 2, "BCD32": 2, "SEC32": 2, "I24": 2,
         "U24": 2, "U64": 4, "I64": 4, "F64": 4, "MS64": 4}
NUMBERS = [0.0, 1.0, 0.5, 0.1, 2.0, 100.0, -1.5, math.inf, math.nan]
# register values that make NaNs, infinities, bad BCD digits, range errors and repeats
REGS = [0, 1, 0x7FC0, 0x7F80, 0xFFFF, 0x8000, 0x1234, 0x00FF, 0x9999, 0xA000]


def random_item(rng: random.Random, bits: bool) -> CodecItem:
    name = "COIL" if bits else rng.choice([n for n in WIDTH if n != "COIL"] + ["BYTES"])
    nregs = rng.randint(1, 6) if name == "BYTES" else WIDTH[name]
    flags = rng.randint(0, 0x3F) & ~F["EXT"]
    if name == "BYTES":
        flags &= F["BYTE_SWAP"] | F["WORD_SWAP"] | F["STRIP"]
    return CodecItem(
        offset=rng.randint(0, 24), nregs=nregs, wire=W[name], flags=flags,
        bit=rng.randint(0, 15), target=0 if name == "BYTES" else rng.randint(0, 16),
        out=4 if name == "BYTES" else rng.randint(0, 3), scale=rng.choice(NUMBERS[1:7]),
        deadband=rng.choice([0.0, 0.0, 0.5, 3.0, 1e6]),
    )


def arrays(plan: CodecPlan) -> bytes:
    """Every array of the plan's allocation but the raw image and the lists (changed,
    errs: compared up to their counts)."""
    p = plan._plan
    out = b""
    for name, ctype in (("out_i64", "int64_t"), ("out_u64", "uint64_t"),
                        ("out_f64", "double"), ("out_bool", "_Bool"),
                        ("out_bytes", "uint8_t"), ("last_bytes", "uint8_t")):
        n = {"out_i64": p.n_i64, "out_u64": p.n_u64, "out_f64": p.n_f64,
             "out_bool": p.n_bool, "out_bytes": p.n_bytes, "last_bytes": p.n_bytes}[name]
        out += bytes(ffi.buffer(getattr(p, name), n * ffi.sizeof(ctype)))
    n = p.n_items
    out += bytes(ffi.buffer(p.status, n)) + bytes(ffi.buffer(p.last_status, n))
    out += bytes(ffi.buffer(p.last, 8 * n))
    out += bytes(ffi.buffer(p.errval, n * ffi.sizeof("emb_errval")))
    return out


def outcome(plan: CodecPlan, n: int) -> tuple[Any, ...]:
    p = plan._plan
    return n, plan.changed(n) if n > 0 else [], p.n_errors, plan.errors(), arrays(plan)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32))
def test_a_plan_with_its_raw_image_decodes_as_one_without(seed: int) -> None:
    rng = random.Random(seed)
    bits = rng.random() < 0.2
    items = [random_item(rng, bits) for _ in range(rng.randint(1, 12))]
    try:
        fast = CodecPlan(bits, items, [None] * len(items))
    except ValueError:
        return  # an incoherent random item (test_codec_random.py covers refusals)
    slow = CodecPlan(bits, items, [None] * len(items))
    assert fast._plan.raw_last != ffi.NULL and fast._plan.raw_cap > 0
    slow._plan.raw_last = ffi.NULL  # the reference: every item decoded every time
    size = max(it.offset + it.nregs for it in items) + rng.randint(0, 3)
    regs = [rng.choice(REGS) if not bits else rng.randint(0, 1) for _ in range(size)]
    for _ in range(25):
        roll = rng.random()
        if roll < 0.3:
            pass  # the same registers again
        elif roll < 0.8:
            for _ in range(rng.randint(1, 3) if regs else 0):
                k = rng.randrange(len(regs))
                regs[k] = rng.randint(0, 1) if bits else rng.choice(REGS)
        elif roll < 0.9:
            regs = regs[: rng.randint(0, size)] if len(regs) == size else (
                regs + [0] * (size - len(regs)))
        else:
            for plan in (fast, slow):
                plan.reset()
        mode = rng.choice([TRACK] * 8 + [ALL, VALUES])
        block = Block.from_values(regs, bits)
        got = [outcome(plan, plan.decode(block, mode)) for plan in (fast, slow)]
        assert got[0] == got[1], (mode, regs)


def test_a_block_none_of_whose_registers_moved_is_not_decoded_again() -> None:
    """The skip is taken: an output poked after a TRACK decode stays as poked when the
    same registers come again (a decode would rewrite it), and comes back to the value
    once a register of its item moves."""
    u16 = CodecItem(offset=1, nregs=1, wire=W["U16"], flags=0, bit=0, target=0, out=1,
                    scale=1.0, deadband=0.0)
    plan = CodecPlan(False, [u16], [None])
    block = Block.from_values([5, 7], False)
    assert plan.decode(block, TRACK) == 1
    assert plan.values() == [7]
    plan._plan.out_u64[0] = 99
    assert plan.decode(block, TRACK) == 0
    assert plan.values() == [99]
    assert plan.decode(Block.from_values([6, 7], False), TRACK) == 0  # another item's register
    assert plan.values() == [99]
    assert plan.decode(Block.from_values([6, 8], False), TRACK) == 1
    assert plan.values() == [8]
    assert plan.decode(Block.from_values([6, 8], False), VALUES) == 0
    plan._plan.out_u64[0] = 99
    assert plan.decode(Block.from_values([6, 8], False), TRACK) == 0  # decoded: no image
    assert plan.values() == [8]
