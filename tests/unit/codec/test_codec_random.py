"""Random registers and random item descriptions must never crash the codec.

Run under ``make test-asan`` too: there AddressSanitizer/UBSan turn any out-of-bounds
access or undefined behaviour in csrc/emb_codec.c into a hard failure.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import sys

import pytest

from edgemodbus import _ffi
from edgemodbus._ffi import Block, CodecItem, CodecPlan, CodecScale, ScaleFactors, codec_encode
from edgemodbus.codec import BlockDecoder, ValueSpec, encode
from edgemodbus.datatypes import Area, DataFormat, DataType

SEEDS = range(8)
WEIRD_NUMBERS = [0.0, -0.0, 1.0, -1.0, 0.1, 1e300, -1e-300, math.nan, math.inf, -math.inf, 7.0]


def random_spec(rng: random.Random, k: int) -> ValueSpec:
    quantity = rng.choice([None, None, 0, 1, 2, 3, 4, 5, 8, 125, 126, 1000, -3])
    return ValueSpec(
        name=f"r{k}",
        data_type=rng.choice(list(DataType)),
        data_format=rng.choice(list(DataFormat)),
        quantity=quantity,
        bit=rng.choice([None, None, None, 0, 7, 15, 16, -1]),
        multiplier=rng.choice([1.0, 1.0, 0.1, 0.001, 2.0, -1.5, 0.0, math.nan, 1e308, 5e-324]),
        converted_type=rng.choice([None, None, *DataType]),
        deadband=rng.choice([0.0, 0.0, 0.5, 100.0, -1.0, math.inf]),
        encoding=rng.choice(["utf-8", "gbk", "ascii", "nope"]),
    )


@pytest.mark.parametrize("seed", SEEDS)
def test_random_specs_and_blocks_never_crash(seed: int) -> None:
    rng = random.Random(seed)
    for _ in range(40):
        area = rng.choice(list(Area))
        count = rng.randint(0, 2000 if area.is_bit else 125)
        items: list[tuple[int, ValueSpec]] = []
        for k in range(rng.randint(0, 30)):
            items.append((rng.choice([0, rng.randint(0, 130), -1, 70000]), random_spec(rng, k)))
        try:
            decoder = BlockDecoder(area, count, items)
        except ValueError:
            # keep only the items the decoder accepts, one by one
            kept = []
            for item in items:
                try:
                    BlockDecoder(area, count, [item])
                except ValueError:
                    continue
                kept.append(item)
            decoder = BlockDecoder(area, count, kept)
            items = kept
        top = 1 if area.is_bit else 0xFFFF
        for _ in range(6):
            got = rng.randint(0, count)  # a response as long as planned, or shorter
            block = Block.from_values([rng.randint(0, top) for _ in range(got)], area.is_bit)
            values = decoder.decode_values(block)
            assert len(values) == len(items)
            reported = decoder.decode(block, report_all=rng.random() < 0.3)
            for index, value, reason in reported:
                assert 0 <= index < len(items)
                assert (value is None) or (reason is None)
            assert decoder.decode(block) == []  # the same block again changes nothing
        for index, (_, spec) in enumerate(items):
            value = values[index]
            if value is None:
                continue
            with contextlib.suppress(ValueError):  # e.g. a Boolean read back as a String
                encode(spec, value)


W = _ffi.codec_constants("W")
O = _ffi.codec_constants("O")  # noqa: E741
WIDTH = {
    W["COIL"]: 1,
    W["REGBOOL"]: 1,
    W["REGBIT"]: 1,
    W["U8"]: 1,
    W["I8"]: 1,
    W["U16"]: 1,
    W["I16"]: 1,
    W["BCD16"]: 1,
    W["U32"]: 2,
    W["I32"]: 2,
    W["F32"]: 2,
    W["BCD32"]: 2,
    W["SEC32"]: 2,
    W["I24"]: 2,
    W["U24"]: 2,
    W["U64"]: 4,
    W["I64"]: 4,
    W["F64"]: 4,
    W["MS64"]: 4,
}


def random_c_item(rng: random.Random, bits: bool) -> CodecItem:
    """Mostly coherent items with wild fields; now and then a field that is plain wrong."""
    if bits:
        wire = W["COIL"]
    else:
        wire = rng.choice([w for name, w in W.items() if name not in ("COIL", "LAST")])
    nregs = rng.randint(1, 200) if wire == W["BYTES"] else WIDTH[wire]
    out = O["BYTES"] if wire == W["BYTES"] else rng.randint(0, 3)
    fields = {
        "offset": rng.choice([0, rng.randint(0, 200), 2**32 - 1, 2**31, 2**16]),
        "nregs": nregs,
        "wire": wire,
        # EMB_F_EXT comes from the plan's scales (test below); alone it is refused
        "flags": rng.randint(0, 255) & (0x13 if wire == W["BYTES"] else ~_ffi.codec_constants(
            "F")["EXT"] & 0xFF),
        "bit": rng.randint(0, 15),
        "target": 0 if wire == W["BYTES"] else rng.randint(0, _ffi.codec_constants("C")["LAST"]),
        "out": out,
        "scale": rng.choice(WEIRD_NUMBERS),
        "deadband": rng.choice(WEIRD_NUMBERS),
    }
    if rng.random() < 0.1:  # corrupt one field
        name = rng.choice(list(fields))
        fields[name] = rng.choice([0, 1, 255, 65535, 2**32 - 1]) if name != "scale" else 0.0
    return CodecItem(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", SEEDS)
def test_random_c_item_descriptions_are_refused_or_safe(seed: int) -> None:
    """Items straight into the C plan, past what the codec package would ever build."""
    rng = random.Random(1000 + seed)
    accepted = 0
    for _ in range(150):
        bits = rng.random() < 0.2
        items = [random_c_item(rng, bits) for _ in range(rng.randint(1, 6))]
        try:
            plan = CodecPlan(bits, items, [None] * len(items))
        except ValueError:
            continue
        accepted += 1
        size = rng.randint(0, 300)
        top = 1 if bits else 0xFFFF
        block = Block.from_values([rng.randint(0, top) for _ in range(size)], bits)
        for mode in (
            _ffi.CODEC_MODE_VALUES,
            _ffi.CODEC_MODE_TRACK,
            _ffi.CODEC_MODE_ALL,
        ):
            n = plan.decode(block, mode)
            assert 0 <= n <= len(items)
            assert len(plan.values()) == len(items)
            assert all(0 <= k < len(items) for k in plan.errors())
    assert accepted > 10  # the random plans do reach the decoder


def random_scale(rng: random.Random, n_sf: int) -> CodecScale | None:
    """A wild engineering units step (csrc/emb_codec.h emb_scale), or None; now and
    then a field that is plain wrong."""
    if rng.random() < 0.3:
        return None
    finite = [x for x in WEIRD_NUMBERS if math.isfinite(x)]
    lo, hi = sorted(rng.choice([*finite, -5.0, 5.0, 1e9]) for _ in range(2))
    fields = {
        "sub": rng.choice(finite), "mul": rng.choice(finite), "add": rng.choice(finite),
        "raw_lo": lo, "raw_hi": hi, "eng_lo": min(lo, -1.0), "eng_hi": max(hi, 1.0),
        "sf": rng.choice([-1, 0, n_sf - 1]), "range": rng.choice([0, 1, 2]),
    }
    if rng.random() < 0.1:
        name = rng.choice(list(fields))
        fields[name] = rng.choice([math.nan, math.inf, -7.0, 3, n_sf, 2**31 - 1, 255])
    return CodecScale(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", SEEDS)
def test_random_scaling_steps_are_refused_or_safe(seed: int) -> None:
    """Scaled items, scale factor sources and factor values past what the codec package
    builds: refused by emb_plan_check, or decoded without a fault (asan build too)."""
    rng = random.Random(3000 + seed)
    accepted = 0
    for _ in range(150):
        items = [random_c_item(rng, False) for _ in range(rng.randint(1, 3))]
        factors = ScaleFactors([f"sf{k}" for k in range(rng.randint(0, 3))])
        n_sf = len(factors.names)
        scales = [random_scale(rng, n_sf) for _ in items]
        sources = [(rng.choice([0, len(items) - 1, len(items)]),
                    rng.choice([0, n_sf - 1, n_sf])) for _ in range(rng.randint(0, 1))]
        try:
            plan = CodecPlan(False, items, [None] * len(items), scales,
                             factors if rng.random() < 0.9 else None, sources)
        except ValueError:
            continue
        accepted += 1
        block = Block.from_values([rng.choice([0, 1, 0x8000, 0xFFF6, 11, rng.randint(0, 0xFFFF)])
                                   for _ in range(rng.randint(0, 300))], False)
        for mode in (_ffi.CODEC_MODE_VALUES, _ffi.CODEC_MODE_TRACK, _ffi.CODEC_MODE_ALL):
            n = plan.decode(block, mode)
            assert 0 <= n <= len(items)
            assert len(plan.values()) == len(items)
    assert accepted > 10


@pytest.mark.parametrize("seed", SEEDS)
def test_random_encode_descriptions_never_crash(seed: int) -> None:
    rng = random.Random(2000 + seed)
    for _ in range(300):
        item = CodecItem(
            offset=0,
            nregs=rng.choice([0, 1, 2, 4, rng.randint(0, 200)]),
            wire=rng.randint(0, 20),
            flags=rng.randint(0, 255),
            bit=rng.randint(0, 255),
            target=0,
            out=0,
            scale=1.0,
            deadband=0.0,
        )
        raw = rng.choice([0, 1, -1, 2**63 - 1, -(2**63), 2**64 - 1, 99999999, 100000000])
        data = bytes(rng.randint(0, 255) for _ in range(rng.randint(0, 300)))
        try:
            registers = codec_encode(item, raw, rng.choice(WEIRD_NUMBERS), data)
        except ValueError:
            continue
        assert all(0 <= r <= 0xFFFF for r in registers)


def test_the_sanitizer_build_is_used_when_asked() -> None:
    native_file = str(getattr(sys.modules["edgemodbus._native"], "__file__", ""))
    asked = os.environ.get("EDGEMODBUS_NATIVE") == "asan"
    assert ("build-asan" in native_file) is asked
