"""Shared benchmark set-up: quick mode for CI and a CPU-time helper.

Benchmarks report ratios against a baseline measured in the same run (machines are
shared and noisy); they assert nothing about absolute speed.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

QUICK = os.environ.get("EDGEMODBUS_BENCH_QUICK") == "1"


def scale(full: int, quick: int) -> int:
    """An iteration count: ``quick`` in CI's quick mode, else ``full``."""
    return quick if QUICK else full


def cpu_seconds() -> float:
    """CPU time (user + system) of this process, all threads: the line worker's
    syscalls count, the peer process's do not."""
    return time.process_time()


def cpu_per_call(fn: Callable[[], object], calls: int, repeats: int = 3) -> float:
    """Best-of-``repeats`` CPU seconds per call of ``fn`` (``calls`` calls each)."""
    best = float("inf")
    for _ in range(repeats):
        start_cpu = cpu_seconds()
        for _ in range(calls):
            fn()
        best = min(best, (cpu_seconds() - start_cpu) / calls)
    return best


def report(title: str, rows: list[tuple[str, float, str]]) -> str:
    """A small table, printed (shown with -s or in CI's log) and returned."""
    width = max(len(name) for name, _, _ in rows)
    lines = [title] + [f"  {name:<{width}}  {value:>10.2f}  {unit}" for name, value, unit in rows]
    text = "\n".join(lines)
    print("\n" + text)
    return text
