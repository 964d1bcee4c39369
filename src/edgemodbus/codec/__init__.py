"""Python face of the C value codec: item specs, block decoding with change detection,
and encoding of writes; normalizing what a host hands to a write; values as JSON.

Choices this package makes (where the data type definitions leave them open):

* Smart Cast (NG; docs/device-files.md "Smart Cast"): a numeric item of ``quantity`` registers is
  read with the widest of 4, 2 (Int24/UInt24: their own 24-bit value), 1 registers that
  fits in it.  Fewer registers than the type needs hold a smaller value that is widened
  (Int64/UInt64/Double from 2 registers read Int32/UInt32/Float32, from 1
  Int16/UInt16/Int16; Int32/UInt32/Float from 1 read Int16/UInt16/Int16; BCD32 from 1
  reads BCD16); more hold a wider one that is narrowed to the type and range-checked
  (Int16 from 4 reads Int64; Float from 4 reads Float64).  The registers are taken in
  the item's format order, most significant first: the value is in the first ones, the
  rest (e.g. the 3rd of 3) are ignored on read and written as 0 by :func:`encode`; with a
  word swap (CDAB, DCBA) the first ones in that order are the last ones by address.
  DateTime/Timestamp need 2 (seconds) or 4 (ms).
* Int24/UInt24 are 2 registers rebuilt like an Int32 (bytes A B C D in format order)
  of which the low 3 bytes are the value; byte A is unused (ignored, written as 0).
* Byte/Sbyte and Char are the low byte of the register after the byte swap; Char is a
  1-character str of that byte's code point (latin-1: ``chr(byte)``).
* A bit of a register (``hr:100.3``) is taken after the byte swap, so it agrees with the
  UInt16 reading of the same register in the same format (bit 0 = least significant).
* ``convertedDataType`` Float keeps double precision but must fit a float32's range.
* A Float item's value (deviceDataType Float without a multiplier, or convertedDataType
  Float) is a :class:`Float32`: the exact float, written as text and JSON as the
  shortest decimal that reads back to its float32 (float32.py); a Float converted to
  String holds that text.  A multiplier makes a double (``raw / 10`` for 0.1).
* Deadband applies to numeric results (int, float); bool, str, bytes and datetime values
  report any change.
* An item that stays Invalid is reported again when its reason changes (the slave now
  holds another bad value); the reason always names the value just read.
"""

from __future__ import annotations

from .decoder import BlockDecoder, Change
from .encoder import encode, register_bit
from .float32 import Float32, float32_short, float32_text
from .jsonable import json_bytes, json_text, json_value, jsonable
from .normalize import normalize_value
from .scaling import SF_MAX, ScaleFactors
from .spec import MAX_QUANTITY, SMART_CAST_TYPES, ValueSpec, check_spec, smart_cast

__all__ = [
    "MAX_QUANTITY",
    "SF_MAX",
    "SMART_CAST_TYPES",
    "BlockDecoder",
    "Change",
    "Float32",
    "ScaleFactors",
    "ValueSpec",
    "check_spec",
    "encode",
    "float32_short",
    "float32_text",
    "json_bytes",
    "json_text",
    "json_value",
    "jsonable",
    "normalize_value",
    "register_bit",
    "smart_cast",
]
