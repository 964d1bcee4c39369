"""The instructions of one block decode, counted by callgrind (no timing noise).

Run it: ``valgrind --tool=callgrind --toggle-collect=emb_decode .venv/bin/python -m
bench.decode_cost 0.01`` (needs valgrind; not a pytest module), then
``callgrind_annotate`` on the file it writes: the total over ``--reads`` decodes.  The
block is bench/test_bench_driver.py's: 120 holding registers of that bench's types in
its order (a Double, Int16s, UInt16s, a Bit, an Int32 CDAB, Floats, a Boolean, a UInt32),
73 items, decoded with change tracking (EMB_MODE_TRACK) as the line engine does; the
argument is the fraction of the items whose register moves before each read (0.01:
scenario (a), about two blocks in three change; 1: scenario (b)).  Figures in
docs/performance.md "The engine's own cost per block".
"""

from __future__ import annotations

import argparse
import random
import sys

from edgemodbus import _ffi
from edgemodbus._ffi import Block, CodecItem, CodecPlan

_W = _ffi.codec_constants("W")
_WORD_SWAP = _ffi.codec_constants("F")["WORD_SWAP"]
# (wire, registers, output group: 0 int64, 1 uint64, 2 double, 3 bool, flags)
_GROUP = [("F64", 4, 2, 0), ("I16", 1, 0, 0), ("U16", 1, 1, 0), ("REGBIT", 1, 3, 0),
          ("I32", 2, 0, _WORD_SWAP), ("F32", 2, 2, 0), ("I16", 1, 0, 0), ("U16", 1, 1, 0),
          ("REGBOOL", 1, 3, 0), ("F32", 2, 2, 0), ("U32", 2, 1, 0)]
REGISTERS = 120


def block_items() -> list[CodecItem]:
    """The bench's items in one block of at most REGISTERS registers."""
    items: list[CodecItem] = []
    offset = 0
    while True:
        wire, n, out, flags = _GROUP[len(items) % len(_GROUP)]
        if offset + n > REGISTERS:
            return items
        items.append(CodecItem(offset, n, _W[wire], flags, 3, 0, out, 1.0, 0.0))
        offset += n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fraction", type=float, help="items moved per read (0..1)")
    parser.add_argument("--reads", type=int, default=2000)
    args = parser.parse_args()
    items = block_items()
    plan = CodecPlan(False, items, [None] * len(items))
    rng = random.Random(1)
    regs = [rng.randrange(0x4000) for _ in range(items[-1].offset + items[-1].nregs)]
    moved = 0
    for _ in range(args.reads):
        for it in items:
            if rng.random() < args.fraction:
                regs[it.offset] ^= 1
                moved += 1
        plan.decode(Block.from_values(regs, False), _ffi.CODEC_MODE_TRACK)
    print(f"{len(items)} items, {len(regs)} registers, {args.reads} reads, {moved} items "
          "moved", file=sys.stderr)


if __name__ == "__main__":
    main()
