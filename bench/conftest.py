"""Shared benchmark set-up: quick mode for CI, a CPU-time helper, and the gate.

Benchmarks report ratios against a baseline measured in the same run (machines are
shared and noisy); they assert nothing about absolute speed.  Their headline ratios go
to the gate (bench/gate.py: ``gate.record(name, value)``): at the end of the session one
table shows every ratio with its target and gate limit, and the session fails when a
ratio is past its limit.  ``--bench-gate-all`` (the Makefile's bench targets) also fails
it when a gated ratio was not recorded.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import pytest

from bench import gate

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


# -- the gate (bench/gate.py) -------------------------------------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--bench-gate-all", action="store_true", default=False,
        help="fail the session when a gated benchmark ratio was not recorded",
    )


def _gate_failures(config: pytest.Config) -> list[str]:
    return gate.RECORDER.failures(gate.GATES, bool(config.getoption("--bench-gate-all")))


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """A ratio past its gate limit fails the run even when every test passed."""
    if session.config.option.collectonly:
        return
    if _gate_failures(session.config) and exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, exitstatus: int,
                            config: pytest.Config) -> None:
    """The one table of every gated ratio, after the tests (also under -q)."""
    require_all = bool(config.getoption("--bench-gate-all"))
    if config.option.collectonly or not (gate.RECORDER.ratios or require_all):
        return
    failed = bool(_gate_failures(config))
    terminalreporter.write_sep("=", "bench gate: ratios, targets and gate limits",
                               red=failed, green=not failed)
    for line in gate.RECORDER.summary(gate.GATES, require_all):
        terminalreporter.write_line(line)
