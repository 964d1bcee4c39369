"""What every ``edgemodbus`` command shares: the user-error type, exact value text, JSON
lines, whole-line output and one-line problems."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import threading
from collections.abc import Iterator
from typing import Any

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
    from ..codec import json_text  # on first use: the codec loads the C extension

    return json_text(obj)


def emit(line: str) -> None:
    """One whole line on stdout (print() writes the newline separately, so lines from two
    line workers could interleave).  Once the reader went away (``edgemodbus run |
    head``), nothing more is written and the polling commands stop (see
    :func:`stop_when_stdout_closes`): no traceback per item update."""
    with _stdout_lock:
        if _closed.is_set():
            return
        try:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        except BrokenPipeError:
            _stdout_went_away()


_closed = threading.Event()  # the reader of stdout went away
_watchers: list[threading.Event] = []


def _stdout_went_away() -> None:
    """Point fd 1 at /dev/null (the interpreter's last flush at exit would fail again,
    with a message) and wake whoever waits for it."""
    _closed.set()
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        finally:
            os.close(devnull)
    except (OSError, ValueError):  # stdout is no file (captured): nothing to redirect
        pass
    for event in list(_watchers):
        event.set()


def stdout_closed() -> bool:
    """True once a write to stdout found its reader gone (EPIPE)."""
    return _closed.is_set()


@contextlib.contextmanager
def stop_when_stdout_closes(stop: threading.Event) -> Iterator[None]:
    """Set ``stop`` when stdout's reader goes away during the block (or went before)."""
    _watchers.append(stop)
    if _closed.is_set():
        stop.set()
    try:
        yield
    finally:
        _watchers.remove(stop)


def print_json(data: Any) -> int:
    """A JSON document on stdout; exit code 0, or 1 when stdout's reader went away
    (``edgemodbus descriptor | head``: no traceback, no error line)."""
    from ..codec import json_text

    emit(json_text(data, indent=True))
    return 1 if stdout_closed() else 0


def print_descriptor(args: argparse.Namespace) -> int:
    """``edgemodbus descriptor``: the driver descriptor JSON."""
    from ..descriptor import driver_descriptor

    return print_json(driver_descriptor(args.prefix))


def problem_lines(exc: BaseException) -> list[str]:
    """One line per problem: a ConfigError may hold several."""
    if isinstance(exc, CliError):
        return [one_line(line) for line in exc.lines]
    # a ConfigError exists only once config/ is loaded (importing it here would load
    # pydantic for every command)
    config = sys.modules.get("edgemodbus.config.problems")
    if config is not None and isinstance(exc, config.ConfigError):
        return [one_line(str(p)) for p in exc.problems]
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return [f"{exc.filename}: {exc.strerror}"]
    return [one_line(str(exc)) or type(exc).__name__]


def one_line(text: str) -> str:
    return " ".join(text.split())


MAX_WORD = 200
"""Characters of one word of an error line: a value given as 5,000 characters is shown
as its start and its length (argparse echoed it whole)."""


def shortened(line: str) -> str:
    """``line`` with each word longer than :data:`MAX_WORD` cut to its start and length."""
    return " ".join(word if len(word) <= MAX_WORD
                    else f"{word[:60]}... ({len(word):,} characters)"
                    for word in line.split(" "))


def in_file(file: str | os.PathLike[str], message: str) -> str:
    """``FILE: message`` on one line (the message as it is when it names the file)."""
    message = one_line(message)
    return message if message.startswith(f"{file}:") else f"{file}: {message}"


@contextlib.contextmanager
def config_warnings(messages: list[str]) -> Iterator[None]:
    """Collect into ``messages`` what edgemodbus.config logs (WARNING and up) in the
    block, instead of logging it: the caller prints each as a line that names its file
    (the log line would not say which file)."""
    collector = _Collector(logging.WARNING, messages)
    config_log = logging.getLogger("edgemodbus.config")
    propagate = config_log.propagate
    config_log.addHandler(collector)
    config_log.propagate = False
    try:
        yield
    finally:
        config_log.removeHandler(collector)
        config_log.propagate = propagate


class _Collector(logging.Handler):
    def __init__(self, level: int, messages: list[str]) -> None:
        super().__init__(level)
        self.messages = messages

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())
