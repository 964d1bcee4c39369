"""Host names to connect to or listen on, checked as the resolver will take them: the one
rule of the config models (config/limits.py) and the one-shot read (cli/oneshot.py).
RFC 1035 2.3.4: labels of 63 octets, names of 255 octets, 253 characters as text."""

from __future__ import annotations

import ipaddress

__all__ = ["MAX_HOST", "MAX_LABEL", "check_host"]

MAX_HOST = 253
"""Characters of a host name (RFC 1035 2.3.4 as text: 255 octets on the wire)."""

MAX_LABEL = 63
"""Characters of one label of a host name (RFC 1035 2.3.4)."""


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
