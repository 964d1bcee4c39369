"""Python face of the C value codec: item specs, block decoding with change detection,
and encoding of writes; normalizing what a host hands to a write; values as JSON.

Choices this package makes (where the data type definitions leave them open):

* A ``quantity`` larger than a fixed-size type needs: the value is read from the item's
  first registers (as many as the type needs, combined in the item's word order); the
  other registers are ignored on read and not written by :func:`encode`.
* Smart Cast (a ``quantity`` smaller than the type needs) reads the widest smaller
  value that fits: Int64/UInt64/Double from 2 registers read Int32/UInt32/Float32, from
  1 register Int16/UInt16/Int16; Int32/UInt32/Float from 1 register read Int16/UInt16/Int16;
  BCD32 from 1 register reads BCD16; DateTime/Timestamp need 2 (seconds) or 4 (ms).
* Byte/Sbyte and Char are the low byte of the register after the byte swap; Char is a
  1-character str of that byte's code point (latin-1: ``chr(byte)``).
* A bit of a register (``hr:100.3``) is taken after the byte swap, so it agrees with the
  UInt16 reading of the same register in the same format (bit 0 = least significant).
* ``convertedDataType`` Float keeps double precision but must fit a float32's range.
* Deadband applies to numeric results (int, float); bool, str, bytes and datetime values
  report any change.
* An item that stays Invalid is reported again when its reason changes (the slave now
  holds another bad value); the reason always names the value just read.
"""

from __future__ import annotations

from .decoder import BlockDecoder, Change
from .encoder import encode, register_bit
from .jsonable import jsonable
from .normalize import normalize_value
from .spec import MAX_QUANTITY, ValueSpec, check_spec

__all__ = [
    "MAX_QUANTITY",
    "BlockDecoder",
    "Change",
    "ValueSpec",
    "check_spec",
    "encode",
    "jsonable",
    "normalize_value",
    "register_bit",
]
