"""The benchmark gate (bench/gate.py): which figures fail a benchmark session, what its
table shows, and that the limits kept in one place are consistent.  Plain values only."""

from __future__ import annotations

import math

import pytest
from bench.gate import Gate, Recorder

LOWER = Gate(1.0, 1.5, "lower", "x", "cost over a baseline")
HIGHER = Gate(0.8, 0.5, "higher", "x", "rate kept")
GATES_2 = {"cost": LOWER, "rate": HIGHER}


def test_a_ratio_past_its_limit_fails_the_session() -> None:
    rec = Recorder()
    rec.record("cost", 1.6, GATES_2)
    rec.record("rate", 0.9, GATES_2)
    problems = rec.failures(GATES_2, require_all=True)
    assert len(problems) == 1 and problems[0].startswith("cost = 1.6 is past its gate limit")
    table = "\n".join(rec.summary(GATES_2, require_all=True))
    assert "FAIL: past the gate" in table and "bench gate: FAILED" in table


@pytest.mark.parametrize(("name", "value", "meets", "past"), [
    ("cost", 0.7, True, False),
    ("cost", 1.0, True, False),  # on the target
    ("cost", 1.2, False, False),  # misses the target, within the gate: the run passes
    ("cost", 1.5, False, False),  # on the limit
    ("cost", 1.51, False, True),
    ("rate", 0.95, True, False),
    ("rate", 0.6, False, False),
    ("rate", 0.49, False, True),
    ("rate", math.nan, False, True),  # a failed measurement never passes
    ("cost", math.inf, False, True),
])
def test_direction_target_and_limit(name: str, value: float, meets: bool, past: bool) -> None:
    recorded = Recorder().record(name, value, GATES_2)
    assert (recorded.meets_target, recorded.past_limit) == (meets, past)


def test_a_missing_benchmark_is_reported_and_fails_only_when_all_are_required() -> None:
    rec = Recorder()
    rec.record("cost", 0.9, GATES_2)
    assert rec.failures(GATES_2, require_all=False) == []
    assert rec.failures(GATES_2, require_all=True) == [
        "rate was not recorded (benchmark skipped or failed)"]
    lines = rec.summary(GATES_2, require_all=False)
    assert any(line.startswith("rate") and "MISSING" in line for line in lines)
    assert lines[-1] == "bench gate: passed"
    assert rec.summary(GATES_2, require_all=True)[-2:] == [
        "bench gate: FAILED", "  rate was not recorded (benchmark skipped or failed)"]


def test_the_table_has_one_row_per_gate_and_per_explicit_ratio() -> None:
    rec = Recorder()
    rec.record("cost", 1.2, GATES_2)
    rec.ratio("extra", 1.5, target=2.0, limit=4.0, better="lower")  # a figure without a gate
    rows = rec.summary(GATES_2, require_all=False)
    header, cost, rate, extra = rows[:4]
    assert header.split()[:5] == ["figure", "value", "target", "gate", "unit"]
    assert cost.split()[:7] == ["cost", "1.2", "<=", "1", "<=", "1.5", "x"]
    assert cost.endswith("misses target (within gate)")
    assert rate.split()[:6] == ["rate", "-", ">=", "0.8", ">=", "0.5"]
    assert extra.split()[:6] == ["extra", "1.5", "<=", "2", "<=", "4"] and extra.endswith("ok")


def test_recording_mistakes_are_refused() -> None:
    rec = Recorder()
    with pytest.raises(KeyError, match="no gate named 'nope'"):
        rec.record("nope", 1.0, GATES_2)
    rec.record("cost", 1.0, GATES_2)
    with pytest.raises(ValueError, match="recorded twice"):
        rec.record("cost", 1.1, GATES_2)
    with pytest.raises(ValueError, match="stricter than target"):
        rec.ratio("x", 1.0, target=1.0, limit=0.9, better="lower")
    with pytest.raises(ValueError, match="stricter than target"):
        Gate(0.8, 0.9, "higher", "x", "a limit above a higher-is-better target")
