"""Values as strict JSON carries them: the one conversion used wherever edgemodbus writes
values as JSON (the CLI's JSON lines, every MQTT payload, snapshots sent as JSON).  The
Python API (``item.value``, ``driver.snapshot()``) keeps Python values; only the JSON
writers convert.

The rules (docs/library.md "Values as text and JSON"):

* a finite float is a number, in its shortest form that reads back to it; a
  :class:`~edgemodbus.codec.float32.Float32` (a Float item's value) in the shortest
  form that reads back to the same float32 (``69.74496``, not ``69.74495697021484``);
* NaN and the infinities, which strict JSON has no number for, are the strings
  ``"NaN"``, ``"Infinity"`` and ``"-Infinity"`` (the names Protocol Buffers' JSON
  mapping uses, and what a write accepts back): never ``null``, which stays "no value";
* bytes are hex text, times ISO 8601 text; anything else JSON has no form for, its str.

:func:`jsonable` gives the converted Python objects; :func:`json_bytes` and
:func:`json_text` the JSON text itself, through orjson: orjson hands every value it has
no JSON for (bytes, times, a float subclass such as Float32) to :func:`_default`, but
writes NaN and the infinities as ``null`` itself, so text that has a ``null`` is written
again from :func:`jsonable`'s objects (a payload without one, the usual batch of good
values, is written once).  What orjson refuses outright (an integer beyond 64 bits, a
string with a lone surrogate) goes through the standard library's encoder after
:func:`jsonable`: slower, same values (non-ASCII text written as ``\\u`` escapes there)."""

from __future__ import annotations

import json
from typing import Any

import orjson

from .float32 import Float32, float32_short

__all__ = ["json_bytes", "json_text", "json_value", "jsonable"]

# Times go to _default (isoformat, as jsonable writes them) rather than orjson's own RFC
# 3339 form, which cannot carry an offset in seconds; keys that are not text become text.
_OPTIONS = orjson.OPT_PASSTHROUGH_DATETIME | orjson.OPT_NON_STR_KEYS
_INDENTED = _OPTIONS | orjson.OPT_INDENT_2


def _float(value: float) -> float | str:
    """A float as JSON carries it: a number, or the name of NaN or an infinity."""
    if value - value != 0.0:  # NaN or an infinity
        if value != value:
            return "NaN"
        return "Infinity" if value > 0 else "-Infinity"
    if isinstance(value, Float32):
        return float32_short(value)
    return float(value)


def jsonable(value: Any) -> Any:
    """``value`` with what JSON cannot carry replaced, inside dicts, lists and tuples too
    (the module's rules): floats as :func:`_float` says, bytes as hex, times as ISO 8601
    text; anything else is returned unchanged."""
    if isinstance(value, float):
        return _float(value)
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return value


def json_value(value: Any) -> Any:
    """:func:`jsonable` of one value, quick for the usual ones (a plain float, int, str,
    bool or None): for payloads built value by value (northbound/mqtt/payload.py)."""
    kind = type(value)
    if kind is float:
        return value if value - value == 0.0 else _float(value)
    if kind is int or kind is str or kind is bool or value is None:
        return value
    return jsonable(value)


def _default(value: Any) -> Any:
    """What orjson calls for a value it has no JSON for: jsonable's rules, else str."""
    if isinstance(value, float):  # a subclass (Float32): orjson writes only float itself
        return _float(value)
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return str(value)


def _dumps(obj: Any, indent: bool) -> bytes:
    try:
        return orjson.dumps(obj, default=_default, option=_INDENTED if indent else _OPTIONS)
    except TypeError:  # an int beyond 64 bits, a lone surrogate: the careful path
        # \u escapes: the only way JSON text carries a lone surrogate
        text = json.dumps(jsonable(obj), allow_nan=False, default=_default,
                          indent=2 if indent else None,
                          separators=None if indent else (",", ":"))
        return text.encode()


def json_bytes(obj: Any, *, indent: bool = False, converted: bool = False) -> bytes:
    """``obj`` as compact (or, with ``indent``, two-space indented) strict JSON, UTF-8.

    ``converted``: every float in ``obj`` already went through :func:`json_value` (no
    NaN or infinity is left), so the text is not checked for them."""
    out = _dumps(obj, indent)
    if not converted and b"null" in out:  # None, or NaN / an infinity orjson wrote so
        out = _dumps(jsonable(obj), indent)
    return out


def json_text(obj: Any, *, indent: bool = False) -> str:
    """:func:`json_bytes` as text (for printing)."""
    return json_bytes(obj, indent=indent).decode()
