"""Spellings accepted besides ours, in one place: keys as the seed's files and NG write
them, parity as numbers and names, timestamps as .NET writes them.

* Keys: matching ignores case, ``_`` and ``-`` (:func:`norm_key`), so camelCase (the
  device file, and the canonical spelling), PascalCase (``modbusRtu.json``) and
  snake_case name the same field.
* NG's communication keys (:data:`NG_KEYS`, :func:`ng_aliases`): ``maxGap`` for
  ``maxMergeAddressGap``, ``maxBatch`` for ``maxBlockReadRegisterCount``,
  ``byteOrder``/``wordOrder`` (names, or NG's numbers 0 = BigEndian, 1 = LittleEndian)
  for ``dataFormat`` (and ``byteSwap16``: NG's byteOrder swaps one-register values too),
  and the nested ``connection{kind, host, port, baudRate, dataBits,
  stopBits, parity}`` for ``transport``/``tcpHost``/``tcpPort``/``comPort``/....
* NG's point keys (:data:`NG_POINT_KEYS`, :func:`ng_point`): ``functionCode`` (1..4 or
  NG's names) with a numeric ``address`` for our ``"hr:100"``, ``dataType`` for
  ``deviceDataType``, ``scale`` for ``dataMultiplier``, ``key`` for a missing ``name``.
* Parity (:func:`parity_letter`): ``None/Odd/Even``, ``0/1/2`` (the seed descriptor's
  numbering) and libmodbus's ``N/O/E``, in any case.
* Timestamps (:func:`iso_timestamp`): fractions of more than 6 digits are cut.
"""

from __future__ import annotations

import enum
from typing import Any

from ..datatypes import DataFormat
from .problems import NO_VALUE, ConfigError, Problem, WrongType


def norm_key(key: str) -> str:
    """A key as matched against the fields' keys: case, ``_`` and ``-`` ignored."""
    return key.replace("_", "").replace("-", "").lower()


NG_KEYS: tuple[str, ...] = ("maxGap", "maxBatch", "byteOrder", "wordOrder", "connection")
"""NG's communication keys, accepted besides the fields (see :func:`ng_aliases`)."""

_ENDIAN_NUMBERS = {0: "BigEndian", 1: "LittleEndian"}  # NG's Endianness (serde_repr)

# NG connection.kind -> our transport, and connection keys -> ours, per kind
_NG_KINDS = {"tcp": "tcp", "rtu": "rtu"}
_NG_CONNECTION = {
    "tcp": {"host": "tcpHost", "port": "tcpPort"},
    "rtu": {"port": "comPort", "baudrate": "baudRate", "databits": "dataBits",
            "stopbits": "stopBits", "parity": "parity"},
}


def _put(data: dict[str, Any], key: str, value: Any, where: str,
         problems: list[Problem]) -> None:
    """``data[key] = value`` unless ``data`` already says otherwise (a problem)."""
    if key in data and data[key] != value:
        problems.append(Problem(where, value, f"disagrees with {key} {data[key]!r}"))
    else:
        data[key] = value


def _connection(conn: Any, data: dict[str, Any], problems: list[Problem]) -> None:
    """NG's nested ``connection{kind, ...}`` -> our communication keys in ``data``."""
    if not isinstance(conn, dict):
        problems.append(Problem("connection", conn, "must be an object with a kind"))
        return
    fields = {norm_key(k): v for k, v in conn.items() if isinstance(k, str)}
    kind = str(fields.pop("kind", "")).strip().lower()
    if kind not in _NG_KINDS:
        problems.append(Problem("connection.kind", conn.get("kind", NO_VALUE),
                                "use tcp (Modbus TCP) or rtu (serial RTU)"))
        return
    _put(data, "transport", _NG_KINDS[kind], "connection.kind", problems)
    _put(data, "useTcp", kind == "tcp", "connection.kind", problems)
    names = _NG_CONNECTION[kind]
    for key, value in fields.items():
        ours = names.get(key)
        if ours is None:
            problems.append(Problem(f"connection.{key}", value,
                                    f"not a {kind} connection key (use kind, "
                                    f"{', '.join(names)})"))
        else:
            _put(data, ours, value, f"connection.{key}", problems)


NG_MAX_BATCH = 100
"""NG's default ``maxBatch`` (seed 2.1.5: registers or coils of one read)."""


def ng_batch_defaults(data: dict[str, Any]) -> None:
    """NG's read sizes in communication ``data`` (canonical keys, changed in place):
    ``maxBatch`` bounds a read of coils and discrete inputs as well as one of registers
    (seed 2.1.5: "寄存器数/线圈数"), and defaults to 100 (ours: 120 registers, 2000
    bits); keys given explicitly stay."""
    batch = data.setdefault("maxBlockReadRegisterCount", NG_MAX_BATCH)
    data.setdefault("maxBlockReadBitCount", batch)


def ng_aliases(data: dict[str, Any]) -> dict[str, Any]:
    """NG spellings -> ours in ``data`` (keys already normalised, changed in place);
    disagreements are errors.  With any NG key, NG's read sizes apply
    (:func:`ng_batch_defaults`)."""
    problems: list[Problem] = []
    ng_keyed = any(key in data for key in NG_KEYS)
    if "connection" in data:
        _connection(data.pop("connection"), data, problems)
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
        byte_order = _ENDIAN_NUMBERS.get(byte_order, byte_order)
        word_order = _ENDIAN_NUMBERS.get(word_order, word_order)
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
            # NG defines byteOrder per register: it swaps one-register values too, which
            # dataFormat no longer does (DESIGN, "Data types and formats")
            swap16 = data.get("byteSwap16")
            if isinstance(swap16, str):  # as pydantic reads a bool from text
                swap16 = swap16.strip().lower() in ("1", "true", "t", "yes", "y", "on")
            if swap16 is not None and swap16 != fmt.byte_swap:
                problems.append(Problem("byteSwap16", swap16,
                                        f"disagrees with byteOrder {str(byte_order)!r}"))
            else:
                data["byteSwap16"] = fmt.byte_swap
    if problems:
        raise ConfigError(problems)
    if ng_keyed:
        ng_batch_defaults(data)
    return data


NG_POINT_KEYS: tuple[str, ...] = ("functionCode", "dataType", "scale", "key")
"""NG's point keys, accepted on an item besides the fields (see :func:`ng_point`)."""

NG_FUNCTION_CODES: dict[str, int] = {
    "readcoils": 1,
    "readdiscreteinputs": 2,
    "readholdingregisters": 3,
    "readinputregisters": 4,
    "writesinglecoil": 5,
    "writesingleregister": 6,
    "writemultiplecoils": 15,
    "writemultipleregisters": 16,
}
"""NG's function code names (ModbusFunctionCode) -> their numbers."""

_READ_AREA = {1: "coil", 2: "di", 3: "hr", 4: "ir"}


def function_code(value: Any) -> int | None:
    """A function code as NG writes it: a number (5, "0x10", "16") or a name
    (``WriteMultipleRegisters``, case and ``_`` ignored); None if it is neither."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        text = value.strip().lower()
        try:
            return int(text, 16) if text.startswith("0x") else int(text)
        except ValueError:
            return NG_FUNCTION_CODES.get(norm_key(text))
    return None


def ng_point(data: dict[str, Any]) -> dict[str, Any]:
    """NG's point keys -> ours in ``data`` (keys already normalised, changed in place):
    ``functionCode`` 1..4 with a numeric (0-based, protocol) ``address`` -> ``"hr:100"``
    etc., ``dataType`` -> ``deviceDataType``, ``scale`` -> ``dataMultiplier`` (null: 1),
    ``key`` -> ``name`` when there is none.  Raises ValueError naming the key."""
    if "key" in data:
        key = data.pop("key")
        data.setdefault("name", key)
    for ng, ours in (("dataType", "deviceDataType"), ("scale", "dataMultiplier")):
        if ng in data:
            value = data.pop(ng)
            if value is None and ng == "scale":
                continue
            if ours in data and data[ours] != value:
                raise ValueError(f"{ng} {value!r} disagrees with {ours} {data[ours]!r}")
            data[ours] = value
    if "functionCode" in data:
        given = data.pop("functionCode")
        code = function_code(given)
        if code not in _READ_AREA:
            raise ValueError(
                f"functionCode {given!r}: a point is read with 1 (ReadCoils), "
                "2 (ReadDiscreteInputs), 3 (ReadHoldingRegisters) or 4 (ReadInputRegisters)"
            )
        area = _READ_AREA[code]
        address = data.get("address")
        if isinstance(address, bool) or address is None:
            raise ValueError(f"functionCode {given!r} needs an address (0..65535)")
        if isinstance(address, str) and ":" not in address:
            address = address.strip()
        if isinstance(address, int) or (isinstance(address, str) and address.isdigit()):
            data["address"] = f"{area}:{address}"
        else:
            raise ValueError(
                f"address {address!r}: with functionCode give the offset alone "
                f"(a whole number 0..65535, read as {area}:<offset>)"
            )
    return data


NG_DEVICE_KEYS: tuple[str, ...] = ("points",)
"""NG's device-file keys, accepted besides the fields (see :func:`ng_device`)."""


def ng_device(data: dict[str, Any]) -> dict[str, Any]:
    """NG's ``points`` -> ``addressList`` in ``data`` (keys already normalised, changed
    in place); both at once is an error."""
    if "points" in data:
        if "addressList" in data:
            raise ConfigError([Problem("points", NO_VALUE,
                                       "give the items in points or in addressList, not both")])
        data["addressList"] = data.pop("points")
    return data


NG_ACTION_KEYS: tuple[str, ...] = ("inputParameters",)
"""NG's action keys, accepted besides the fields (see :func:`ng_action`)."""

NG_PARAMETER_KEYS: tuple[str, ...] = ("key", "type", "default", "address")
"""NG's (and the short) parameter keys, accepted besides the fields."""


def ng_action(data: dict[str, Any]) -> dict[str, Any]:
    """NG's ``inputParameters`` -> ``parameters`` (keys already normalised)."""
    if "inputParameters" in data:
        if "parameters" in data:
            raise ValueError("give parameters or inputParameters, not both")
        data["parameters"] = data.pop("inputParameters")
    return data


def ng_action_parameter(data: dict[str, Any]) -> dict[str, Any]:
    """A parameter's ``key`` -> ``name`` (NG: ``key`` is the id, ``name`` a label, kept
    as description), ``type`` -> ``dataType``, ``default`` -> ``defaultValue``.  NG's
    per-parameter ``address`` is refused: a parameter sets an item of the address list."""
    if "key" in data:
        key = data.pop("key")
        label = data.get("name")
        if label is not None and label != key:
            data.setdefault("description", label)
        data["name"] = key
    for short, ours in (("type", "dataType"), ("default", "defaultValue")):
        if short in data:
            value = data.pop(short)
            if ours in data and data[ours] != value:
                raise ValueError(f"{short} {value!r} disagrees with {ours} {data[ours]!r}")
            data[ours] = value
    if "address" in data:
        raise ValueError(
            f"address {data['address']!r}: a parameter sets an item: name it with "
            '"item" (add the address to the address list as an item)'
        )
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


class Parity(str, enum.Enum):
    """Serial parity, as libmodbus spells it."""

    NONE = "N"
    ODD = "O"
    EVEN = "E"

    @classmethod
    def parse(cls, value: Any) -> Parity:
        if isinstance(value, Parity):
            return value
        letter = parity_letter(value)
        if letter is None:
            raise WrongType("use None|Odd|Even, 0|1|2 or N|O|E")
        return cls(letter)

    @property
    def number(self) -> int:
        """The seed descriptor's numbering: 0 = None, 1 = Odd, 2 = Even."""
        return {Parity.NONE: 0, Parity.ODD: 1, Parity.EVEN: 2}[self]
