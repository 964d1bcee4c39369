"""tools/check_tests.py finds a fixed sleep without its reason and a short deadline in a
test's wait, in sources made for the test, and the repository's tests have none
(make lint runs it)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

TOP = Path(__file__).resolve().parents[2]
TOOL = TOP / "tools" / "check_tests.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("check_tests", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _lines(source: str) -> list[int]:
    """The line numbers the check reports in ``source``."""
    return [int(p.split(":")[1]) for p in _tool().check_source(source, "t.py")]


def test_the_repository_s_tests_and_benchmarks_pass() -> None:
    assert _tool().check(TOP) == []


@pytest.mark.parametrize("call", [
    "time.sleep(0.5)", "asyncio.sleep(0.1)", "sleep(1)", "time.sleep(seconds)",
])
def test_an_unmarked_sleep_is_reported(call: str) -> None:
    assert _lines(f"import time\n\ndef test() -> None:\n    {call}\n") == [4]


@pytest.mark.parametrize("source", [
    "time.sleep(0.5)  # pacing: the peer answers slowly on purpose\n",
    "time.sleep(0.01)  # poll: the step of a loop with a deadline\n",
    "# pacing: a window in which nothing may happen\ntime.sleep(1.0)\n",
    "time.sleep(\n    0.5,  # pacing: on the call's second line\n)\n",
])
def test_a_sleep_with_a_reasoned_marker_passes(source: str) -> None:
    assert _lines(source) == []


@pytest.mark.parametrize("source", [
    "time.sleep(0.5)  # pacing:\n",  # no reason
    "time.sleep(0.5)  # pacing:   \n",
    "time.sleep(0.5)  # let things settle\n",  # no marker word
    "time.sleep(0.5)  # bound: a wait_for marker does not excuse a sleep\n",
    "# pacing: two lines above does not count\n\ntime.sleep(0.5)\n",
    "x = 1  # pacing: a marker on another statement\ny = 2\ntime.sleep(0.5)\n",
])
def test_a_sleep_without_a_reasoned_marker_is_reported(source: str) -> None:
    assert len(_lines(source)) == 1


def test_a_string_that_looks_like_a_marker_is_not_one() -> None:
    assert _lines('time.sleep(0.5); s = "# pacing: inside a string"\n') == [1]


@pytest.mark.parametrize(("source", "reported"), [
    ("wait_for(cond, timeout=5)\n", True),
    ("wait_for(cond, 3, 'Running')\n", True),  # tests/waiting.py's second argument
    ("probe.wait_for('a/b', timeout=2.5)\n", True),
    ("wait_for(cond, timeout=9.99)\n", True),
    ("wait_for(cond, timeout=10)\n", False),
    ("wait_for(cond, 20, 'Running')\n", False),
    ("wait_for(cond)\n", False),  # its default: 20 s
    ("wait_for(cond, timeout=limit)\n", False),  # not a number written here
    ("probe.wait_for('a/b', cond)\n", False),  # a probe's second argument is no timeout
    ("wait_for(cond, timeout=2)  # bound: closed before the 10 s timeout\n", False),
    ("wait_for(cond, timeout=2)  # bound:\n", True),
    ("wait_for(cond, timeout=2)  # pacing: not the marker for a deadline\n", True),
])
def test_a_short_deadline_needs_its_bound_marker(source: str, reported: bool) -> None:
    assert bool(_lines(source)) is reported


def test_each_finding_names_file_and_line_in_order() -> None:
    source = "time.sleep(1)\nwait_for(c, timeout=1)\nasyncio.sleep(2)\n"
    found = _tool().check_source(source, "tests/x.py")
    assert [p.split(":")[:2] for p in found] == [["tests/x.py", "1"], ["tests/x.py", "2"],
                                                 ["tests/x.py", "3"]]
    assert "tests/waiting.py" in found[0] and "'# bound: <why>'" in found[1]
