"""Size limits of what a config file may hold, and host names.

A config file is untrusted text: a 10 MB ``gatewayId`` was accepted and echoed into
every log line that named it.  So every string a config model takes is at most
:data:`MAX_TEXT` characters, ids, names and hosts less (:data:`MAX_NAME`,
:data:`MAX_HOST`; a model may name tighter ones per key, ``_max_lengths``), checked
with the other key rules (keys.py via base.py) before any validator sees the value.
Host names are checked as the resolver will take them (:func:`check_host`): a
``"plc..local"`` or a label over 63 characters fails at load, naming the field, not
later in a line's worker (RFC 1035 2.3.4: labels of 63 octets, names of 255 octets,
253 characters as text).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from typing import Any

from .problems import Problem, join_path

MAX_TEXT = 4096
"""Characters of any string of a config file (descriptions, patterns, paths, topics)."""

MAX_NAME = 256
"""Characters of an id or a name (deviceCode, gatewayId, dtuId, item names...)."""

MAX_HOST = 253
"""Characters of a host name (RFC 1035 2.3.4 as text: 255 octets on the wire)."""

MAX_LABEL = 63
"""Characters of one label of a host name (RFC 1035 2.3.4)."""

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


def check_host(value: str) -> str:
    """A host to connect to or listen on, as given: an IPv4 or IPv6 address, or a host
    name whose labels are 1..63 characters (letters, digits, ``-``, ``_``; non-ASCII
    names as IDNA takes them), at most 253 characters in all.  Empty passes (the
    model's cross checks say whether a host is required).  ValueError says what is
    wrong."""
    text = value.strip()
    if not text:
        return value
    if len(text) > MAX_HOST:
        raise ValueError(f"{len(text):,} characters: a host name has at most {MAX_HOST}")
    try:
        ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        pass
    else:
        return value
    name = text[:-1] if text.endswith(".") else text  # a fully qualified name's root
    for label in name.split("."):
        if not label:
            raise ValueError("is not a host name: an empty label (two dots in a row, or "
                             "a dot at the start); use e.g. plc1.local or 192.168.0.10")
        if len(label) > MAX_LABEL:
            raise ValueError(f"is not a host name: the label {label[:20]!r}... has "
                             f"{len(label)} characters, at most {MAX_LABEL}")
        if label.isascii() and not all(c.isalnum() or c in "-_" for c in label):
            raise ValueError(f"is not a host name: {label!r} has characters other than "
                             "letters, digits, '-' and '_' (give the host alone, without "
                             "scheme, port or path)")
    try:
        text.encode("idna")  # what the resolver does with it (socket.getaddrinfo)
    except UnicodeError as exc:
        raise ValueError(f"is not a host name IDNA can encode ({exc})") from None
    return value


def check_seconds(value: float) -> float:
    """A duration in seconds where 0 means never: 0, or at least :data:`MIN_SECONDS`
    (a shorter one would round to 0 ms, silently "never")."""
    if 0 < value < MIN_SECONDS:
        raise ValueError(f"rounds to 0 ms, which means never: use 0 (never) or at least "
                         f"{MIN_SECONDS} s")
    return value


__all__ = ["MAX_HOST", "MAX_LABEL", "MAX_NAME", "MAX_TEXT", "MIN_SECONDS", "check_host",
           "check_seconds", "length_problems"]
