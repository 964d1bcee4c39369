"""Check that tests and benchmarks wait for conditions, not for fixed times.

A test that sleeps a fixed time to let something happen passes on an idle machine and
fails on a loaded one (issue #24, "A suite that cannot flake").  What waits for something
uses tests/waiting.py's ``wait_for`` (or an event) with a generous deadline.  Checked on
the source text of tests/ and bench/ (nothing is imported):

* every call of ``time.sleep``, ``asyncio.sleep`` or a bare ``sleep`` carries a marker
  comment on one of its lines or the line above, saying why the time is fixed:

  - ``# pacing: <why>``: the time is part of the scenario (pacing a peer, holding a
    connection open on purpose, a window in which something is counted or must not
    happen);
  - ``# poll: <why>``: the step of a loop that checks a condition against a deadline;

* a ``wait_for(..., timeout=<number>)`` call (``tests.waiting.wait_for`` or a probe's)
  gives at least MIN_WAIT seconds, or carries ``# bound: <why>`` when the short deadline
  is itself what the test checks.

A marker needs its reason (the text after the colon).  Exit status 1 with one line per
violation, 0 when the tree is clean.  docs/testing.md says how to wait in a test.
"""

from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
from pathlib import Path

TOP = Path(__file__).resolve().parents[1]
TREES = ("tests", "bench")
MIN_WAIT = 10.0
SLEEP_MARKERS = ("pacing", "poll")
BOUND_MARKERS = ("bound",)
MARKER = re.compile(r"#\s*(pacing|poll|bound):\s*(\S.*)?$")


def _comments(source: str) -> dict[int, list[tuple[str, str]]]:
    """Line number -> the (marker, reason) pairs of the comments on it."""
    found: dict[int, list[tuple[str, str]]] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type != tokenize.COMMENT:
            continue
        match = MARKER.search(token.string)
        if match:
            found.setdefault(token.start[0], []).append((match[1], (match[2] or "").strip()))
    return found


def _callee(node: ast.Call) -> str:
    """``time.sleep`` -> "time.sleep", ``sleep`` -> "sleep", ``probe.wait_for`` -> ".wait_for"."""
    func = node.func
    if isinstance(func, ast.Name):
        return func.id
    if isinstance(func, ast.Attribute):
        owner = func.value.id if isinstance(func.value, ast.Name) else ""
        return f"{owner}.{func.attr}"
    return ""


def _constant_timeout(node: ast.Call, callee: str) -> float | None:
    """The call's ``timeout=`` as a number (tests/waiting.py's ``wait_for`` also takes it
    second by position); None when it is not a number written in the call."""
    given = [k.value for k in node.keywords if k.arg == "timeout"]
    if callee == "wait_for" and len(node.args) > 1:
        given.append(node.args[1])
    for value in given:
        if isinstance(value, ast.Constant) and isinstance(value.value, (int, float)) \
                and not isinstance(value.value, bool):
            return float(value.value)
    return None


def _marker(comments: dict[int, list[tuple[str, str]]], node: ast.Call,
            kinds: tuple[str, ...]) -> tuple[bool, bool]:
    """(a marker of ``kinds`` is there, it has a reason) on the call's lines or the one above."""
    last = node.end_lineno or node.lineno
    present = False
    for line in range(node.lineno - 1, last + 1):
        for kind, reason in comments.get(line, []):
            if kind in kinds:
                if reason:
                    return True, True
                present = True
    return present, False


def check_source(source: str, where: str) -> list[str]:
    """The violations of one file's text; ``where`` names it in the messages."""
    tree = ast.parse(source)
    comments = _comments(source)
    problems: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        callee = _callee(node)
        if callee in ("time.sleep", "asyncio.sleep", "sleep"):
            present, reasoned = _marker(comments, node, SLEEP_MARKERS)
            if not reasoned:
                what = "its marker gives no reason" if present else "no marker"
                problems.append((node.lineno,
                    f"{where}:{node.lineno}: {callee}() with {what}: wait for the condition "
                    "(tests/waiting.py wait_for), or say why the time is fixed with "
                    "'# pacing: <why>' or '# poll: <why>'"))
        elif callee == "wait_for" or callee.endswith(".wait_for"):
            timeout = _constant_timeout(node, callee)
            if timeout is None or timeout >= MIN_WAIT:
                continue
            present, reasoned = _marker(comments, node, BOUND_MARKERS)
            if not reasoned:
                problems.append((node.lineno,
                    f"{where}:{node.lineno}: {callee}(timeout={timeout:g}) is below "
                    f"{MIN_WAIT:g} s: give a generous deadline, or say why the short one is "
                    "what the test checks with '# bound: <why>'"))
    return [text for _, text in sorted(problems)]


def check(top: Path) -> list[str]:
    """The violations of every Python file under tests/ and bench/ of ``top``."""
    problems: list[str] = []
    for tree in TREES:
        for path in sorted((top / tree).rglob("*.py")):
            where = str(path.relative_to(top))
            problems += check_source(path.read_text(encoding="utf-8"), where)
    return problems


def main() -> int:
    problems = check(TOP)
    for problem in problems:
        print(problem)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
