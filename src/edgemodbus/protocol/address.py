"""Address grammar ``[type:]offset[.bit]`` -> (area, offset, bit).

The numeric type prefix is the Modbus read function code by default (3 = holding,
4 = input, as the seed's parsing rules say); ``prefix="modicon"`` selects the Modicon
numbering of the seed's descriptor note (3 = input, 4 = holding).  Offsets are decimal
(leading zeros allowed) and 0-based protocol addresses unless ``base=1``.

:func:`address_regex` builds the regular expression that accepts exactly the texts
:func:`parse_address` accepts, so the driver descriptor cannot drift from the parser.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..datatypes import Area

AddressPrefix = Literal["function-code", "modicon"]

PREFIXES: tuple[AddressPrefix, ...] = ("function-code", "modicon")
MAX_OFFSET = 0xFFFF
MAX_BIT = 15

# Whitespace stripped around the whole text (ASCII only, so the regex is portable).
_STRIP = " \t\r\n"

_NAMED_TYPES: dict[str, Area] = {
    "coil": Area.COIL,
    "c": Area.COIL,
    "di": Area.DISCRETE_INPUT,
    "discreteinput": Area.DISCRETE_INPUT,
    "hr": Area.HOLDING_REGISTER,
    "holding": Area.HOLDING_REGISTER,
    "ir": Area.INPUT_REGISTER,
    "input": Area.INPUT_REGISTER,
}

_NUMERIC_TYPES: dict[str, dict[str, Area]] = {
    "function-code": {
        "1": Area.COIL,
        "2": Area.DISCRETE_INPUT,
        "3": Area.HOLDING_REGISTER,
        "4": Area.INPUT_REGISTER,
    },
    "modicon": {
        "1": Area.COIL,
        "2": Area.DISCRETE_INPUT,
        "3": Area.INPUT_REGISTER,
        "4": Area.HOLDING_REGISTER,
    },
}


@dataclass(frozen=True, slots=True)
class Address:
    """A parsed address: area, 0-based protocol offset and optional bit of a register."""

    area: Area
    offset: int
    bit: int | None = None

    def __str__(self) -> str:
        text = f"{self.area.short_name}:{self.offset}"
        return text if self.bit is None else f"{text}.{self.bit}"


def check_prefix(prefix: str) -> AddressPrefix:
    """Validate an ``addressPrefix`` option value."""
    for known in PREFIXES:
        if prefix == known:
            return known
    raise ValueError(f"address prefix {prefix!r}: use 'function-code' or 'modicon'")


def check_base(base: int) -> int:
    """Validate an ``addressBase`` option value."""
    if base not in (0, 1) or isinstance(base, bool):
        raise ValueError(f"address base {base!r}: use 0 or 1")
    return base


def type_help(prefix: str = "function-code") -> str:
    """The accepted type tokens, grouped by area, for error messages."""
    return ", ".join(
        f"{name}|{type_number(area, prefix)}"
        for name, area in (
            ("coil|c", Area.COIL),
            ("di|discreteinput", Area.DISCRETE_INPUT),
            ("hr|holding", Area.HOLDING_REGISTER),
            ("ir|input", Area.INPUT_REGISTER),
        )
    )


def type_number(area: Area, prefix: str = "function-code") -> str:
    """The numeric type token of ``area`` under ``prefix`` ("3" is hr by function code)."""
    numbers = _NUMERIC_TYPES[check_prefix(prefix)]
    return next(num for num, a in numbers.items() if a is area)


def _is_decimal(text: str) -> bool:
    return text.isascii() and text.isdigit()


def parse_address(text: str, prefix: str = "function-code", base: int = 0) -> Address:
    """Parse ``[type:]offset[.bit]``; raise ValueError naming the text and the problem."""
    numeric = _NUMERIC_TYPES[check_prefix(prefix)]
    check_base(base)
    if not isinstance(text, str):
        raise ValueError(f"{text!r}: an address must be a string like 'hr:100'")
    body = text.strip(_STRIP)
    if not body:
        raise ValueError(f"{text!r}: empty address (use [type:]offset[.bit], e.g. 'hr:100')")
    if ":" in body:
        token, rest = body.split(":", 1)
        area = numeric.get(token) or (_NAMED_TYPES.get(token.lower()) if token.isascii() else None)
        if area is None:
            raise ValueError(f"{text!r}: unknown type {token!r} (use {type_help(prefix)})")
    else:
        area, rest = Area.HOLDING_REGISTER, body
    offset_text, dot, bit_text = rest.partition(".")
    if not _is_decimal(offset_text):
        raise ValueError(f"{text!r}: offset {offset_text!r} is not a decimal number")
    number = int(offset_text)
    low, high = base, MAX_OFFSET + base
    if not low <= number <= high:
        where = "" if base == 0 else f" (addressBase {base})"
        raise ValueError(f"{text!r}: offset {number} out of range {low}..{high}{where}")
    bit: int | None = None
    if dot:
        if area.is_bit:
            raise ValueError(f"{text!r}: a bit index is only allowed on hr/ir registers")
        if not _is_decimal(bit_text):
            raise ValueError(f"{text!r}: bit {bit_text!r} is not a decimal number")
        bit = int(bit_text)
        if bit > MAX_BIT:
            raise ValueError(f"{text!r}: bit {bit} out of range 0..{MAX_BIT}")
    return Address(area, number - base, bit)


def check_span(addr: Address, registers: int) -> None:
    """Raise ValueError when ``registers`` registers (or bits) from ``addr`` pass 65535."""
    if registers < 1:
        raise ValueError(f"{addr}: size {registers} must be at least 1")
    last = addr.offset + registers - 1
    if last > MAX_OFFSET:
        unit = "bits" if addr.area.is_bit else "registers"
        raise ValueError(f"{addr}: {registers} {unit} from here run past the last address 65535")


def _any_case(word: str) -> str:
    return "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c for c in word)


def _offset_regex(base: int) -> str:
    """Decimal 0..65535 (base 0) or 1..65536 (base 1), any number of leading zeros."""
    small, top = ("[0-9]{1,4}", "6553[0-5]") if base == 0 else ("[1-9][0-9]{0,3}", "6553[0-6]")
    return f"0*(?:{small}|[1-5][0-9]{{4}}|6[0-4][0-9]{{3}}|65[0-4][0-9]{{2}}|655[0-2][0-9]|{top})"


def address_regex(prefix: str = "function-code", base: int = 0) -> str:
    """A regex (Python and JavaScript syntax, no flags) that matches a text iff
    :func:`parse_address` accepts it with these options."""
    numeric = _NUMERIC_TYPES[check_prefix(prefix)]
    check_base(base)
    register_tokens = [n for n, a in numeric.items() if not a.is_bit]
    register_tokens += [_any_case(n) for n, a in _NAMED_TYPES.items() if not a.is_bit]
    bit_tokens = [n for n, a in numeric.items() if a.is_bit]
    bit_tokens += [_any_case(n) for n, a in _NAMED_TYPES.items() if a.is_bit]
    ws = "[ \\t\\r\\n]*"
    offset = _offset_regex(base)
    bit = "0*(?:1[0-5]|[0-9])"
    registers = f"(?:(?:{'|'.join(register_tokens)}):)?{offset}(?:\\.{bit})?"
    bits = f"(?:{'|'.join(bit_tokens)}):{offset}"
    return f"^{ws}(?:{registers}|{bits}){ws}$"
