"""Address grammar ``[type:]offset[.bit]`` -> (area, offset, bit).

The numeric type prefix is the Modbus read function code by default (3 = holding,
4 = input, as the seed's parsing rules say); ``prefix="modicon"`` selects the Modicon
numbering of the seed's descriptor note (3 = input, 4 = holding).  Offsets are decimal
(leading zeros allowed) and 0-based protocol addresses unless ``base=1``.

``prefix="entity"`` also takes Modicon entity numbers as people type them (docs/device-files.md,
"Entity addresses"): the first digit is the table (0 coil, 1 discrete input, 3 input
register, 4 holding register) and the rest the 1-based entity, in the 5-digit form
(``40001`` = holding register 0, up to ``49999``; fewer digits are coils: ``1`` =
``00001``) or the 6-digit form (``400001``..``465536``).  A text with a ``:`` is read as
under ``function-code`` (with ``base``); entity numbers are 1-based whatever ``base``.

:func:`address_regex` builds the regular expression that accepts exactly the texts
:func:`parse_address` accepts, so the driver descriptor cannot drift from the parser.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..datatypes import Area
from .limits import MAX_ADDRESS

AddressPrefix = Literal["function-code", "modicon", "entity"]

PREFIXES: tuple[AddressPrefix, ...] = ("function-code", "modicon", "entity")
MAX_OFFSET = MAX_ADDRESS  # the highest protocol offset (protocol/limits.py)
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
_NUMERIC_TYPES["entity"] = _NUMERIC_TYPES["function-code"]  # its texts with a ':'

# Modicon entity numbers: table digit -> area (the 5- and 6-digit forms)
ENTITY_TABLES: dict[str, Area] = {
    "0": Area.COIL,
    "1": Area.DISCRETE_INPUT,
    "3": Area.INPUT_REGISTER,
    "4": Area.HOLDING_REGISTER,
}
ENTITY_DIGITS: dict[Area, str] = {area: digit for digit, area in ENTITY_TABLES.items()}
MAX_ENTITY_5 = 9999  # 5-digit form: 4 digits of entity
MAX_ENTITY_6 = MAX_OFFSET + 1  # 6-digit form: 00001..65536


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
    raise ValueError(f"address prefix {prefix!r}: use 'function-code', 'modicon' or 'entity'")


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
    if ":" not in body and prefix == "entity":
        return _parse_entity(text, body)
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
    return Address(area, number - base, _bit(text, area, dot, bit_text))


def _bit(text: str, area: Area, dot: str, bit_text: str) -> int | None:
    """The ``.bit`` of an address (None without a dot)."""
    if not dot:
        return None
    if area.is_bit:
        raise ValueError(f"{text!r}: a bit index is only allowed on hr/ir registers")
    if not _is_decimal(bit_text):
        raise ValueError(f"{text!r}: bit {bit_text!r} is not a decimal number")
    bit = int(bit_text)
    if bit > MAX_BIT:
        raise ValueError(f"{text!r}: bit {bit} out of range 0..{MAX_BIT}")
    return bit


def entity_range(area: Area, six_digits: bool) -> str:
    """The entity numbers of ``area`` in one form, as text (``400001..465536``)."""
    table = ENTITY_DIGITS[area]
    if six_digits:
        return f"{table}00001..{table}{MAX_ENTITY_6}"
    return f"{table}0001..{table}{MAX_ENTITY_5}"


def _parse_entity(text: str, body: str) -> Address:
    """A Modicon entity number (``40001``, ``400001``, ``1`` ...) -> its address."""
    number_text, dot, bit_text = body.partition(".")
    if not _is_decimal(number_text):
        raise ValueError(f"{text!r}: entity number {number_text!r} is not a decimal number "
                         "(use e.g. 40001, 400001, or hr:0)")
    if len(number_text) > 6:
        raise ValueError(f"{text!r}: an entity number has 5 digits (40001..49999) or 6 "
                         "(400001..465536), fewer for coils (1 = 00001)")
    six = len(number_text) == 6
    digits = number_text if six else number_text.zfill(5)
    area = ENTITY_TABLES.get(digits[0])
    if area is None:
        raise ValueError(f"{text!r}: table digit {digits[0]!r} is not a Modbus table "
                         "(use 0 coil, 1 discrete input, 3 input register, 4 holding register)")
    entity = int(digits[1:])
    if not 1 <= entity <= (MAX_ENTITY_6 if six else MAX_ENTITY_5):
        raise ValueError(f"{text!r}: entity number out of range: {_AREA_WORDS[area]} "
                         f"{entity_range(area, False)} (5 digits) or "
                         f"{entity_range(area, True)} (6 digits)")
    return Address(area, entity - 1, _bit(text, area, dot, bit_text))


_AREA_WORDS = {
    Area.COIL: "coils are",
    Area.DISCRETE_INPUT: "discrete inputs are",
    Area.INPUT_REGISTER: "input registers are",
    Area.HOLDING_REGISTER: "holding registers are",
}


def format_entity(addr: Address, six_digits: bool = True) -> str:
    """``addr`` as a Modicon entity number (6-digit form by default; the 5-digit form
    only reaches offset 9998)."""
    entity = addr.offset + 1
    if not six_digits and entity > MAX_ENTITY_5:
        raise ValueError(f"{addr}: offset {addr.offset} has no 5-digit entity number "
                         f"(the 5-digit form ends at {entity_range(addr.area, False)})")
    text = f"{ENTITY_DIGITS[addr.area]}{entity:0{5 if six_digits else 4}d}"
    return text if addr.bit is None else f"{text}.{addr.bit}"


def format_address(addr: Address, prefix: str = "function-code", base: int = 0) -> str:
    """``addr`` as text that :func:`parse_address` reads back with these options: a
    6-digit entity number under ``entity``, else ``type:offset[.bit]`` (named type)."""
    if check_prefix(prefix) == "entity":
        return format_entity(addr)
    text = f"{addr.area.short_name}:{addr.offset + check_base(base)}"
    return text if addr.bit is None else f"{text}.{addr.bit}"


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
    if prefix == "entity":  # the typed form needs its type; a bare number is an entity
        registers = f"(?:{'|'.join(register_tokens)}):{offset}(?:\\.{bit})?"
    else:
        registers = f"(?:(?:{'|'.join(register_tokens)}):)?{offset}(?:\\.{bit})?"
    bits = f"(?:{'|'.join(bit_tokens)}):{offset}"
    forms = [registers, bits]
    if prefix == "entity":
        forms += _entity_regexes(bit)
    return f"^{ws}(?:{'|'.join(forms)}){ws}$"


def _nonzero(width: int) -> str:
    """Exactly ``width`` decimal digits, not all zero."""
    return "(?:" + "|".join(f"0{{{z}}}[1-9][0-9]{{{width - z - 1}}}"
                            for z in range(width)) + ")"


def _entity_regexes(bit: str) -> list[str]:
    """The entity-number forms of :func:`_parse_entity`: coils of 1..4 digits, then the
    5- and 6-digit forms (a bit only on the register tables 3 and 4)."""
    six = ("(?:0000[1-9]|000[1-9][0-9]|00[1-9][0-9]{2}|0[1-9][0-9]{3}|[1-5][0-9]{4}"
           "|6[0-4][0-9]{3}|65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-6])")
    short = "|".join(_nonzero(w) for w in range(1, 5))
    return [f"(?:{short})", f"[01](?:{_nonzero(4)}|{six})",
            f"[34](?:{_nonzero(4)}|{six})(?:\\.{bit})?"]


AREA_NAMES: dict[Area, str] = {
    Area.COIL: "coil",
    Area.DISCRETE_INPUT: "discrete input",
    Area.INPUT_REGISTER: "input register",
    Area.HOLDING_REGISTER: "holding register",
}


def entity_lookalike(text: str, prefix: str) -> Address | None:
    """A bare 5-digit number that ``prefix`` (not ``entity``) reads as a holding register
    offset but that reads as a Modicon entity number of the discrete input or register
    tables (``10001``, ``30001``, ``40001``): the address it is under ``entity``.  None
    for anything else (a typed address, ``entity``, other numbers).  Valid under both
    readings (SunSpec's base 40000 is such an offset), so worth a notice, not an error;
    a zero-padded number (``00005``) is taken for an offset."""
    if prefix == "entity" or ":" in text:
        return None
    body = text.strip().partition(".")[0]
    if len(body) != 5 or not body.isdecimal() or body[0] not in "134":
        return None
    try:
        return parse_address(text.strip(), "entity")
    except ValueError:
        return None


def entity_notice(text: str, read_as: Address, entity: Address) -> str:
    """The notice for an address :func:`entity_lookalike` found (read as ``read_as``),
    without the way to switch (a device file and the command line say it differently)."""
    return (f"address {text!r} is read as {AREA_NAMES[read_as.area]} {read_as.offset} "
            f"({read_as}); as a Modicon entity number it would be "
            f"{AREA_NAMES[entity.area]} {entity.offset} ({entity})")
