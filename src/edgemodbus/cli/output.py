"""What every ``edgemodbus`` command shares: the user-error type, exact value text, JSON
lines, whole-line output and one-line problems."""

from __future__ import annotations

import sys
import threading
from typing import Any

from ..codec import json_text
from ..config import ConfigError

_stdout_lock = threading.Lock()  # lines from several line workers must not interleave


class CliError(Exception):
    """A user error: printed one line per problem, exit code 2."""

    def __init__(self, *lines: str) -> None:
        super().__init__("\n".join(lines))
        self.lines = list(lines)


def value_text(value: Any) -> str:
    """A value as text that reads back exactly: a float is its shortest round-trip form
    (``repr``: ``1.5e-07``, ``nan``, ``inf``), a Float item's value (codec.Float32) the
    shortest that reads back to the same float32 (``69.74496``), bytes are hex, times
    ISO 8601."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if hasattr(value, "isoformat"):
        return str(value.isoformat())
    return str(value)


def json_line(obj: Any) -> str:
    """One strict JSON line (the `run --json` output), values as codec.json_bytes writes
    them: NaN and infinities as "NaN", "Infinity", "-Infinity" (null is no value)."""
    return json_text(obj)


def emit(line: str) -> None:
    """One whole line on stdout (print() writes the newline separately, so lines from two
    line workers could interleave)."""
    with _stdout_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def print_json(data: Any) -> int:
    print(json_text(data, indent=True))
    return 0


def problem_lines(exc: BaseException) -> list[str]:
    """One line per problem: a ConfigError may hold several."""
    if isinstance(exc, CliError):
        return [one_line(line) for line in exc.lines]
    if isinstance(exc, ConfigError):
        return [one_line(str(p)) for p in exc.problems]
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return [f"{exc.filename}: {exc.strerror}"]
    return [one_line(str(exc)) or type(exc).__name__]


def one_line(text: str) -> str:
    return " ".join(text.split())
