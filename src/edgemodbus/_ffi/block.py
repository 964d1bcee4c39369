"""The register or bit buffer a read fills (a view of cdata)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .native import ffi


class Block:
    """The data of the last read on a :class:`Context`: registers or bits (one per byte).

    It is a view of the context's own buffer, valid until the next read on it; the line's
    worker decodes it before issuing another request, so no read allocates.
    """

    __slots__ = ("_ptr", "bits", "count")

    def __init__(self, ptr: Any, bits: bool) -> None:
        self._ptr = ptr
        self.bits = bits
        self.count = 0

    def to_list(self) -> list[int]:
        """Copy out the values (registers as ints, bits as 0/1)."""
        return list(ffi.unpack(self._ptr, self.count))

    @classmethod
    def from_values(cls, values: Sequence[int], bits: bool) -> Block:
        """A block holding ``values`` (registers 0..65535, or bits 0/1), for tests and for
        an item reassembled from pieces read separately."""
        top = 1 if bits else 0xFFFF
        for k, v in enumerate(values):
            if not 0 <= v <= top:
                kind = "bit" if bits else "register"
                raise ValueError(f"{kind} value {v!r} at index {k} is out of range 0..{top}")
        block = cls(ffi.new("uint8_t[]" if bits else "uint16_t[]", list(values) or [0]), bits)
        block.count = len(values)
        return block

