"""What a user's build gets (issue 29): -Werror only in development and CI builds
(EDGEMODBUS_WERROR=1, set by the Makefile), runtime dependencies as version ranges in
pyproject.toml, exact versions only in constraints.txt (make build)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _compile_args(werror: str | None) -> list[str]:
    """The C flags build_ffi.py hands to the compiler with EDGEMODBUS_WERROR as given."""
    env = {k: v for k, v in os.environ.items() if k != "EDGEMODBUS_WERROR"}
    if werror is not None:
        env["EDGEMODBUS_WERROR"] = werror
    code = ("import json, build_ffi; "
            "print(json.dumps(build_ffi.ffibuilder._assigned_source[3]['extra_compile_args']))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True,
                         text=True, timeout=60, check=True)
    args: list[str] = json.loads(out.stdout)
    return args


def test_werror_only_when_asked() -> None:
    assert "-Werror" not in _compile_args(None)  # pip install of the sdist
    assert "-Werror" not in _compile_args("0")
    strict = _compile_args("1")  # make build, .ci/run
    assert "-Werror" in strict and {"-Wall", "-Wextra"} <= set(strict)


def _dependencies() -> list[str]:
    tomllib = pytest.importorskip("tomllib")
    with (REPO / "pyproject.toml").open("rb") as f:
        deps: list[str] = tomllib.load(f)["project"]["dependencies"]
    return deps


def _name(requirement: str) -> str:
    return re.split(r"[<>=!~ ;\[]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def test_runtime_dependencies_are_ranges_with_an_upper_bound() -> None:
    for requirement in _dependencies():
        assert "==" not in requirement, f"{requirement}: exact pins go in constraints.txt"
        assert ">=" in requirement and "<" in requirement, \
            f"{requirement}: give a lower bound and the next major version as upper bound"


def test_constraints_pin_every_runtime_dependency_exactly() -> None:
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep and version, f"constraints.txt: {line!r} is not an exact pin"
            pins[name.strip().lower().replace("_", "-")] = version
    for requirement in _dependencies():
        assert _name(requirement) in pins, f"{requirement}: not pinned in constraints.txt"
