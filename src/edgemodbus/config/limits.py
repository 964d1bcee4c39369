"""Size limits of what a config file may hold, and host names.

A config file is untrusted text: a 10 MB ``gatewayId`` was accepted and echoed into
every log line that named it.  So every string a config model takes is at most
:data:`MAX_TEXT` characters, ids, names and hosts less (:data:`MAX_NAME`,
:data:`MAX_HOST`; a model may name tighter ones per key, ``_max_lengths``), checked
with the other key rules (keys.py via base.py) before any validator sees the value.
Host names are checked as the resolver will take them (:func:`check_host`, protocol/hosts.py): a
``"plc..local"`` or a label over 63 characters fails at load, naming the field, not
later in a line's worker (RFC 1035 2.3.4: labels of 63 octets, names of 255 octets,
253 characters as text).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..protocol.hosts import MAX_HOST, MAX_LABEL, check_host  # one rule: the CLI's too
from .problems import Problem, join_path

MAX_TEXT = 4096
"""Characters of any string of a config file (descriptions, patterns, paths, topics)."""

MAX_NAME = 256
"""Characters of an id or a name (deviceCode, gatewayId, dtuId, item names...)."""

MIN_SECONDS = 0.001
"""The shortest duration in seconds a float-seconds field takes besides 0 (the ms the
code rounds to: a shorter one would round to 0, which means "never")."""


def length_problems(data: Mapping[str, Any], limits: Mapping[str, int],
                    prefix: str) -> list[Problem]:
    """Strings of ``data`` (canonical keys) longer than allowed: ``limits[key]``, else
    :data:`MAX_TEXT`; strings inside lists and objects of it too (a list of networks, a
    metadata object)."""
    problems: list[Problem] = []
    for key, value in data.items():
        limit = limits.get(key, MAX_TEXT)
        if isinstance(value, str):
            if len(value) > limit:
                problems.append(_too_long(join_path(prefix, key), value, limit))
        elif isinstance(value, (list, tuple)) and len(value) <= MAX_TEXT:
            for i, entry in enumerate(value):
                if isinstance(entry, str) and len(entry) > limit:
                    problems.append(_too_long(join_path(prefix, f"{key}[{i}]"), entry, limit))
    return problems


def _too_long(path: str, value: str, limit: int) -> Problem:
    return Problem(path, value, f"{len(value):,} characters: at most {limit:,}")


def check_seconds(value: float) -> float:
    """A duration in seconds where 0 means never: 0, or at least :data:`MIN_SECONDS`
    (a shorter one would round to 0 ms, silently "never")."""
    if 0 < value < MIN_SECONDS:
        raise ValueError(f"rounds to 0 ms, which means never: use 0 (never) or at least "
                         f"{MIN_SECONDS} s")
    return value


__all__ = ["MAX_HOST", "MAX_LABEL", "MAX_NAME", "MAX_TEXT", "MIN_SECONDS", "check_host",
           "check_seconds", "length_problems"]
