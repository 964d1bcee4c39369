"""CLI start-up: whole-process wall time of ``python -c "import edgemodbus"``
and of ``edgemodbus read`` of one register from a simulator, each over ``python -c pass``
timed in the same rounds (the interpreter's own start, the baseline).

Each round runs the three commands one after the other, so a busy moment of the shared
machine hits all three; the ratios are of the medians.  Children run with bytecode caches
on (PYTHONDONTWRITEBYTECODE removed from their environment: an installed package has its
.pyc files), after one warm-up run that writes them.  The simulator is started once, in a
process of its own (``python -m edgemodbus.sim``; in this process its thread answered
late, ~250 ms more per read, while the main thread waited on the child).  docs/benchmarks.md,
"CLI", has the absolute figures.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from tests.waiting import wait_for

from bench import gate
from bench.conftest import report, scale


def _edgemodbus_command() -> list[str]:
    """The console script installed beside this interpreter (what a user runs), else
    ``python -m edgemodbus.cli``."""
    script = Path(sys.executable).with_name("edgemodbus")
    if script.is_file():
        return [str(script)]
    found = shutil.which("edgemodbus")
    return [found] if found else [sys.executable, "-m", "edgemodbus.cli"]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.pop("PYTHONPROFILEIMPORTTIME", None)
    return env


def _wall(argv: Sequence[str], env: dict[str, str], number: bool = False) -> float:
    started = time.perf_counter()
    out = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=60,
                         check=False)
    took = time.perf_counter() - started
    assert out.returncode == 0, (argv, out.stderr)
    if number:  # a read printed the register's value
        assert out.stdout.strip().isdigit(), (argv, out.stdout, out.stderr)
    return took


@pytest.fixture(scope="module")
def simulator_port(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    log = tmp_path_factory.mktemp("sim") / "sim.out"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "edgemodbus.sim", "--port", "0",
                                 "--slaves", "1"], stdout=out, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: "tcp 127.0.0.1:" in log.read_text(), 30, "the simulator's port")
        first = log.read_text().splitlines()[0]  # "tcp 127.0.0.1:PORT"
        yield int(first.rsplit(":", 1)[1])
    finally:
        proc.terminate()
        proc.wait(30)


def test_cli_startup(simulator_port: int, benchmark: Any) -> None:
    env = _env()
    python = [sys.executable]
    commands = {
        "pass": ([*python, "-c", "pass"], False),
        "import": ([*python, "-c", "import edgemodbus"], False),
        "read": ([*_edgemodbus_command(), "read", "--host", "127.0.0.1", "--port",
                  str(simulator_port), "--rtu-over-tcp", "hr:7"], True),
    }
    for argv, number in commands.values():  # warm-up: writes the bytecode caches
        _wall(argv, env, number)
    times: dict[str, list[float]] = {name: [] for name in commands}
    for _ in range(scale(30, 9)):
        for name, (argv, number) in commands.items():
            times[name].append(_wall(argv, env, number))
    median = {name: statistics.median(values) for name, values in times.items()}
    import_ratio = median["import"] / median["pass"]
    read_ratio = median["read"] / median["pass"]
    benchmark.extra_info.update({f"{name}_ms": round(value * 1000, 1)
                                 for name, value in median.items()})
    report("CLI start-up, whole process, median wall time", [
        ("python -c pass", median["pass"] * 1000, "ms"),
        ("python -c 'import edgemodbus'", median["import"] * 1000, "ms"),
        ("edgemodbus read (simulator)", median["read"] * 1000, "ms"),
        ("import / pass", import_ratio, "x"),
        ("read / pass", read_ratio, "x"),
    ])
    gate.record("cli.import_vs_pass", import_ratio)
    gate.record("cli.read_vs_pass", read_ratio)
    read_argv, _ = commands["read"]
    benchmark.pedantic(_wall, args=(read_argv, env, True), rounds=scale(5, 2),
                       iterations=1)
