"""Values as strict JSON carries them: the one conversion used wherever edgemodbus makes
values JSON (snapshots, the CLI's JSON output, every MQTT payload).

:func:`jsonable` gives the Python objects (for ``snapshot()`` and callers that serialise
themselves); :func:`json_bytes` and :func:`json_text` give the JSON text itself, through
orjson, by the same rules: orjson writes NaN and the infinities as null, and hands every
other value it has no JSON for to :func:`_default`, which applies :func:`jsonable`'s rules
(bytes as hex, times as ISO 8601, anything else as its ``str``).  What orjson refuses
outright (an integer beyond 64 bits, a string with a lone surrogate) goes through the
standard library's encoder after :func:`jsonable`: slower, same values (non-ASCII text
written as ``\\u`` escapes there)."""

from __future__ import annotations

import json
import math
from typing import Any

import orjson

__all__ = ["json_bytes", "json_text", "jsonable"]

# Times go to _default (isoformat, as jsonable writes them) rather than orjson's own RFC
# 3339 form, which cannot carry an offset in seconds; keys that are not text become text.
_OPTIONS = orjson.OPT_PASSTHROUGH_DATETIME | orjson.OPT_NON_STR_KEYS
_INDENTED = _OPTIONS | orjson.OPT_INDENT_2


def jsonable(value: Any) -> Any:
    """``value`` with what JSON cannot carry replaced, inside dicts, lists and tuples too:
    finite floats stay as they are (json writes their shortest round-trip form), NaN and
    the infinities become null (strict JSON has no such numbers), bytes become hex and
    times ISO 8601 text; anything else is returned unchanged."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


def _default(value: Any) -> Any:
    """What orjson calls for a value it has no JSON for: jsonable's rules, else str."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return str(value)


def json_bytes(obj: Any, *, indent: bool = False) -> bytes:
    """``obj`` as compact (or, with ``indent``, two-space indented) strict JSON, UTF-8."""
    try:
        return orjson.dumps(obj, default=_default, option=_INDENTED if indent else _OPTIONS)
    except TypeError:  # an int beyond 64 bits, a lone surrogate: the careful path
        # \u escapes: the only way JSON text carries a lone surrogate
        text = json.dumps(jsonable(obj), allow_nan=False, default=_default,
                          indent=2 if indent else None,
                          separators=None if indent else (",", ":"))
        return text.encode()


def json_text(obj: Any, *, indent: bool = False) -> str:
    """:func:`json_bytes` as text (for printing)."""
    return json_bytes(obj, indent=indent).decode()
