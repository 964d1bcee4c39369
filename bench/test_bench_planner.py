"""Planner throughput: plan 100,000 items of mixed areas and sizes.

EDGEMODBUS_BENCH_QUICK=1 runs fewer rounds.
"""

from __future__ import annotations

import os
import random

from pytest_benchmark.fixture import BenchmarkFixture

from edgemodbus.datatypes import Area
from edgemodbus.poll.planner import PlanItem, ReadBlock, plan_reads

QUICK = os.environ.get("EDGEMODBUS_BENCH_QUICK") == "1"
N_ITEMS = 100_000


def make_items(n: int = N_ITEMS, seed: int = 4) -> list[PlanItem]:
    """Tags as gateways see them: clusters of registers with holes, some long strings."""
    rng = random.Random(seed)
    areas = [Area.HOLDING_REGISTER] * 4 + [Area.INPUT_REGISTER] * 3 + [Area.COIL] * 2
    areas.append(Area.DISCRETE_INPUT)
    register_sizes = [1, 1, 1, 2, 2, 2, 4, 10]
    items: list[PlanItem] = []
    cursor = {a: 0 for a in Area}
    for i in range(n):
        area = rng.choice(areas)
        if area.is_bit:
            size = 1
        elif rng.random() < 0.001:
            size = rng.randint(126, 300)  # read in pieces
        else:
            size = rng.choice(register_sizes)
        cursor[area] += rng.choice((0, 0, 0, 1, 2, 5, 15))
        if cursor[area] + size > 65536:
            cursor[area] = 0
        items.append(PlanItem(f"t{i}", area, cursor[area], size))
        cursor[area] += size if rng.random() < 0.9 else 0  # a few overlapping items
    rng.shuffle(items)
    return items


def test_plan_100k_items(benchmark: BenchmarkFixture) -> None:
    items = make_items()
    rounds = 3 if QUICK else 10
    blocks: list[ReadBlock] = benchmark.pedantic(
        plan_reads, args=(items,), rounds=rounds, iterations=1, warmup_rounds=0 if QUICK else 1
    )
    planned = {p.key for b in blocks for p in b.pieces}
    assert len(planned) == N_ITEMS
    assert all(b.count <= (2000 if b.area.is_bit else 120) for b in blocks)
    benchmark.extra_info["items"] = N_ITEMS
    benchmark.extra_info["blocks"] = len(blocks)
