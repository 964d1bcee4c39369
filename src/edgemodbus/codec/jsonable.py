"""Values as strict JSON carries them: the one conversion used wherever edgemodbus makes
values JSON-able (snapshots, the CLI's JSON lines, MQTT payloads)."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["jsonable"]


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
