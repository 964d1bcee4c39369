"""Tag lists from other tools -> our device file (docs/command-line.md, "Importing a tag list").

Two CSV forms, told apart by the header row:

* Kepware's CSV export of a Modbus device's tags (columns ``Tag Name, Address, Data
  Type, Respect Data Type, Client Access, Scan Rate, Scaling, Raw Low, Raw High, Scaled
  Low, Scaled High, Scaled Data Type, Clamp Low, Clamp High, Eng Units, Description``,
  and ``Negate Value`` where present).  Addresses are Modicon entity numbers as Kepware
  writes them with its default zero-based addressing (``400001`` and ``40001`` = holding
  register 0, ``300010``, ``100001``, ``000001``), with ``.bit`` (0..15) on registers.
* A generic list: ``name, address, type`` and optionally ``scanRate`` (ms), ``scale``
  (a multiplier), ``unit``, ``description`` and the engineering units keys ``offset``,
  ``rawMin``, ``rawMax``, ``engMin``, ``engMax``, ``clamp``, ``scaleFactor``
  (docs/engineering-units.md); its addresses are ours (``hr:100``), read with the
  chosen ``addressPrefix`` (``entity`` reads ``40001``).  A row with a scaleFactor is
  checked alone: the item it names is checked when the device file loads.

Every row is converted on its own and checked by the config loader; a row that cannot be
converted is a :class:`Refusal` naming its row (the header is row 1), column, value and
what is allowed.  Addresses are written in our canonical form (``ir:9``), which every
addressPrefix reads the same way.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..config import ConfigError, load_device_config
from ..datatypes import DataType
from ..protocol.address import entity_lookalike, entity_notice, format_address, parse_address

KEPWARE_COLUMNS: tuple[str, ...] = (
    "Tag Name", "Address", "Data Type", "Respect Data Type", "Client Access", "Scan Rate",
    "Scaling", "Raw Low", "Raw High", "Scaled Low", "Scaled High", "Scaled Data Type",
    "Clamp Low", "Clamp High", "Eng Units", "Description",
)
GENERIC_COLUMNS: tuple[str, ...] = ("name", "address", "type", "scanRate", "scale", "unit",
                                    "description", "offset", "rawMin", "rawMax", "engMin",
                                    "engMax", "clamp", "scaleFactor")

KEPWARE_TYPES: dict[str, DataType] = {
    "Boolean": DataType.BOOLEAN,
    "Short": DataType.INT16,
    "Word": DataType.UINT16,
    "Long": DataType.INT32,
    "DWord": DataType.UINT32,
    "LLong": DataType.INT64,
    "QWord": DataType.UINT64,
    "Float": DataType.FLOAT,
    "Double": DataType.DOUBLE,
    "BCD": DataType.BCD16,
    "LBCD": DataType.BCD32,
}
"""Kepware's Modbus data types with one meaning here ("Default": Boolean for bits, Word
for registers).  Not converted: String (its length and byte order live in an address
suffix), Char and Byte (8-bit values), arrays."""

_KEPWARE_LOWER = {k.lower(): v for k, v in KEPWARE_TYPES.items()}
_KEPWARE_ALLOWED = "Default, " + ", ".join(KEPWARE_TYPES)


@dataclass(frozen=True, slots=True)
class Refusal:
    """One row that was not converted: where, what and why."""

    row: int
    column: str
    value: str
    reason: str

    def __str__(self) -> str:
        return f"row {self.row}, column {self.column!r}, value {self.value!r}: {self.reason}"


@dataclass(slots=True)
class ImportResult:
    """The converted items (device-file dicts, in row order), the refused rows, and
    ``notice``: the first generic row whose bare address looks like a Modicon entity
    number but was read as an offset (``40001`` -> hr:40001), with the count of such
    rows; None when there is none."""

    form: str
    items: list[dict[str, Any]] = field(default_factory=list)
    refused: list[Refusal] = field(default_factory=list)
    notice: str | None = None
    entity_lookalikes: int = 0

    def device(self, communication: dict[str, Any] | None = None,
               organization: dict[str, Any] | None = None) -> dict[str, Any]:
        """A device file holding the converted items."""
        return {"organization": dict(organization or {}),
                "communication": dict(communication or {}),
                "addressList": list(self.items)}


class _Refused(Exception):
    def __init__(self, column: str, value: str, reason: str) -> None:
        super().__init__(reason)
        self.column, self.value, self.reason = column, value, reason


def _number(text: str, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise _Refused(column, text, "must be a number") from None
    if not math.isfinite(value):
        raise _Refused(column, text, "must be a finite number")
    return value


def _flag(row: dict[str, str], column: str) -> bool:
    text = row.get(column, "").strip()
    if text in ("", "0"):
        return False
    if text == "1":
        return True
    raise _Refused(column, text, "must be 0 or 1")


def _kepware_type(text: str, column: str, area_is_bit: bool) -> DataType:
    key = text.strip().lower()
    if key in ("", "default"):
        return DataType.BOOLEAN if area_is_bit else DataType.UINT16
    if key in _KEPWARE_LOWER:
        return _KEPWARE_LOWER[key]
    if key.endswith("array") or "[" in key:
        why = "arrays are not converted (give each element its own tag)"
    elif key == "string":
        why = ("String is not converted (its length and byte order are in a Kepware "
               "address suffix; add it by hand with deviceDataType String and quantity)")
    elif key in ("char", "byte"):
        why = f"{text.strip()} (an 8-bit value) is not converted"
    else:
        why = "unknown Kepware data type"
    raise _Refused(column, text, f"{why} (allowed: {_KEPWARE_ALLOWED})")


def _scaling(row: dict[str, str]) -> dict[str, Any]:
    """The item keys of Kepware's scaling columns (docs/engineering-units.md): Linear
    extrapolates, so it is ``dataMultiplier`` and ``offset`` (scaled = raw x factor +
    offset); Linear with both clamps is a clamped range (rawMin..engMax, clamp).  Negate
    Value negates the scaled value."""
    kind = row.get("Scaling", "").strip().lower()
    clamps = [_flag(row, c) for c in ("Clamp Low", "Clamp High")]
    if kind in ("", "none"):
        for column, on in zip(("Clamp Low", "Clamp High"), clamps, strict=True):
            if on:
                raise _Refused(column, row[column], "clamping needs Linear scaling (use 0)")
        return {"dataMultiplier": -1.0} if _flag(row, "Negate Value") else {}
    if kind != "linear":
        raise _Refused("Scaling", row.get("Scaling", ""),
                       "only None and Linear scaling are converted")
    raw_lo, raw_hi, sc_lo, sc_hi = (_number(row.get(c, "").strip(), c) for c in
                                    ("Raw Low", "Raw High", "Scaled Low", "Scaled High"))
    if raw_hi == raw_lo:
        raise _Refused("Raw High", row.get("Raw High", ""), "must differ from Raw Low")
    if sc_hi == sc_lo:
        raise _Refused("Scaled High", row.get("Scaled High", ""),
                       "must differ from Scaled Low")
    sign = -1.0 if _flag(row, "Negate Value") else 1.0
    if clamps[0] != clamps[1]:
        column = "Clamp Low" if clamps[0] else "Clamp High"
        raise _Refused(column, row[column], "clamping one end only is not converted (set "
                                            "Clamp Low and Clamp High both, or neither)")
    if clamps[0]:
        return {"rawMin": raw_lo, "rawMax": raw_hi, "engMin": sign * sc_lo,
                "engMax": sign * sc_hi, "clamp": True}
    factor = (sc_hi - sc_lo) / (raw_hi - raw_lo)
    offset = sc_lo - raw_lo * factor
    keys: dict[str, Any] = {"dataMultiplier": sign * factor}
    if abs(offset) > 1e-12 * max(1.0, abs(sc_lo), abs(sc_hi)):
        keys["offset"] = sign * offset
    return keys


def _kepware_item(row: dict[str, str]) -> dict[str, Any]:
    name = row.get("Tag Name", "").strip()
    if not name:
        raise _Refused("Tag Name", row.get("Tag Name", ""), "a tag needs a name")
    address_text = row.get("Address", "").strip()
    try:
        addr = parse_address(address_text, "entity")
    except ValueError as exc:
        raise _Refused("Address", address_text,
                       f"{str(exc).removeprefix(repr(address_text) + ': ')} (Kepware Modbus "
                       "addresses: 0xxxxx coils, 1xxxxx discrete inputs, 3xxxxx input "
                       "registers, 4xxxxx holding registers, 5 or 6 digits, .bit on "
                       "registers)") from None
    if ":" in address_text:
        raise _Refused("Address", address_text, "not a Kepware Modbus address (e.g. 400001)")
    dtype = _kepware_type(row.get("Data Type", ""), "Data Type",
                          addr.area.is_bit or addr.bit is not None)
    item: dict[str, Any] = {"name": name, "address": format_address(addr),
                            "deviceDataType": dtype.value}
    scaling = _scaling(row)
    item.update(scaling)
    if scaling and row.get("Scaled Data Type", "").strip():
        item["convertedDataType"] = _kepware_type(row["Scaled Data Type"], "Scaled Data Type",
                                                  False).value
    _rate(item, row, "Scan Rate")
    for column, key in (("Eng Units", "unit"), ("Description", "description")):
        if row.get(column, "").strip():
            item[key] = row[column].strip()
    return item


def _rate(item: dict[str, Any], row: dict[str, str], column: str) -> None:
    text = row.get(column, "").strip()
    if text:
        rate = _number(text, column)
        if not rate.is_integer() or rate < 1:
            raise _Refused(column, text, "must be a whole number of milliseconds, 1 or more")
        item["readCycle"] = int(rate)


def _generic_item(row: dict[str, str], prefix: str) -> dict[str, Any]:
    name = row.get("name", "").strip()
    if not name:
        raise _Refused("name", row.get("name", ""), "a tag needs a name")
    address_text = row.get("address", "").strip()
    try:
        addr = parse_address(address_text, prefix)
    except ValueError as exc:
        raise _Refused("address", address_text,
                       f"{str(exc).removeprefix(repr(address_text) + ': ')} "
                       f"(addressPrefix {prefix})") from None
    try:
        dtype = DataType.parse(row.get("type", ""))
    except ValueError as exc:
        raise _Refused("type", row.get("type", ""), str(exc)) from None
    item: dict[str, Any] = {"name": name, "address": format_address(addr),
                            "deviceDataType": dtype.value}
    scale = row.get("scale", "").strip()
    if scale:
        item["dataMultiplier"] = _number(scale, "scale")
    for key in ("offset", "rawMin", "rawMax", "engMin", "engMax"):
        text = row.get(key, "").strip()
        if text:
            item[key] = _number(text, key)
    clamp = row.get("clamp", "").strip().lower()
    if clamp:
        if clamp not in ("true", "false", "1", "0"):
            raise _Refused("clamp", row["clamp"], "must be true or false (1 or 0)")
        item["clamp"] = clamp in ("true", "1")
    if row.get("scaleFactor", "").strip():
        item["scaleFactor"] = row["scaleFactor"].strip()
    _rate(item, row, "scanRate")
    for key in ("unit", "description"):
        if row.get(key, "").strip():
            item[key] = row[key].strip()
    return item


# config loader paths -> the column of each form that gave the value
_COLUMN_OF = {
    "kepware": {"name": "Tag Name", "address": "Address", "deviceDataType": "Data Type",
                "quantity": "Data Type", "dataMultiplier": "Scaling",
                "convertedDataType": "Scaled Data Type", "readCycle": "Scan Rate",
                "offset": "Scaling", "rawMin": "Raw Low", "rawMax": "Raw High",
                "engMin": "Scaled Low", "engMax": "Scaled High", "clamp": "Clamp Low"},
    "generic": {"name": "name", "address": "address", "deviceDataType": "type",
                "quantity": "type", "dataMultiplier": "scale", "convertedDataType": "scale",
                "readCycle": "scanRate", **{k: k for k in ("offset", "rawMin", "rawMax",
                                                           "engMin", "engMax", "clamp",
                                                           "scaleFactor")}},
}


def _checked(item: dict[str, Any], form: str, row: dict[str, str]) -> None:
    """The config loader's own check of one item; its first problem is a refusal.  The
    item a scaleFactor names is stood in for by an Int16 (import_tags checks that the
    list holds it)."""
    items = [item]
    factor = item.get("scaleFactor")
    if isinstance(factor, str) and factor != item["name"]:
        items.append({"name": factor, "address": "hr:0", "deviceDataType": "Int16"})
    try:
        load_device_config({"addressList": items})
    except ConfigError as exc:
        problem = exc.problems[0]
        key = problem.path.rpartition(".")[2]
        column = _COLUMN_OF[form].get(key, _COLUMN_OF[form]["address"])
        raise _Refused(column, row.get(column, ""), problem.message) from None


def _form(header: Sequence[str]) -> str:
    names = {h.strip() for h in header}
    if {"Tag Name", "Address", "Data Type"} <= names:
        return "kepware"
    if {"name", "address", "type"} <= {n for n in names}:
        return "generic"
    raise ValueError(
        f"header {', '.join(header)!r}: not a tag list this importer knows (Kepware's "
        f"export: {', '.join(KEPWARE_COLUMNS)}; or generic: {', '.join(GENERIC_COLUMNS)}, "
        "the first three required)")


def _note_entity_lookalike(result: ImportResult, row: int, text: str, prefix: str) -> None:
    """Count a generic row whose address reads as an offset but looks like an entity
    number; the first one is the notice (docs/command-line.md, "Importing a tag list")."""
    entity = entity_lookalike(text, prefix)
    if entity is None:
        return
    result.entity_lookalikes += 1
    if result.notice is None:
        read_as = parse_address(text.strip(), prefix)
        result.notice = f"row {row}: {entity_notice(text.strip(), read_as, entity)}"


def _rows(reader: Any) -> Iterator[list[str]]:
    """The reader's rows; a row the csv module cannot read (a field over its limit of
    csv.field_size_limit(), a NUL byte) is a ValueError naming the line, not a
    traceback."""
    while True:
        try:
            cells: list[str] = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise ValueError(f"line {reader.line_num}: not CSV the tag list can hold "
                             f"({exc})") from None
        yield cells


def import_tags(text: str, address_prefix: str = "function-code") -> ImportResult:
    """Convert a CSV tag list (its text); see the module doc.  ``address_prefix`` reads
    the generic form's addresses.  Raises ValueError for a header of neither form."""
    reader = csv.reader(io.StringIO(text.lstrip("\ufeff")))
    header: list[str] | None = None
    result: ImportResult | None = None
    seen: dict[str, int] = {}
    for cells in _rows(reader):
        number = reader.line_num
        if not any(c.strip() for c in cells):
            continue
        if header is None:
            header = [c.strip() for c in cells]
            result = ImportResult(_form(header))
            continue
        assert result is not None
        row = {h: (cells[i] if i < len(cells) else "") for i, h in enumerate(header)}
        if result.form == "generic":
            _note_entity_lookalike(result, number, row.get("address", ""), address_prefix)
        name_column = "Tag Name" if result.form == "kepware" else "name"
        try:
            if result.form == "kepware":
                item = _kepware_item(row)
            else:
                item = _generic_item(row, address_prefix)
            if item["name"] in seen:
                raise _Refused(name_column, item["name"],
                               f"duplicate tag name (also row {seen[item['name']]})")
            _checked(item, result.form, row)
        except _Refused as refused:
            result.refused.append(Refusal(number, refused.column, refused.value,
                                          refused.reason))
            continue
        seen[item["name"]] = number
        result.items.append(item)
    if result is None:
        raise ValueError("the file holds no header row (and no tags)")
    _check_factors(result, seen)
    return result


def _check_factors(result: ImportResult, seen: dict[str, int]) -> None:
    """Refuse the rows whose scaleFactor names no converted tag."""
    column = "scaleFactor"
    kept: list[dict[str, Any]] = []
    for item in result.items:
        factor = item.get(column)
        if factor is not None and factor not in seen:
            result.refused.append(Refusal(seen[item["name"]], column, factor,
                                          "no tag of that name in the list (a scale factor "
                                          "is an Int16 tag of the same device)"))
            continue
        kept.append(item)
    result.items = kept
    result.refused.sort(key=lambda r: r.row)
