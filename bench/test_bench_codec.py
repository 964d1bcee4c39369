"""Decode cost per value of a 120-register block: our C batch codec against a plain
Python struct decoder and against pymodbus' per-item ``convert_from_registers``; and the
same block with every number in engineering units (an offset, docs/engineering-units.md),
beside the plain one, whose items pay nothing for the feature (run this module against
a build without it for the before/after figure).

Prints a table of ns per value (and the ratios, from this same run) when the module
ends.  EDGEMODBUS_BENCH_QUICK=1 keeps every benchmark short.
"""

from __future__ import annotations

import os
import random
import struct
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import pytest
from pymodbus.client.mixin import ModbusClientMixin
from pytest_benchmark.fixture import BenchmarkFixture

from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, ValueSpec, encode
from edgemodbus.datatypes import Area, DataFormat, DataType

QUICK = os.environ.get("EDGEMODBUS_BENCH_QUICK") == "1"
T, F = DataType, DataFormat
DT = ModbusClientMixin.DATATYPE

# -- the block: 120 registers, 107 values ------------------------------------------------

SPECS: list[tuple[int, ValueSpec]] = []
_offset = 0


def _add(spec: ValueSpec, registers: int) -> None:
    global _offset
    SPECS.append((_offset, spec))
    _offset += registers


for _k in range(30):
    _add(ValueSpec(f"temp{_k}", T.INT16), 1)
for _k in range(20):
    _add(ValueSpec(f"count{_k}", T.UINT16), 1)
for _k in range(10):
    _add(ValueSpec(f"energy{_k}", T.INT32, F.CDAB), 2)
for _k in range(10):
    _add(ValueSpec(f"flow{_k}", T.FLOAT), 2)
for _k in range(4):
    _add(ValueSpec(f"total{_k}", T.DOUBLE), 4)
for _r in range(2):
    for _b in range(16):
        SPECS.append((_offset, ValueSpec(f"alarm{_r}_{_b}", T.BOOLEAN, bit=_b)))
    _offset += 1
_add(ValueSpec("model", T.STRING, quantity=12), 12)
REGISTERS = _offset
N_VALUES = len(SPECS)
assert REGISTERS == 120


def _registers(seed: int) -> list[int]:
    """Plausible device data; every value differs between seeds 0 and 1."""
    rng = random.Random(42)
    regs: list[int] = []
    for _, spec in SPECS:
        t = spec.data_type
        if spec.bit is not None:
            if spec.bit == 0:
                regs.append(rng.randrange(0x10000) ^ (0xFFFF * (seed & 1)))
            continue
        value: object
        if t is T.INT16:
            value = rng.randint(-400, 1200) * 2 + seed
        elif t is T.UINT16:
            value = rng.randint(0, 30000) * 2 + seed
        elif t is T.INT32:
            value = rng.randint(-(10**8), 10**8) * 2 + seed
        elif t in (T.FLOAT, T.DOUBLE):
            value = rng.uniform(-1000, 1000) + seed
        else:
            value = f"EMB-{seed}-GW{rng.randint(1000, 9999)}"
        regs += encode(spec, value)
    return regs


REGS_A = _registers(0)
REGS_B = _registers(1)


# -- the comparison decoders ---------------------------------------------------------------


def struct_decoder() -> Callable[[list[int]], list[object]]:
    """A straightforward pure-Python decoder of the same items, with struct."""
    steps: list[Callable[[bytes, list[int]], object]] = []
    for offset, spec in SPECS:
        t, fmt = spec.data_type, spec.data_format
        if spec.bit is not None:
            steps.append(lambda raw, regs, o=offset, b=spec.bit: (regs[o] >> b) & 1 == 1)
        elif t is T.STRING:
            q = spec.quantity or 0
            steps.append(
                lambda raw, regs, o=offset, q=q: (
                    raw[2 * o : 2 * o + 2 * q].rstrip(b"\0").decode("utf-8", "replace")
                )
            )
        else:
            code, width = {
                T.INT16: ("h", 1),
                T.UINT16: ("H", 1),
                T.INT32: ("i", 2),
                T.FLOAT: ("f", 2),
                T.DOUBLE: ("d", 4),
            }[t]
            unpack = struct.Struct(">" + code).unpack
            if fmt.word_swap:

                def step(
                    raw: bytes,
                    regs: list[int],
                    o: int = offset,
                    w: int = width,
                    unpack: Any = unpack,
                ) -> object:
                    words = regs[o : o + w][::-1]
                    return unpack(struct.pack(f">{w}H", *words))[0]
            else:
                unpack_from = struct.Struct(">" + code).unpack_from

                def step(
                    raw: bytes, regs: list[int], o: int = offset, unpack_from: Any = unpack_from
                ) -> object:
                    return unpack_from(raw, 2 * o)[0]

            steps.append(step)
    pack = struct.Struct(f">{REGISTERS}H").pack

    def decode(regs: list[int]) -> list[object]:
        raw = pack(*regs)
        return [step(raw, regs) for step in steps]

    return decode


def pymodbus_decoder() -> Callable[[list[int]], list[object]]:
    """pymodbus 3.16.1: one ``convert_from_registers`` call per item (per register for
    the 16 bits packed in one register)."""
    convert = ModbusClientMixin.convert_from_registers
    plan: list[tuple[int, int, Any, str, int | None]] = []
    for offset, spec in SPECS:
        t = spec.data_type
        if spec.bit is not None:
            if spec.bit == 0:
                plan.append((offset, 1, DT.BITS, "big", 16))
            continue
        kind, width = {
            T.INT16: (DT.INT16, 1),
            T.UINT16: (DT.UINT16, 1),
            T.INT32: (DT.INT32, 2),
            T.FLOAT: (DT.FLOAT32, 2),
            T.DOUBLE: (DT.FLOAT64, 4),
            T.STRING: (DT.STRING, spec.quantity or 0),
        }[t]
        plan.append((offset, width, kind, "little" if spec.data_format.word_swap else "big", None))

    def decode(regs: list[int]) -> list[object]:
        out: list[object] = []
        for offset, width, kind, order, bits in plan:
            value = convert(regs[offset : offset + width], kind, word_order=order)
            if bits:
                out += value  # type: ignore[arg-type]
            else:
                out.append(value)
        return out

    return decode


# -- benchmarks ------------------------------------------------------------------------------

RESULTS: dict[str, tuple[float, float]] = {}  # name -> (min, median) seconds per call


def _run(benchmark: BenchmarkFixture, name: str, fn: Callable[[], object]) -> None:
    if QUICK:
        benchmark.pedantic(fn, rounds=30, iterations=20, warmup_rounds=2)
    else:
        benchmark(fn)
    stats = benchmark.stats.stats
    RESULTS[name] = (stats.min, stats.median)


@pytest.fixture(scope="module", autouse=True)
def table(request: pytest.FixtureRequest) -> Iterator[None]:
    """Print ns/value and speed-ups of this run once the module's benchmarks are done."""
    yield
    if not RESULTS:
        return
    struct_s = RESULTS.get("python struct", (0.0, 0.0))[0]
    pymodbus_s = RESULTS.get("pymodbus convert_from_registers", (0.0, 0.0))[0]
    lines = [
        "",
        f"codec: {REGISTERS}-register block, {N_VALUES} values (Int16, UInt16, Int32 CDAB, "
        "Float, Double, 32 bits of registers, one String)",
        f"{'decoder':36s} {'ns/value':>9s} {'median':>7s} {'faster than struct':>19s} "
        f"{'than pymodbus':>14s}",
    ]
    for name, (low, median) in RESULTS.items():
        vs_struct = f"{struct_s / low:.1f}x" if struct_s and name.startswith("ours") else "-"
        vs_pymodbus = f"{pymodbus_s / low:.1f}x" if pymodbus_s and name.startswith("ours") else "-"
        lines.append(
            f"{name:36s} {1e9 * low / N_VALUES:9.1f} {1e9 * median / N_VALUES:7.1f} "
            f"{vs_struct:>19s} {vs_pymodbus:>14s}"
        )
    lines.append("(ns/value: fastest round; median: median round; speed-ups from the fastest)")
    capture = request.config.pluginmanager.getplugin("capturemanager")
    reporter = request.config.pluginmanager.getplugin("terminalreporter")
    with capture.global_and_fixture_disabled():
        for line in lines:
            if reporter is not None:
                reporter.write_line(line)
            else:
                print(line)


@pytest.fixture(scope="module")
def blocks() -> tuple[Block, Block]:
    return Block.from_values(REGS_A, bits=False), Block.from_values(REGS_B, bits=False)


def test_struct_reference(benchmark: BenchmarkFixture) -> None:
    decode = struct_decoder()
    ours = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    assert decode(REGS_A) == ours.decode_values(Block.from_values(REGS_A, bits=False))
    _run(benchmark, "python struct", lambda: decode(REGS_A))


def test_pymodbus(benchmark: BenchmarkFixture) -> None:
    decode = pymodbus_decoder()
    values = decode(REGS_A)
    assert len(values) == N_VALUES
    assert (
        values[:50]
        == BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS).decode_values(
            Block.from_values(REGS_A, bits=False)
        )[:50]
    )
    _run(benchmark, "pymodbus convert_from_registers", lambda: decode(REGS_A))


def test_ours_decode_values(benchmark: BenchmarkFixture, blocks: tuple[Block, Block]) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    block = blocks[0]
    _run(benchmark, "ours decode_values", lambda: decoder.decode_values(block))


def test_ours_report_all_every_value_new(
    benchmark: BenchmarkFixture, blocks: tuple[Block, Block]
) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    flip = [0]

    def run() -> object:
        flip[0] ^= 1
        return decoder.decode(blocks[flip[0]], report_all=True)

    assert len(decoder.decode(blocks[0])) == N_VALUES
    assert len(decoder.decode(blocks[1])) == N_VALUES  # every value differs between A and B
    _run(benchmark, "ours decode(report_all) all new", run)


def test_ours_report_all_unchanged(
    benchmark: BenchmarkFixture, blocks: tuple[Block, Block]
) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    decoder.decode(blocks[0])
    _run(
        benchmark,
        "ours decode(report_all) unchanged",
        lambda: decoder.decode(blocks[0], report_all=True),
    )


def test_ours_nothing_changed(benchmark: BenchmarkFixture, blocks: tuple[Block, Block]) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    decoder.decode(blocks[0])
    assert decoder.decode(blocks[0]) == []
    _run(benchmark, "ours decode, nothing changed", lambda: decoder.decode(blocks[0]))


def _scaled_specs() -> list[tuple[int, ValueSpec]]:
    """SPECS with an offset on every numeric item (the String and bits stay as they are)."""
    if "offset" not in getattr(ValueSpec, "__dataclass_fields__", {}):
        pytest.skip("this build has no engineering units (ValueSpec.offset)")
    return [(o, replace(spec, offset=0.5) if spec.data_type.is_numeric else spec)
            for o, spec in SPECS]


def test_ours_scaled_nothing_changed(
    benchmark: BenchmarkFixture, blocks: tuple[Block, Block]
) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, _scaled_specs())
    decoder.decode(blocks[0])
    assert decoder.decode(blocks[0]) == []
    _run(benchmark, "ours decode, nothing changed, offsets", lambda: decoder.decode(blocks[0]))


def test_ours_scaled_decode_values(
    benchmark: BenchmarkFixture, blocks: tuple[Block, Block]
) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, _scaled_specs())
    block = blocks[0]
    plain = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS).decode_values(block)
    scaled = decoder.decode_values(block)
    assert [v + 0.5 if isinstance(v, (int, float)) and not isinstance(v, bool) else v
            for v in plain] == scaled
    _run(benchmark, "ours decode_values, offsets", lambda: decoder.decode_values(block))


def test_ours_one_value_changed(benchmark: BenchmarkFixture, blocks: tuple[Block, Block]) -> None:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, REGISTERS, SPECS)
    one = Block.from_values([REGS_A[0] ^ 1, *REGS_A[1:]], bits=False)
    pair = (blocks[0], one)
    flip = [0]
    decoder.decode(blocks[0])

    def run() -> object:
        flip[0] ^= 1
        return decoder.decode(pair[flip[0]])

    assert len(run()) == 1
    _run(benchmark, "ours decode, 1 value changed", run)
