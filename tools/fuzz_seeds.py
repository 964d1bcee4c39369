"""Write the seed corpora of the fuzzers in csrc/fuzz/ into a directory per harness.

Small inputs in each harness's byte layout (see the comment at the top of the harness).
fuzz_codec: every wire kind in every byte order, conversions that fail (range, NaN, BCD
digits), scaled values, coils, strings, an absurd plan and a plan with a NULL array, each
with a program of decode steps; the wire/flag/target numbers are read from
csrc/emb_codec.h, so the seeds follow the codec if its constants move.
fuzz_frames: good and bad replies to reads and writes, RTU and Modbus TCP: exception
responses, another slave's reply, a stale reply before ours, two replies at once, an
echo, a short frame.
fuzz_stream: wrapped reports, heartbeats and noise fed in chunks, wrapped reads and
writes behind reports, a plain RTU stream with heartbeats and an echo, an idle link.
fuzz_serve: requests to the Modbus TCP server: reads of its image (fresh, stale, fed a
byte at a time), refused ones (address, quantity, function, unit), writes confirmed or
refused, forwarded requests, a request split across pieces, bad MBAP headers, function
codes with the high bit.

    python tools/fuzz_seeds.py build/fuzz   # build/fuzz/seeds-codec, -frames, -stream, -serve
"""

from __future__ import annotations

import re
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# rd_double() selectors of the harness's table
SCALE_1, SCALE_10, SCALE_0_1 = 0, 1, 2
DEADBAND_0, DEADBAND_0_5, NAN_SEL = 12, 7, 14

# run_step() ops (op % 6)
TRACK2, ALL2, VALUES, RESET, MUTATE, SHORTER = range(6)


def codec_constants() -> dict[str, int]:
    """EMB_* constants of csrc/emb_codec.h, without the prefix ("W_U16": 6, ...)."""
    text = (ROOT / "csrc" / "emb_codec.h").read_text()
    pattern = r"#define EMB_(\w+)\s+(0x[0-9A-Fa-f]+|\d+)"
    return {m[1]: int(m[2], 0) for m in re.finditer(pattern, text)}


K = codec_constants()

WIDTH = {
    **dict.fromkeys(["COIL", "REGBOOL", "REGBIT", "U8", "I8", "U16", "I16", "BCD16"], 1),
    **dict.fromkeys(["U32", "I32", "F32", "BCD32", "SEC32"], 2),
    **dict.fromkeys(["U64", "I64", "F64", "MS64"], 4),
}


@dataclass
class Item:
    wire: str
    offset: int
    flags: int = 0
    target: str = "NONE"
    out: str | None = None
    bit: int = 0
    nregs: int | None = None  # BYTES only
    scale: int = SCALE_1
    deadband: int = DEADBAND_0

    def natural_out(self) -> str:
        if self.wire in ("COIL", "REGBOOL", "REGBIT"):
            return "BOOL"
        if self.wire == "U64":
            return "U64"
        if self.wire in ("F32", "F64") or self.flags & (K["F_MULTIPLY"] | K["F_DIVIDE"]):
            return "F64"
        return "BYTES" if self.wire == "BYTES" else "I64"

    def pack(self) -> bytes:
        """Production layout: wire flags target out bit nregs_sel, offset, scale, deadband."""
        nsel = self.nregs if self.wire == "BYTES" else WIDTH[self.wire]
        return struct.pack(
            ">6BH2B",
            K["W_" + self.wire],
            self.flags,
            K["C_" + self.target],
            K["O_" + (self.out or self.natural_out())],
            self.bit,
            nsel or 0,
            self.offset,
            self.scale,
            self.deadband,
        )


def seed(items: list[Item], count: int, data: bytes, *, bits: bool = False,
         steps: tuple[int, ...] = (TRACK2, MUTATE, TRACK2, ALL2, VALUES, RESET, SHORTER),
         after: bytes = b"\x00\x03\x12\x34\x00\x05", raw: int = 0x0102030405060708,
         ctl_extra: int = 0, null_sel: int | None = None) -> bytes:
    """One input: header, items, steps, encode selectors (19 bytes), block, step args."""
    ctl = (1 if bits else 0) | ctl_extra | (4 if null_sel is not None else 0)
    out = bytes([ctl]) + (bytes([null_sel]) if null_sel is not None else b"")
    out += struct.pack(">HB", count, len(items)) + b"".join(it.pack() for it in items)
    out += bytes([len(steps), *steps])
    out += struct.pack(">QBBB", raw, 1, 2, 8) + bytes(8)  # raw, fval sel, max_regs, nbytes
    return out + data + after


def registers(values: list[int]) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


def seeds() -> dict[str, bytes]:
    swap = {"ABCD": 0, "BADC": K["F_BYTE_SWAP"], "CDAB": K["F_WORD_SWAP"],
            "DCBA": K["F_BYTE_SWAP"] | K["F_WORD_SWAP"],
            "EFGHABCD": K["F_DWORD_SWAP"],  # 64-bit orders of their own (emb_codec.h)
            "DCBAHGFE": K["F_BYTE_SWAP"] | K["F_WORD_SWAP"] | K["F_DWORD_SWAP"]}
    fixed = [w for w in WIDTH if w != "COIL"]
    ramp = registers([(0x1111 * k + 0x0102) & 0xFFFF for k in range(64)])
    out: dict[str, bytes] = {}
    for name, flags in swap.items():
        items, at = [], 0
        for w in fixed:
            items.append(Item(w, at, flags=flags, bit=at % 16))
            at += WIDTH[w]
        out[f"wires-{name}"] = seed(items, at, ramp[: 2 * at])
    scaled = K["F_DIVIDE"]
    out["scaled-deadband"] = seed(
        [Item("I16", 0, flags=scaled, scale=SCALE_10, deadband=DEADBAND_0_5),
         Item("U32", 1, flags=K["F_MULTIPLY"], scale=SCALE_0_1),
         Item("F32", 3, target="I16", out="I64"),
         Item("F64", 5, target="U64", out="U64", deadband=DEADBAND_0_5)],
        9, registers([0xFFFE, 0, 1000, 0x7FC0, 0, 0x4059, 0, 0, 0]),
    )
    out["conversions"] = seed(
        [Item("I16", 0, target="U8"), Item("U16", 1, target="BCD16"),
         Item("BCD16", 2), Item("BCD32", 3), Item("SEC32", 5, target="DATETIME"),
         Item("MS64", 7, target="DATETIME"), Item("F32", 11, target="F32"),
         Item("F64", 13, target="F32", out="F64"), Item("U64", 17, target="I8", out="I64"),
         Item("I8", 21, target="BOOL", out="BOOL")],
        22, registers([0xFF80, 0x1234, 0x12A4, 0x9999, 0x9999, 0xFFFF, 0xFFFF, 0x8000, 0, 0, 0,
                       0x7F80, 0, 0x7FF0, 0, 0, 1, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF, 0x00FF]),
    )
    out["coils"] = seed([Item("COIL", k) for k in range(16)], 16,
                        bytes([k % 3 == 0 for k in range(16)]), bits=True)
    out["strings"] = seed(
        [Item("BYTES", 0, flags=K["F_STRIP"], nregs=5), Item("BYTES", 5, nregs=3),
         Item("BYTES", 8, flags=K["F_STRIP"] | K["F_BYTE_SWAP"], nregs=2)],
        10, b"hello\x00\x00\x00\x00\x00abcdef\x00\x00\x00\x00\x00\x00\x00\x00",
    )
    out["missing"] = seed([Item("U64", 60), Item("U16", 124), Item("BYTES", 100, nregs=125)], 125,
                          ramp * 2, steps=(SHORTER, TRACK2, RESET, ALL2))
    # absurd layout: raw slots, aux and lengths (ctl bit 1); most of it is refused
    # wire flags target out bit nregs_sel, offset, scale (NaN), deadband (inf), slot, aux,
    # nregs, and (nregs_sel odd) the offset's high half
    absurd_item = struct.pack(">6BH2BHHHH", 18, 0xFF, 0, 4, 99, 1, 0xFFFF, NAN_SEL, NAN_SEL + 1,
                              0, 0xFFF0, 0xFFFF, 0xFFFF)
    out["absurd"] = (bytes([2]) + struct.pack(">HB", 256, 1) + absurd_item
                     + struct.pack(">5H", 1, 1, 1, 1, 1000) + bytes([2, TRACK2, ALL2]) + bytes(19))
    out["null-array"] = seed([Item("U16", 0)], 1, b"\x00\x01", null_sel=1)
    out["empty-plan"] = seed([], 0, b"", null_sel=6)
    return out


# -- fuzz_frames ------------------------------------------------------------------------

MBAP, ECHO, TRANSACT, SEND, ECHO_FIRST, FIXUP, WRONG_TID, CLOSE = 1, 2, 8, 12, 16, 32, 64, 128


def frame_seed(ctl: int, slave: int, function: int, addr: int, nb: int, frames: list[bytes],
               *, tid: int = 0x1233, stale: bytes = b"", pdu: bytes = b"",
               rest: bytes = b"") -> bytes:
    """ctl, slave, function-1, addr, nb, tid, stale bytes, [pdu], frames, raw rest."""
    out = struct.pack(">BBBHHH", ctl, slave, function - 1, addr, nb, tid)
    out += bytes([len(stale)]) + stale
    if ctl & 12 >= TRANSACT:
        out += bytes([len(pdu)]) + pdu
    out += bytes([len(frames)]) + b"".join(bytes([len(f)]) + f for f in frames)
    return out + rest


def frame_seeds() -> dict[str, bytes]:
    regs = bytes([1, 3, 4, 0x12, 0x34, 0xAB, 0xCD])  # slave 1, FC03, 2 registers
    write = bytes([6, 0, 1, 0, 3])  # FC06 register 1 = 3
    return {
        "rtu-read": frame_seed(FIXUP, 1, 3, 0, 2, [regs]),
        "rtu-read-coils": frame_seed(FIXUP, 1, 1, 0, 10, [bytes([1, 1, 2, 0xFF, 0x03])]),
        "rtu-read-input": frame_seed(FIXUP, 9, 4, 7, 1, [bytes([9, 4, 2, 0x80, 0x01])]),
        "rtu-exception": frame_seed(FIXUP, 1, 3, 0, 2, [bytes([1, 0x83, 2])]),
        "rtu-other-slave": frame_seed(FIXUP, 1, 3, 0, 2, [bytes([2, *regs[1:]])]),
        "rtu-wrong-count": frame_seed(FIXUP, 1, 3, 0, 3, [regs]),
        "rtu-two-replies": frame_seed(FIXUP, 1, 3, 0, 2, [regs, bytes([1, 3, 4, 0, 1, 0, 2])]),
        "rtu-stale-first": frame_seed(FIXUP, 1, 3, 0, 2, [regs], stale=b"\x01\x03\x04\x00"),
        "rtu-echo": frame_seed(FIXUP | ECHO | ECHO_FIRST, 1, 3, 0, 2, [regs]),
        "rtu-echo-unexpected": frame_seed(FIXUP | ECHO_FIRST, 1, 3, 0, 2, [regs]),
        "rtu-short-then-close": frame_seed(CLOSE, 1, 3, 0, 2, [regs[:4]]),
        "rtu-write": frame_seed(FIXUP | TRANSACT, 1, 3, 0, 0, [bytes([1, *write])], pdu=write),
        "rtu-write-exception": frame_seed(FIXUP | TRANSACT, 1, 3, 0, 0, [bytes([1, 0x86, 4])],
                                          pdu=write),
        "rtu-broadcast": frame_seed(SEND, 0, 3, 0, 0, [], pdu=write),
        "tcp-read": frame_seed(MBAP | FIXUP, 1, 3, 0, 2, [regs]),
        "tcp-read-other-tid-first": frame_seed(MBAP | FIXUP | WRONG_TID, 1, 3, 0, 2,
                                               [regs, regs]),
        "tcp-exception": frame_seed(MBAP | FIXUP, 1, 4, 0, 2, [bytes([1, 0x84, 0x0B])]),
        "tcp-write": frame_seed(MBAP | FIXUP | TRANSACT, 1, 3, 0, 0, [bytes([1, *write])],
                                pdu=write),
        "tcp-raw-header": frame_seed(MBAP, 1, 3, 0, 2, [bytes([0x12, 0x34, 0, 0, 0, 7]) + regs]),
    }


# -- fuzz_stream ------------------------------------------------------------------------

WRAPPED, S_ECHO, S_READ, S_WRITE, S_IDLE, S_CRC, S_WRAP, S_CLOSE, S_TAKE = (
    1, 2, 4, 8, 12, 16, 32, 64, 128)


def stream_seed(ctl: int, chunks: list[bytes], *, heartbeat: bytes = b"", slave: int = 1,
                function: int = 3, addr: int = 1, nb: int = 2, pdu: bytes = b"",
                rest: bytes = b"") -> bytes:
    """ctl, heartbeat, slave, function-1, addr, nb, [pdu], chunks, raw rest."""
    out = bytes([ctl, len(heartbeat)]) + heartbeat
    out += struct.pack(">BBHH", slave, function - 1, addr, nb)
    if ctl & 12 == S_WRITE:
        out += bytes([len(pdu)]) + pdu
    out += bytes([len(chunks)]) + b"".join(bytes([len(c)]) + c for c in chunks)
    return out + rest


def stream_seeds() -> dict[str, bytes]:
    regs = bytes([1, 3, 4, 0x12, 0x34, 0xAB, 0xCD])  # slave 1, FC03, 2 registers
    report = bytes([1, 3, 6, 0, 1, 0, 2, 0, 3])  # the same address, another count
    fixed = S_CRC | S_WRAP
    return {
        "feed-reports": stream_seed(WRAPPED | fixed, [regs, report], heartbeat=b"\xfe",
                                    rest=b"\xfe\x00\x13\xff\xaa\x00"),
        "feed-each": stream_seed(WRAPPED | fixed | S_TAKE, [regs, bytes([1, 0x83, 2])]),
        "feed-bad": stream_seed(WRAPPED | S_WRAP, [regs, bytes([1, 3, 0])]),
        "feed-plain": stream_seed(S_CRC, [regs], heartbeat=b"HB", rest=b"HBxHBH"),
        "wrapped-read": stream_seed(WRAPPED | S_READ | fixed, [report, regs, report]),
        "wrapped-exception": stream_seed(WRAPPED | S_READ | fixed, [bytes([1, 0x83, 2])]),
        "wrapped-write": stream_seed(WRAPPED | S_WRITE | fixed, [bytes([1, 6, 0, 1, 0, 3])],
                                     pdu=bytes([1, 0, 1, 0, 3])),
        "wrapped-short": stream_seed(WRAPPED | S_READ | S_WRAP | S_CLOSE, [regs]),
        "plain-read": stream_seed(S_READ | S_CRC, [regs], heartbeat=b"HB", rest=b"HB"),
        "plain-echo": stream_seed(S_READ | S_ECHO | S_CRC, [bytes([1, 3, 0, 1, 0, 2]), regs],
                                  heartbeat=b"\xfe"),
        "idle": stream_seed(WRAPPED | S_IDLE | fixed, [regs, report], heartbeat=b"HB"),
    }


# -- fuzz_serve -------------------------------------------------------------------------

FRAMED, FRESH = 1, 2
WRITABLE_VALID = 1 | 4


def serve_seed(ctl: int, chunk: int, areas: list[tuple[int, list[int]]],
               answers: list[tuple[int, int, bytes]], stream: bytes) -> bytes:
    """ctl, chunk, the image (per area: start, count, state and value per address),
    Python's answers (kind, code, pdu), the stream."""
    out = bytes([ctl, chunk])
    for start, states in areas + [(0, [])] * (4 - len(areas)):
        out += struct.pack(">HB", start, len(states))
        out += b"".join(struct.pack(">BH", st, 100 + k) for k, st in enumerate(states))
    out += bytes([len(answers)])
    out += b"".join(bytes([kind, code, max(len(pdu), 1) - 1]) + (pdu or b"\x00")
                    for kind, code, pdu in answers)
    return out + stream


def mbap(tid: int, unit: int, pdu: bytes, proto: int = 0, length: int | None = None) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1 if length is None else length,
                       unit) + pdu


def framed(*requests: tuple[int, bytes]) -> bytes:
    """(unit, pdu) pairs in fuzz_serve's framed layout."""
    return b"".join(bytes([unit, len(pdu)]) + pdu for unit, pdu in requests)


def serve_seeds() -> dict[str, bytes]:
    image = [(0, [WRITABLE_VALID] * 8), (0, [1, 1]), (10, [WRITABLE_VALID] * 6 + [2, 0]),
             (0, [1] * 4)]
    reads = framed((1, bytes([3, 0, 10, 0, 4])), (1, bytes([1, 0, 0, 0, 8])),
                   (1, bytes([2, 0, 0, 0, 2])), (1, bytes([4, 0, 0, 0, 4])))
    refused = framed((1, bytes([3, 0, 16, 0, 2])), (1, bytes([3, 0, 0, 0, 1])),
                     (1, bytes([3, 0, 10, 0, 0])), (1, bytes([0x41, 0])), (1, bytes([3, 0])),
                     (7, bytes([3, 0, 0, 0, 1])))
    writes = framed((1, bytes([6, 0, 10, 0x12, 0x34])), (1, bytes([5, 0, 1, 0xFF, 0])),
                    (1, bytes([0x10, 0, 10, 0, 2, 4, 0, 1, 0, 2])),
                    (1, bytes([0x0F, 0, 0, 0, 3, 1, 5])), (1, bytes([5, 0, 1, 0x12, 0])))
    forward = framed((2, bytes([3, 1, 0, 0, 1])), (2, bytes([0x17, 0, 0, 0, 1])),
                     (2, bytes([6, 0, 0, 0, 1])))
    answers = [(0, 0, bytes([3, 2, 0, 7])), (1, 4, b""), (0, 0, bytes([0x83, 2]))]
    raw = (mbap(1, 1, bytes([3, 0, 10, 0, 1])) + mbap(2, 1, bytes([3, 0, 10, 0, 1]))[:9])
    return {
        "reads": serve_seed(FRAMED | FRESH, 0, image, [], reads),
        "reads-stale": serve_seed(FRAMED, 0, image, [], reads),
        "reads-bytewise": serve_seed(FRAMED | FRESH, 1, image, [], reads),
        "refused": serve_seed(FRAMED | FRESH, 5, image, [], refused),
        "writes": serve_seed(FRAMED | FRESH, 0, image, [(0, 0, b""), (1, 4, b"")], writes),
        "forward": serve_seed(FRAMED | FRESH, 3, image, answers, forward),
        "raw-split": serve_seed(FRESH, 7, image, [], raw),
        "raw-bad-protocol": serve_seed(FRESH, 0, image, [], mbap(1, 1, bytes([3, 0, 0, 0, 1]))
                                       + mbap(2, 1, bytes([3, 0, 0, 0, 1]), proto=7)),
        "raw-bad-length": serve_seed(FRESH, 0, image, [],
                                     mbap(1, 1, bytes([3, 0, 0, 0, 1]), length=1000)),
        "raw-max-length": serve_seed(FRESH, 0, image, [answers[0]],
                                     mbap(3, 2, bytes([0x10]) + bytes(252))),
        # a function code with the high bit (libmodbus's exception reply wrapped it)
        "high-bit-function": serve_seed(FRAMED | FRESH, 0, image, [(1, 1, b"")],
                                        framed((1, bytes([0xFF, 0, 0, 0, 1])),
                                               (9, bytes([0x80])), (2, bytes([0x83, 0])))),
    }


def write_seeds(directory: Path) -> dict[str, int]:
    """Seeds of each harness in directory/seeds-<harness>; returns the counts."""
    counts = {}
    for harness, corpus in (("codec", seeds()), ("frames", frame_seeds()),
                            ("stream", stream_seeds()), ("serve", serve_seeds())):
        target = directory / f"seeds-{harness}"
        target.mkdir(parents=True, exist_ok=True)
        for name, data in corpus.items():
            (target / name).write_bytes(data)
        counts[harness] = len(corpus)
    return counts


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "build" / "fuzz"
    print(f"fuzz_seeds: {write_seeds(target)} seeds in {target}")
