"""Every benchmark module imports against the code as it is: a bench that still names a
removed internal (bench/test_bench_report.py imported the FaultPolicy mixin after it was
gone) fails here in `make test`, not only in `make bench-quick`."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"
MODULES = sorted(p.stem for p in BENCH.glob("*.py") if p.stem != "__init__")


@pytest.mark.parametrize("name", MODULES)
def test_the_bench_module_imports(name: str) -> None:
    importlib.import_module(f"bench.{name}")
