"""NormalizeIncomingValue: turn what a host hands to a write into a plain Python value.

Hosts pass values from JSON (numbers, booleans, strings, parsed or as text), from
MQTT payloads or from code.  This module accepts all of those and returns the Python
type the codec encodes for the item's type, or raises ``ValueError`` naming the item,
the value and what the type allows.  It does no range checks: the codec does them
after the multiplier is applied.
"""

from __future__ import annotations

import json
import math
from datetime import datetime, timezone
from typing import Any

from ..datatypes import DataType

_TRUE = frozenset({"true", "1", "on", "yes"})
_FALSE = frozenset({"false", "0", "off", "no"})


def normalize_value(name: str, data_type: DataType, value: Any) -> Any:
    """The value to encode for an item of ``data_type`` (its converted type, if any)."""
    if value is None:
        raise ValueError(f"{name}: no value given (null) for a {data_type.value} item")
    if data_type is DataType.STRING:
        return _to_str(name, value)
    if data_type is DataType.BINARY:
        return _to_bytes(name, value)
    if isinstance(value, (bytes, bytearray)):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str):
        value = _parse_text(name, data_type, value)
    if data_type is DataType.BOOLEAN:
        return _to_bool(name, value)
    if data_type is DataType.DATETIME:
        return _to_datetime(name, value)
    if data_type is DataType.CHAR and isinstance(value, str):
        return value
    return _to_number(name, data_type, value)


def _parse_text(name: str, data_type: DataType, text: str) -> Any:
    stripped = text.strip()
    if data_type is DataType.BOOLEAN and stripped.lower() in _TRUE | _FALSE:
        return stripped.lower() in _TRUE
    if data_type is DataType.DATETIME:
        try:
            return datetime.fromisoformat(stripped.replace("Z", "+00:00"))
        except ValueError:
            pass
    if data_type is DataType.CHAR and len(text) == 1:
        return text
    try:
        return json.loads(stripped)
    except ValueError:
        raise ValueError(
            f"{name}: {text!r} is not a {data_type.value} value "
            f"({_allowed(data_type)})"
        ) from None


def _allowed(data_type: DataType) -> str:
    if data_type is DataType.BOOLEAN:
        return "use true/false, 1/0 or on/off"
    if data_type is DataType.DATETIME:
        return "use an ISO 8601 time or Unix seconds"
    return "use a number"


def _to_bool(name: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)) and value in (0, 1):
        return bool(value)
    raise ValueError(f"{name}: {value!r} is not a Boolean value (use true/false, 1/0 or on/off)")


def _to_number(name: str, data_type: DataType, value: Any) -> int | float:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if data_type.is_integer and value.is_integer():
            return int(value)
        return value
    raise ValueError(f"{name}: {value!r} is not a number for a {data_type.value} item")


def _to_datetime(name: str, value: Any) -> datetime:
    if isinstance(value, datetime):
        return value if value.tzinfo else value.replace(tzinfo=timezone.utc)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return datetime.fromtimestamp(value, timezone.utc)
    raise ValueError(f"{name}: {value!r} is not a time (use an ISO 8601 time or Unix seconds)")


def _to_str(name: str, value: Any) -> str:
    if isinstance(value, str):
        text = value
        if len(text) >= 2 and text[0] == text[-1] == '"':
            try:
                decoded = json.loads(text)
            except ValueError:
                return text
            if isinstance(decoded, str):
                return decoded
        return text
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).decode("utf-8")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return str(value)
    raise ValueError(f"{name}: {value!r} is not text for a String item")


def _to_bytes(name: str, value: Any) -> bytes:
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, str):
        try:
            return bytes.fromhex(value.replace("0x", "").replace(" ", ""))
        except ValueError:
            pass
    if isinstance(value, list) and all(isinstance(b, int) and 0 <= b <= 255 for b in value):
        return bytes(value)
    raise ValueError(
        f"{name}: {value!r} is not binary data (use bytes, a hex string or a list of 0..255)"
    )
