"""An independent decode of register values, written from the device-file contract
(docs/device-files.md "Byte order", "Int24 and UInt24"; docs/engineering-units.md
"Formulas"; Modbus Application Protocol 4.2: registers big-endian), never by calling
edgemodbus's codec: the reference the differential tests of the newer paths compare with
(wrapped reports decoded in C, the one-shot CLI read, the console's JSON).

``decode(registers, item, comm)`` gives ``(True, value)`` or ``(False, None)`` for a value
the contract says is invalid (a BCD digit over 9, a raw value outside rawMin..rawMax).
``float32_text(x)``: the shortest decimal that reads back to the float32 ``x``, as Python
writes that decimal.
"""

from __future__ import annotations

import math
import struct
from typing import Any

FORMAT64_OF = {"ABCD": "ABCDEFGH", "BADC": "BADCFEHG", "CDAB": "GHEFCDAB",
               "DCBA": "HGFEDCBA"}
"""dataFormat's meaning for 64-bit values (docs/device-files.md's table)."""

SIZES = {"UInt16": 1, "Int16": 1, "BCD16": 1, "Int32": 2, "UInt32": 2, "Float": 2,
         "Int24": 2, "UInt24": 2, "Int64": 4, "UInt64": 4, "Double": 4}


def _key(item: dict[str, Any], comm: dict[str, Any], key: str, default: Any) -> Any:
    """The item's key, else the device's, else the default (the item's wins)."""
    if key in item:
        return item[key]
    return comm.get(key, default)


def value_bytes(registers: list[int], order: str) -> bytes:
    """The value's bytes A (most significant).. from registers whose bytes, in address
    order and big-endian in each register, are the letters of ``order``."""
    wire = b"".join(struct.pack(">H", r) for r in registers)
    return bytes(wire[order.index(letter)] for letter in "ABCDEFGH"[:len(order)])


def raw_value(registers: list[int], item: dict[str, Any],
              comm: dict[str, Any]) -> tuple[bool, Any]:
    """The raw (unscaled) value of ``item`` (``deviceDataType``, optional ``bit``) over
    its registers."""
    data_type = item["deviceDataType"]
    fmt = str(_key(item, comm, "dataFormat", "ABCD")).upper()
    if data_type == "Boolean" or SIZES[data_type] == 1:
        reg = registers[0]
        if _key(item, comm, "byteSwap16", False):
            reg = ((reg & 0xFF) << 8) | (reg >> 8)
        if data_type == "Boolean":
            return True, bool(reg >> item["bit"] & 1)
        if data_type == "UInt16":
            return True, reg
        if data_type == "Int16":
            return True, reg - 0x10000 if reg >= 0x8000 else reg
        digits = [reg >> s & 0xF for s in (12, 8, 4, 0)]
        if max(digits) > 9:
            return False, None
        return True, int("".join(map(str, digits)))
    if SIZES[data_type] == 2:
        v = value_bytes(registers[:2], fmt)
        if data_type == "Float":
            return True, struct.unpack(">f", v)[0]
        if data_type in ("Int24", "UInt24"):
            n = int.from_bytes(v[1:], "big")
            return True, n - (1 << 24) if data_type == "Int24" and n >> 23 else n
        return True, int.from_bytes(v, "big", signed=data_type == "Int32")
    order64 = str(_key(item, comm, "dataFormat64", "") or FORMAT64_OF[fmt]).upper()
    v = value_bytes(registers[:4], order64)
    if data_type == "Double":
        return True, struct.unpack(">d", v)[0]
    return True, int.from_bytes(v, "big", signed=data_type == "Int64")


def scaled(raw: Any, item: dict[str, Any]) -> tuple[bool, Any]:
    """docs/engineering-units.md "Formulas", one double operation a step (a multiplier
    of 1/n divides by n); no scaleFactor here."""
    if "rawMin" in item:
        r0, r1 = float(item["rawMin"]), float(item["rawMax"])
        e0, e1 = float(item["engMin"]), float(item["engMax"])
        x = float(raw)
        lo, hi = min(r0, r1), max(r0, r1)
        if math.isnan(x) or not lo <= x <= hi:
            if not item.get("clamp") or math.isnan(x):
                return False, None
            x = lo if x < lo else hi
        k = (e1 - e0) / (r1 - r0)
        return True, (x - r0) * k + e0
    multiplier = float(item.get("dataMultiplier", 1))
    offset = float(item.get("offset", 0))
    if multiplier == 1 and offset == 0:
        return True, raw
    x = float(raw)
    if multiplier != 1:
        n = round(1 / multiplier)
        x = x / n if n != 0 and 1 / n == multiplier and abs(multiplier) < 1 else x * multiplier
    return True, x + offset if offset else x


def decode(registers: list[int], item: dict[str, Any],
           comm: dict[str, Any]) -> tuple[bool, Any]:
    """The engineering value of ``item`` over its registers (see the module)."""
    ok, raw = raw_value(registers, item, comm)
    if not ok or item["deviceDataType"] == "Boolean":
        return ok, raw
    return scaled(raw, item)


def same(value: Any, expected: Any) -> bool:
    """Equal values, NaN equal to NaN, a float's sign of zero ignored."""
    if isinstance(expected, float) and math.isnan(expected):
        return isinstance(value, float) and math.isnan(value)
    if isinstance(expected, bool) or isinstance(value, bool):
        return value is expected
    return bool(value == expected)


def float32_text(x: float) -> str:
    """The shortest decimal that reads back to float32 ``x`` (the nearest of that length),
    written as Python writes a float: ``69.74496``, ``nan``, ``inf``."""
    if not math.isfinite(x):
        return repr(x)
    want = struct.pack(">f", x)
    for digits in range(1, 10):
        text = f"{x:.{digits}g}"
        if struct.pack(">f", float(text)) == want:
            return repr(float(text))
    raise AssertionError(f"no float32 text for {x!r}")  # 9 digits always read back
