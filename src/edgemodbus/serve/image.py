"""A served device's items as a unit's register image, and back.

Serve mode answers reads from an image in C (csrc/emb_serve.c) that holds, per address,
a register (or bit) and its state: unmapped (exception 02), valid, or invalid (0B).  The
image is the items' values re-encoded with their own codec spec (the exact inverse of
the decode, as writes use): a register is what the slave holds, except where the decode
drops something (the unused registers of a Smart Cast item and byte A of Int24 read 0;
a String's trailing NULs are NULs again).  A register holding bit items (``hr:5.3``)
holds those bits and 0 elsewhere; it is read-only through the server.

Writes come the other way: the registers or coils a master writes are decoded into the
values of the items they cover, which the driver writes (``write_addresses``).  A write
must cover whole items: a part of a multi-register item gets exception 02.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from .._ffi import Block
from .._ffi.serve import STATE_INVALID, STATE_VALID, STATE_WRITABLE, ImageRun
from ..codec import BlockDecoder, ValueSpec, encode, register_bit
from ..config import ConfigError, DeviceAddressItem, ParsedItem, Problem
from ..datatypes import Area, ItemStatus

AREA_INDEX = {Area.COIL: 0, Area.DISCRETE_INPUT: 1, Area.HOLDING_REGISTER: 2,
              Area.INPUT_REGISTER: 3}

# exception codes (Modbus Application Protocol v1.1b3, 7)
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03


@dataclass(eq=False)
class MappedItem:
    """One item at its address in the unit's address space."""

    name: str
    area: Area
    address: int  # the unit's address: the device's plus the unit's offset
    size: int  # registers (1 for a bit area or a bit of a register)
    spec: ValueSpec
    bit: int | None  # the wire bit of a register's bit item
    value: int = 0  # a bit item's bit, as last encoded
    valid: bool = False
    decoder: BlockDecoder | None = field(default=None, repr=False)

    @property
    def writable(self) -> bool:
        return self.area.writable and self.bit is None


class UnitImage:
    """The image of one served device (``unit``: its unit id; ``offset`` is added to the
    device's addresses).  Raises ConfigError when an item falls outside 0..65535."""

    def __init__(self, unit: int, device: str, parsed: Sequence[ParsedItem],
                 offset: int = 0) -> None:
        self.unit = unit
        self.device = device
        self.items: dict[str, MappedItem] = {}
        self._owner: dict[tuple[Area, int], MappedItem] = {}  # whole items, by address
        self._bits: dict[int, list[MappedItem]] = {}  # bit items of a holding/input register
        problems: list[Problem] = []
        for p in parsed:
            if not p.item.is_enable:
                continue
            area = p.address.area
            size = 1 if area.is_bit or p.address.bit is not None else p.registers
            address = p.address.offset + offset
            if not (address >= 0 and address + size <= 0x10000):
                problems.append(Problem(f"serve.units[unitId={unit}].offset", offset,
                                        f"item {p.name!r} of {device!r} would be at "
                                        f"{address}..{address + size - 1}: outside 0..65535"))
                continue
            spec = p.value_spec()
            bit = register_bit(spec) if p.address.bit is not None and not area.is_bit else None
            mapped = MappedItem(p.name, area, address, size, spec, bit)
            self.items[p.name] = mapped
            if bit is not None:
                self._bits.setdefault(_bit_key(area, address), []).append(mapped)
            else:
                for k in range(size):
                    self._owner[(area, address + k)] = mapped
        if problems:
            raise ConfigError(problems)

    def spans(self) -> list[tuple[int, int]]:
        """(start, count) of each area (coils, discrete inputs, holding, input)."""
        result = []
        for area in AREA_INDEX:
            addresses = [m.address for m in self.items.values() if m.area is area]
            ends = [m.address + m.size for m in self.items.values() if m.area is area]
            result.append((min(addresses), max(ends) - min(addresses)) if addresses
                          else (0, 0))
        return result

    def mapping(self) -> list[ImageRun]:
        """Every item's addresses, invalid until its value is known (the image's start)."""
        return [ImageRun(self.unit, AREA_INDEX[m.area], m.address, self._state(m, False),
                         [0] * m.size) for m in self.items.values()]

    def runs(self, items: Iterable[DeviceAddressItem]) -> list[ImageRun]:
        """The image runs for items just reported (their value and status read now)."""
        runs: list[ImageRun] = []
        for item in items:
            mapped = self.items.get(item.name)
            if mapped is not None:
                runs.append(self._run(mapped, item.value, item.status))
        return runs

    def seed(self, snapshot_items: dict[str, dict[str, object]]) -> list[ImageRun]:
        """The runs for a driver's ``snapshot()["items"]`` (the items' Python values)."""
        from ..codec import normalize_value

        runs: list[ImageRun] = []
        for name, entry in snapshot_items.items():
            mapped = self.items.get(name)
            if mapped is None:
                continue
            value = entry.get("value")
            status = ItemStatus.OK if entry.get("status") == ItemStatus.OK.value else None
            if value is not None and status is ItemStatus.OK:
                spec = mapped.spec
                try:
                    value = normalize_value(name, spec.converted_type or spec.data_type, value)
                except ValueError:
                    status = None
            runs.append(self._run(mapped, value, status))
        return runs

    def _run(self, mapped: MappedItem, value: object, status: object) -> ImageRun:
        registers: list[int] | None = None
        if status is ItemStatus.OK and value is not None:
            try:
                registers = encode(mapped.spec, value)
            except (ValueError, TypeError, OverflowError):
                registers = None
        area = AREA_INDEX[mapped.area]
        if mapped.bit is not None:
            mapped.valid = registers is not None
            mapped.value = registers[0] if registers is not None else 0
            sharing = self._bits[_bit_key(mapped.area, mapped.address)]
            word = sum(m.value << m.bit for m in sharing if m.bit is not None)
            valid = all(m.valid for m in sharing)
            return ImageRun(self.unit, area, mapped.address, self._state(mapped, valid), [word])
        mapped.valid = registers is not None
        if registers is None or len(registers) != mapped.size:
            return ImageRun(self.unit, area, mapped.address, self._state(mapped, False),
                            [0] * mapped.size)
        return ImageRun(self.unit, area, mapped.address, self._state(mapped, True), registers)

    @staticmethod
    def _state(mapped: MappedItem, valid: bool) -> int:
        return ((STATE_VALID if valid else STATE_INVALID)
                | (STATE_WRITABLE if mapped.writable else 0))

    # -- writes ----------------------------------------------------------------------
    def write_values(self, area: Area, address: int,
                     words: Sequence[int]) -> list[tuple[str, object]] | int:
        """The (item name, value) writes for ``words`` (registers, or bits 0/1) written
        from ``address`` of ``area``, or the exception code to answer: 02 for an address
        without a writable item or a part of an item, 03 for registers that decode to
        no value of their item."""
        writes: list[tuple[str, object]] = []
        end = address + len(words)
        at = address
        while at < end:
            mapped = self._owner.get((area, at))
            if mapped is None or not mapped.writable or mapped.address != at \
                    or at + mapped.size > end:
                return ILLEGAL_DATA_ADDRESS
            chunk = list(words[at - address: at - address + mapped.size])
            if area.is_bit:
                writes.append((mapped.name, bool(chunk[0])))
            else:
                if mapped.decoder is None:
                    mapped.decoder = BlockDecoder(area, mapped.size, [(0, mapped.spec)])
                value = mapped.decoder.decode_values(Block.from_values(chunk, bits=False))[0]
                if value is None:
                    return ILLEGAL_DATA_VALUE
                writes.append((mapped.name, value))
            at += mapped.size
        return writes


def _bit_key(area: Area, address: int) -> int:
    return AREA_INDEX[area] << 16 | address
