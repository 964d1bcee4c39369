"""Spellings accepted besides ours, in one place: keys as the seed's files and NG write
them, parity as numbers and names, timestamps as .NET writes them.

* Keys: matching ignores case, ``_`` and ``-`` (:func:`norm_key`), so camelCase (the
  device file, and the canonical spelling), PascalCase (``modbusRtu.json``) and
  snake_case name the same field.
* NG's communication keys (:data:`NG_KEYS`, :func:`ng_aliases`): ``maxGap`` for
  ``maxMergeAddressGap``, ``maxBatch`` for ``maxBlockReadRegisterCount``,
  ``byteOrder``/``wordOrder`` for ``dataFormat``.
* Parity (:func:`parity_letter`): ``None/Odd/Even``, ``0/1/2`` (the seed descriptor's
  numbering) and libmodbus's ``N/O/E``, in any case.
* Timestamps (:func:`iso_timestamp`): fractions of more than 6 digits are cut.
"""

from __future__ import annotations

from typing import Any

from ..datatypes import DataFormat
from .problems import NO_VALUE, ConfigError, Problem


def norm_key(key: str) -> str:
    """A key as matched against the fields' keys: case, ``_`` and ``-`` ignored."""
    return key.replace("_", "").replace("-", "").lower()


NG_KEYS: tuple[str, ...] = ("maxGap", "maxBatch", "byteOrder", "wordOrder")
"""NG's communication keys, accepted besides the fields (see :func:`ng_aliases`)."""


def ng_aliases(data: dict[str, Any]) -> dict[str, Any]:
    """NG spellings -> ours in ``data`` (keys already normalised, changed in place);
    disagreements are errors."""
    problems: list[Problem] = []
    for ng, ours in (
        ("maxGap", "maxMergeAddressGap"),
        ("maxBatch", "maxBlockReadRegisterCount"),
    ):
        if ng in data:
            value = data.pop(ng)
            if ours in data and data[ours] != value:
                problems.append(Problem(ng, value, f"disagrees with {ours} {data[ours]!r}"))
            else:
                data[ours] = value
    if "byteOrder" in data or "wordOrder" in data:
        byte_order = data.pop("byteOrder", "BigEndian")
        word_order = data.pop("wordOrder", "BigEndian")
        try:
            fmt = DataFormat.from_orders(str(byte_order), str(word_order))
        except ValueError as exc:
            problems.append(Problem("byteOrder/wordOrder", NO_VALUE, str(exc)))
        else:
            given = data.get("dataFormat")
            if given is not None and _parse_format_or_none(given) is not fmt:
                problems.append(
                    Problem(
                        "dataFormat", given, f"disagrees with byteOrder/wordOrder ({fmt.value})"
                    )
                )
            data["dataFormat"] = fmt
    if problems:
        raise ConfigError(problems)
    return data


def _parse_format_or_none(value: Any) -> DataFormat | None:
    try:
        return DataFormat.parse(value) if isinstance(value, str) else value
    except ValueError:
        return None


PARITY_NUMBERS = {0: "N", 1: "O", 2: "E"}
"""The seed descriptor's parity numbers -> libmodbus's letters."""

PARITY_NAMES = {
    "none": "N",
    "n": "N",
    "0": "N",
    "odd": "O",
    "o": "O",
    "1": "O",
    "even": "E",
    "e": "E",
    "2": "E",
}
"""Parity as text (lower case) -> libmodbus's letters."""


def parity_letter(value: Any) -> str | None:
    """libmodbus's parity letter (``N``, ``O``, ``E``) of any accepted spelling, else None."""
    if isinstance(value, int) and not isinstance(value, bool):
        return PARITY_NUMBERS.get(value)
    if isinstance(value, str):
        return PARITY_NAMES.get(value.strip().lower())
    return None


def iso_timestamp(value: Any) -> Any:
    """Cut ISO 8601 fractions to 6 digits (.NET writes 7: ...58.9644719Z)."""
    if isinstance(value, str) and "." in value:
        head, _, tail = value.partition(".")
        digits = len(tail) - len(tail.lstrip("0123456789"))
        if digits > 6:
            value = f"{head}.{tail[:6]}{tail[digits:]}"
    return value
