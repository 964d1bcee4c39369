"""The one way we read a JSON file (device files, ``gateway.json``, templates, and the
CLI through them): a regular file of at most :data:`MAX_JSON_BYTES`, nested at most
:data:`MAX_JSON_DEPTH` levels.  Anything else is a :class:`ConfigError` that names the
file and the limit (one line, not a traceback: a 100,000-deep ``[[[...`` made
``json.loads`` raise RecursionError, and a FIFO made the load block forever)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from typing import Any

from .files import mode_kind, open_regular
from .keys import quote_key
from .problems import NO_VALUE, ConfigError, Problem

MAX_JSON_BYTES = 32 * 1024 * 1024
"""Bytes of a JSON file we read (a device file of 50,000 items is about 10 MB)."""

MAX_JSON_DEPTH = 32
"""Levels of objects and lists in a JSON file (a device file needs 5)."""


def _error(name: str, message: str) -> ConfigError:
    return ConfigError([Problem(name, NO_VALUE, message)])


def read_json_file(path: str | os.PathLike[str]) -> Any:
    """The decoded JSON of the file at ``path`` (UTF-8, a BOM allowed).  ConfigError
    names the file: not a regular file, too large, not UTF-8, invalid JSON, too deep;
    OSError when it cannot be opened (missing, permission)."""
    name = os.fspath(path)
    info = os.stat(name)
    kind = mode_kind(info.st_mode)
    if kind is not None:
        raise _error(name, f"is {kind}: give a JSON file")
    if info.st_size > MAX_JSON_BYTES:
        raise _error(name, f"{info.st_size:,} bytes: a JSON file we read has at most "
                           f"{MAX_JSON_BYTES:,}")
    fd, info = open_regular(name)  # the same kind and size as the stat said
    with os.fdopen(fd, "rb") as file:
        kind = mode_kind(info.st_mode)
        if kind is not None:  # it was replaced since the stat
            raise _error(name, f"is {kind}: give a JSON file")
        data = file.read(MAX_JSON_BYTES + 1)
    if len(data) > MAX_JSON_BYTES:  # it grew after the stat
        raise _error(name, f"more than {MAX_JSON_BYTES:,} bytes: a JSON file we read has "
                           "at most that many")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise _error(name, f"not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    return parse_json(text, name)


def parse_json(text: str, name: str) -> Any:
    """Decoded JSON ``text`` (``name`` says where it came from in messages), within the
    size and depth limits."""
    if len(text) > MAX_JSON_BYTES:
        raise _error(name, f"{len(text):,} characters: JSON we read has at most "
                           f"{MAX_JSON_BYTES:,}")
    try:
        data = json.loads(text.lstrip("\ufeff"))
    except json.JSONDecodeError as exc:
        raise _error(name, f"invalid JSON: {exc.msg} at line {exc.lineno} column "
                           f"{exc.colno}") from None
    except RecursionError:
        raise _error(name, f"nested more than {MAX_JSON_DEPTH} levels deep (objects and "
                           "lists): the limit of JSON we read") from None
    check_depth(data, name)
    return data


def check_depth(data: Any, name: str) -> None:
    """ConfigError naming the first place in ``data`` nested more than
    :data:`MAX_JSON_DEPTH` levels (walked without recursion)."""
    if _within_depth(data):
        return
    stack: list[tuple[Any, int, tuple[Any, ...]]] = [(data, 1, ())]
    while stack:
        value, depth, parents = stack.pop()
        children: Iterable[tuple[Any, Any]]
        if isinstance(value, Mapping):
            children = value.items()
        elif isinstance(value, (list, tuple)):
            children = enumerate(value)
        else:
            continue
        if depth > MAX_JSON_DEPTH:
            raise _error(name, f"{_path(parents)}: nested more than {MAX_JSON_DEPTH} levels "
                               "deep (objects and lists): the limit of JSON we read")
        for key, child in children:
            if isinstance(child, (Mapping, list, tuple)):
                stack.append((child, depth + 1, (*parents, key)))


def _within_depth(data: Any) -> bool:
    """Whether ``data`` is nested at most :data:`MAX_JSON_DEPTH` levels: the walk of
    :func:`check_depth` without the paths (a device file is thousands of containers;
    the path is made only for the error)."""
    level: list[Any] = [data]
    for _ in range(MAX_JSON_DEPTH):
        deeper: list[Any] = []
        for value in level:
            if isinstance(value, dict):
                value = value.values()
            elif not isinstance(value, (list, tuple)):
                if isinstance(value, Mapping):
                    value = value.values()
                else:
                    continue
            deeper += [v for v in value if isinstance(v, (dict, list, tuple, Mapping))]
        if not deeper:
            return True
        level = deeper
    return False


def _path(parents: tuple[Any, ...]) -> str:
    """The JSON path of a deep value, its first levels only."""
    text = ""
    for key in parents[:6]:
        text += f"[{key}]" if isinstance(key, int) else f".{quote_key(key).strip(chr(39))}"
    return (text.lstrip(".") or "<root>") + ("..." if len(parents) > 6 else "")


__all__ = ["MAX_JSON_BYTES", "MAX_JSON_DEPTH", "check_depth", "parse_json",
           "read_json_file"]
