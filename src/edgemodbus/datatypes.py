"""Data types, data formats, Modbus areas and item/driver statuses: the vocabulary shared
by every layer."""

from __future__ import annotations

import enum
from typing import Any


class Area(enum.Enum):
    """A Modbus data area, by the function code that reads it (MODBUS Application
    Protocol v1.1b3, 4.3 and 6.1-6.4)."""

    COIL = 1
    DISCRETE_INPUT = 2
    HOLDING_REGISTER = 3
    INPUT_REGISTER = 4

    @property
    def read_function(self) -> int:
        return self.value

    @property
    def is_bit(self) -> bool:
        return self in (Area.COIL, Area.DISCRETE_INPUT)

    @property
    def writable(self) -> bool:
        return self in (Area.COIL, Area.HOLDING_REGISTER)

    @property
    def short_name(self) -> str:
        return _AREA_SHORT[self]


_AREA_SHORT = {
    Area.COIL: "coil",
    Area.DISCRETE_INPUT: "di",
    Area.HOLDING_REGISTER: "hr",
    Area.INPUT_REGISTER: "ir",
}


class DataType(enum.Enum):
    """Device data types of the seed (plus NG's Timestamp/Binary, BCD, and the 24-bit
    integers the Pascal.Edge seed lists as an extension: 2 registers, one byte unused)."""

    BOOLEAN = "Boolean"
    BYTE = "Byte"
    SBYTE = "Sbyte"
    CHAR = "Char"
    INT16 = "Int16"
    UINT16 = "UInt16"
    INT24 = "Int24"
    UINT24 = "UInt24"
    INT32 = "Int32"
    UINT32 = "UInt32"
    INT64 = "Int64"
    UINT64 = "UInt64"
    FLOAT = "Float"
    DOUBLE = "Double"
    STRING = "String"
    DATETIME = "DateTime"
    TIMESTAMP = "Timestamp"
    BINARY = "Binary"
    BCD16 = "BCD16"
    BCD32 = "BCD32"

    @classmethod
    def parse(cls, name: str) -> DataType:
        """Case-insensitive; accepts the seed's and NG's spellings (Float32, Float64...)."""
        found = _TYPE_ALIASES.get(name.strip().lower())
        if found is None:
            allowed = ", ".join(t.value for t in cls)
            raise ValueError(f"unknown data type {name!r} (use one of {allowed})")
        return found

    @property
    def registers(self) -> int:
        """Registers the type occupies by default (String/Binary: none, use quantity)."""
        return _REGISTERS[self]

    @property
    def is_integer(self) -> bool:
        return self in _INTEGER_RANGES

    @property
    def is_numeric(self) -> bool:
        return self.is_integer or self in (DataType.FLOAT, DataType.DOUBLE)

    @property
    def integer_range(self) -> tuple[int, int]:
        """Inclusive (min, max) of an integer type's values."""
        return _INTEGER_RANGES[self]

    @property
    def needs_quantity(self) -> bool:
        return self in (DataType.STRING, DataType.BINARY)


_TYPE_ALIASES: dict[str, DataType] = {t.value.lower(): t for t in DataType}
_TYPE_ALIASES.update(
    {
        "bool": DataType.BOOLEAN,
        "float32": DataType.FLOAT,
        "single": DataType.FLOAT,
        "float64": DataType.DOUBLE,
        "int8": DataType.SBYTE,
        "uint8": DataType.BYTE,
        "short": DataType.INT16,
        "ushort": DataType.UINT16,
        "int": DataType.INT32,
        "uint": DataType.UINT32,
        "long": DataType.INT64,
        "ulong": DataType.UINT64,
    }
)

_REGISTERS = {
    DataType.BOOLEAN: 1,
    DataType.BYTE: 1,
    DataType.SBYTE: 1,
    DataType.CHAR: 1,
    DataType.INT16: 1,
    DataType.UINT16: 1,
    DataType.BCD16: 1,
    DataType.INT32: 2,
    DataType.UINT32: 2,
    DataType.FLOAT: 2,
    DataType.BCD32: 2,
    DataType.INT24: 2,
    DataType.UINT24: 2,
    DataType.DATETIME: 2,
    DataType.TIMESTAMP: 2,
    DataType.INT64: 4,
    DataType.UINT64: 4,
    DataType.DOUBLE: 4,
    DataType.STRING: 0,
    DataType.BINARY: 0,
}

_INTEGER_RANGES = {
    DataType.BYTE: (0, 0xFF),
    DataType.SBYTE: (-0x80, 0x7F),
    DataType.INT16: (-0x8000, 0x7FFF),
    DataType.UINT16: (0, 0xFFFF),
    DataType.INT24: (-0x80_0000, 0x7F_FFFF),
    DataType.UINT24: (0, 0xFF_FFFF),
    DataType.INT32: (-0x8000_0000, 0x7FFF_FFFF),
    DataType.UINT32: (0, 0xFFFF_FFFF),
    DataType.INT64: (-0x8000_0000_0000_0000, 0x7FFF_FFFF_FFFF_FFFF),
    DataType.UINT64: (0, 0xFFFF_FFFF_FFFF_FFFF),
    DataType.BCD16: (0, 9999),
    DataType.BCD32: (0, 99_999_999),
}


class DataFormat(enum.Enum):
    """Byte order of values of two or more registers: (byte swap inside each register) x
    (word order).

    ABCD is big-endian throughout (the Modbus default, Application Protocol 4.2);
    BADC swaps the bytes of each register; CDAB swaps the register order; DCBA both.
    64-bit values take the same two flags (ABCD -> ABCDEFGH, DCBA -> HGFEDCBA) unless a
    :class:`DataFormat64` is given.  A one-register value is not reordered by it: it is
    byte-swapped only by the explicit 16-bit switch (``byteSwap16``, docs/device-files.md "Byte
    order").
    """

    ABCD = "ABCD"
    BADC = "BADC"
    CDAB = "CDAB"
    DCBA = "DCBA"

    @classmethod
    def parse(cls, name: str) -> DataFormat:
        try:
            return cls(name.strip().upper())
        except ValueError:
            raise ValueError(
                f"unknown data format {name!r} (use ABCD, BADC, CDAB or DCBA)"
            ) from None

    @classmethod
    def from_orders(cls, byte_order: str, word_order: str) -> DataFormat:
        """NG-style byteOrder/wordOrder ('BigEndian'/'LittleEndian') as one format."""
        byte_swap = _endian_is_little("byteOrder", byte_order)
        word_swap = _endian_is_little("wordOrder", word_order)
        return cls.from_flags(byte_swap, word_swap)

    @classmethod
    def from_flags(cls, byte_swap: bool, word_swap: bool) -> DataFormat:
        return _FORMAT_BY_FLAGS[(byte_swap, word_swap)]

    @property
    def byte_swap(self) -> bool:
        return self in (DataFormat.BADC, DataFormat.DCBA)

    @property
    def word_swap(self) -> bool:
        return self in (DataFormat.CDAB, DataFormat.DCBA)


class DataFormat64(enum.Enum):
    """Byte order of 64-bit values (4 registers), apart from :class:`DataFormat`: the
    value's bytes A (most significant) .. H as they sit in the registers, in address
    order.  Two word orders (the order of the two 32-bit halves, and of the two registers
    inside each half) and the byte swap inside each register: ABCDEFGH is big-endian,
    EFGHABCD is Kepware's "first DWord low" (low half first, its registers high first),
    GHEFCDAB reverses all four registers (what CDAB means for 64-bit values)."""

    ABCDEFGH = "ABCDEFGH"
    BADCFEHG = "BADCFEHG"
    CDABGHEF = "CDABGHEF"
    DCBAHGFE = "DCBAHGFE"
    EFGHABCD = "EFGHABCD"
    FEHGBADC = "FEHGBADC"
    GHEFCDAB = "GHEFCDAB"
    HGFEDCBA = "HGFEDCBA"

    @classmethod
    def parse(cls, name: str) -> DataFormat64:
        try:
            return cls(name.strip().upper())
        except ValueError:
            allowed = ", ".join(f.value for f in cls)
            raise ValueError(f"unknown 64-bit data format {name!r} (use {allowed})") from None

    @classmethod
    def from_format(cls, fmt: DataFormat) -> DataFormat64:
        """What ``fmt`` means for a 64-bit value (ABCD -> ABCDEFGH, CDAB -> GHEFCDAB)."""
        return _FORMAT64_OF[fmt]

    @property
    def byte_swap(self) -> bool:
        """The two bytes of each register are swapped (B before A)."""
        return self.value[0] in "BDFH"

    @property
    def word_swap(self) -> bool:
        """The registers of the value are reversed (before the halves are swapped back
        by :attr:`dword_swap`): the codec's two flags, emb_codec.h."""
        return self.value[0] in "CDGH"

    @property
    def dword_swap(self) -> bool:
        """The two 32-bit halves are swapped after :attr:`word_swap`."""
        return self.value[0] in "CDEF"


_FORMAT64_OF = {
    DataFormat.ABCD: DataFormat64.ABCDEFGH,
    DataFormat.BADC: DataFormat64.BADCFEHG,
    DataFormat.CDAB: DataFormat64.GHEFCDAB,
    DataFormat.DCBA: DataFormat64.HGFEDCBA,
}

_FORMAT_BY_FLAGS = {
    (False, False): DataFormat.ABCD,
    (True, False): DataFormat.BADC,
    (False, True): DataFormat.CDAB,
    (True, True): DataFormat.DCBA,
}


def _endian_is_little(field: str, value: str) -> bool:
    key = value.strip().lower().replace("_", "").replace("-", "")
    if key in ("bigendian", "big", "be"):
        return False
    if key in ("littleendian", "little", "le"):
        return True
    raise ValueError(f"{field} {value!r}: use BigEndian or LittleEndian")


class ItemStatus(str, enum.Enum):
    """Quality of an item's value."""

    UNKNOWN = "Unknown"
    OK = "Ok"
    INVALID = "Invalid"


class DeviceDriverStatus(str, enum.Enum):
    """Lifecycle state of a driver (docs/library.md, "The driver")."""

    STOPPED = "Stopped"
    DISABLED = "Disabled"
    CONNECTING = "Connecting"
    RUNNING = "Running"
    OFFLINE = "Offline"
    RECONNECTING = "Reconnecting"


def enum_value(value: object) -> Any:
    """The ``value`` of an enum member (``ItemStatus.OK`` -> ``"Ok"``), anything else
    unchanged: for fields and arguments that hold either a member or its raw value."""
    return getattr(value, "value", value)
