"""Address list items: :class:`DeviceAddressItem` (one tag as loaded), :class:`ParsedItem`
(an item checked against the communication options) and :func:`validate_items`.

Limits are those of the layers that use the values (one source of truth): item
quantities come from the codec, offsets and bits from the address parser, and
:func:`validate_items` runs the codec's own item check.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from ..codec import SMART_CAST_TYPES, ValueSpec, check_spec, smart_cast
from ..codec.shared import SharedCache
from ..datatypes import Area, DataFormat, DataFormat64, DataType
from ..protocol.address import Address, check_span, parse_address
from .base import MS_RANGE, field_checks, recheck
from .communication import DriverModbusRtuParameter
from .item_fields import ON_DEMAND, ItemFields, _strip_echo
from .item_model import CONF_FIELDS, MOVING, STATUSES, DeviceAddressItem, ItemReading
from .problems import NO_VALUE, ConfigError, Problem
from .scaling import (
    ScaleFactors,
    link_scale_factors,
    scaling_fields,
    scaling_keys,
    scaling_shape,
)

__all__ = ["ALLOWED_QUANTITIES", "MOVING", "ON_DEMAND", "STATUSES", "DeviceAddressItem",
           "ItemFields", "ItemReading", "ParsedItem", "validate_items"]

_log = logging.getLogger("edgemodbus.config")


ALLOWED_QUANTITIES: dict[DataType, tuple[int, ...]] = {
    DataType.BOOLEAN: (1,),
    DataType.CHAR: (1,),
    DataType.DATETIME: (2, 4),
    DataType.TIMESTAMP: (2, 4),
}
"""Register counts an item of these types may read.  The numeric types
(:data:`SMART_CAST_TYPES`) take any quantity 1..125 (Smart Cast: fewer registers hold a
smaller value that is widened, more hold a wider one that is narrowed, see docs/device-files.md
"Smart Cast"); String and Binary take any quantity >= 1."""

_SMART_CAST_WARNED: set[tuple[Any, ...]] = set()
_SMART_CAST_WARNED_MAX = 10_000  # forget (and warn again) past this many distinct items


def _warn_smart_cast(spec: ValueSpec, path: str) -> None:
    """Log once per item (by name and shape) what Smart Cast does with its quantity."""
    text = smart_cast(spec)
    if text is None:
        return
    key = (spec.name, spec.data_type, spec.quantity, spec.data_format, spec.multiplier != 1)
    if key in _SMART_CAST_WARNED:
        return
    if len(_SMART_CAST_WARNED) >= _SMART_CAST_WARNED_MAX:
        _SMART_CAST_WARNED.clear()
    _SMART_CAST_WARNED.add(key)
    _log.warning("%s (%r): Smart Cast: %s", path, spec.name, text)


_AREA_NAMES = {
    Area.COIL: "coil",
    Area.DISCRETE_INPUT: "discrete input",
    Area.HOLDING_REGISTER: "holding register",
    Area.INPUT_REGISTER: "input register",
}


@dataclass(frozen=True, slots=True)
class ParsedItem:
    """An item checked against the communication options, ready for the planner/codec.

    ``registers``: registers (register areas) or bits (1) the item occupies;
    ``data_format``, ``byte_swap16``, ``data_format64`` and ``encoding`` are the
    effective ones (item's, else comm's, each key on its own)."""

    item: DeviceAddressItem
    address: Address
    data_type: DataType
    converted_type: DataType | None
    data_format: DataFormat
    byte_swap16: bool
    data_format64: DataFormat64 | None
    registers: int
    quantity: int | None
    multiplier: float
    deadband: float | None
    encoding: str
    factors: ScaleFactors | None = None  # the device's, when an item has a scaleFactor

    @property
    def name(self) -> str:
        return self.item.name

    def value_spec(self, name: str | None = None) -> ValueSpec:
        """The codec's spec of this item (what the driver decodes and encodes with);
        ``name`` replaces the item's name (a spec shared by items of one kind has none)."""
        return ValueSpec(
            name=self.item.name if name is None else name,
            data_type=self.data_type,
            data_format=self.data_format,
            byte_swap16=self.byte_swap16,
            data_format64=self.data_format64,
            quantity=self.quantity,
            bit=self.address.bit,
            multiplier=self.multiplier,
            converted_type=self.converted_type,
            deadband=self.deadband or 0.0,
            encoding=self.encoding,
            **scaling_keys(self.item, self.factors),
        )


def _item_registers(
    item: DeviceAddressItem, addr: Address, path: str, problems: list[Problem]
) -> int:
    """Registers/bits the item occupies; appends problems for type/area mismatches."""
    dtype, quantity = item.device_data_type, item.quantity
    if addr.area.is_bit or addr.bit is not None:
        where = (
            f"a {_AREA_NAMES[addr.area]} holds one bit"
            if addr.area.is_bit
            else "a bit address (.N) reads one bit"
        )
        if dtype is not DataType.BOOLEAN:
            problems.append(Problem(f"{path}.deviceDataType", dtype.value, f"{where}: use Boolean"))
        if quantity not in (None, 1):
            problems.append(
                Problem(f"{path}.quantity", quantity, f"{where}: use 1 or leave it out")
            )
        return 1
    if dtype.needs_quantity:
        if quantity is None:
            problems.append(
                Problem(
                    f"{path}.quantity",
                    NO_VALUE,
                    f"{dtype.value} needs quantity (its length in registers)",
                )
            )
            return 1
        return quantity
    if quantity is None:
        return dtype.registers
    if dtype in SMART_CAST_TYPES:
        return quantity
    allowed = ALLOWED_QUANTITIES[dtype]
    if quantity not in allowed:
        problems.append(
            Problem(
                f"{path}.quantity",
                quantity,
                f"{dtype.value} allows quantity {' or '.join(map(str, allowed))} (or leave it out)",
            )
        )
        return dtype.registers
    return quantity


COMM_KEYS = ("address_prefix", "address_base", "framing", "data_format", "byte_swap16",
             "data_format64", "encoding", "read_cycle", "report_every", "report_mode")
"""The communication fields :func:`validate_items` reads: with the items' own fields,
the whole of its input (tests/unit/config/test_items_memo.py checks it reads no other)."""

_Checked = tuple[tuple["ParsedItem", ...], tuple[tuple[Any, ...], ...]]
_VALIDATED: SharedCache[_Checked] = SharedCache(keep=64, weak=False)
"""Address lists validated before, by their whole input (:func:`_input_key`); with the
results, the config tuples whose ids the key holds (alive, so no other tuple has them)."""


def _input_key(items: Sequence[DeviceAddressItem],
               comm: DriverModbusRtuParameter) -> tuple[Any, ...] | None:
    """What :func:`validate_items` reads of its input, as a key: the communication
    fields of :data:`COMM_KEYS` and each item's name, address, description (each a str)
    and config tuple (every other field, item_model.py: by identity, as items of one
    kind share one tuple, and equal values of other types, 1 and True, are not one
    input).  None when the result is not one to share: a scaleFactor (the device's own
    table), an item of another class, a value that is not hashable, a list longer than
    :data:`MEMO_MAX_ITEMS`."""
    if len(items) > MEMO_MAX_ITEMS:
        return None
    rows = []
    for it in items:
        if type(it) is not DeviceAddressItem:
            return None
        name, address, description, conf = it.name, it.address, it.description, it._conf
        if conf[_SCALE_FACTOR] is not None or type(name) is not str \
                or type(address) is not str or type(description) is not str:
            return None
        rows.append((name, address, description, id(conf)))
    key = (tuple([(type(v), v) for v in [getattr(comm, f) for f in COMM_KEYS]]),
           tuple(rows))
    try:
        hash(key)
    except TypeError:
        return None
    return key


_SCALE_FACTOR = CONF_FIELDS.index("scale_factor")
MEMO_MAX_ITEMS = 500
"""The longest list memoised: a key holds a row per item, and a template that many
devices share is short (a device of thousands of tags is rarely one of thousands)."""

# the last list validated: a gateway loads a file, then starts its device with the same
# items (key, the items, their results, the config tuples whose ids the key holds)
_last: tuple[tuple[Any, ...], tuple[DeviceAddressItem, ...], list[ParsedItem],
             tuple[Any, ...]] | None = None


def validate_items(
    items: Sequence[DeviceAddressItem], comm: DriverModbusRtuParameter
) -> list[ParsedItem]:
    """Check every item against ``comm`` (address prefix/base, type vs area, quantity,
    span, unique names), against its own field limits again (an item may have been
    changed after it was loaded) and against the codec's check of the spec the driver
    will build; return them parsed, in order.  Raises one ConfigError listing every
    problem with its path (``addressList[3].address`` ...).

    The check is a function of its input alone, so an input checked before (the same
    fields and options: a template's 5,000 devices, or a file loaded then started)
    takes that result, given these items (docs/scale.md, "Starting thousands of
    devices"); an item changed since it was checked is a new input, checked."""
    global _last
    key = _input_key(items, comm)
    if key is None:
        return _validate(items, comm)
    last = _last
    if last is not None and last[0] == key and len(last[1]) == len(items) \
            and all(a is b for a, b in zip(last[1], items, strict=True)):
        return list(last[2])
    checked, confs = _VALIDATED.get(key, lambda: (tuple(_validate(items, comm)),
                                                  tuple(it._conf for it in items)))
    parsed = [one if one.item is item else _rebind(one, item)
              for one, item in zip(checked, items, strict=True)]
    _last = (key, tuple(items), parsed, confs)
    return list(parsed)


def _rebind(one: ParsedItem, item: DeviceAddressItem) -> ParsedItem:
    """``one`` (checked for an equal item) for ``item``."""
    return ParsedItem(item, one.address, one.data_type, one.converted_type, one.data_format,
                      one.byte_swap16, one.data_format64, one.registers, one.quantity,
                      one.multiplier, one.deadband, one.encoding, one.factors)


def _validate(
    items: Sequence[DeviceAddressItem], comm: DriverModbusRtuParameter
) -> list[ParsedItem]:
    """:func:`validate_items`, computed."""
    problems: list[Problem] = []
    parsed: list[ParsedItem] = []
    first_index: dict[str, int] = {}
    checked: set[tuple[Any, ...]] = set()
    inherited_checked: set[str] = set()  # communication.reportEvery: one problem at most
    for i, item in enumerate(items):
        path = f"addressList[{i}]"
        before = len(problems)
        if item.name in first_index:
            problems.append(
                Problem(
                    f"{path}.name",
                    item.name,
                    f"duplicate item name (also addressList[{first_index[item.name]}])",
                )
            )
        else:
            first_index[item.name] = i
        limits = recheck(item, _ITEM_CHECKS, path)
        if limits:  # the checks below use these values
            problems += limits
            continue
        try:
            addr = parse_address(item.address, comm.address_prefix, comm.address_base)
        except ValueError as exc:
            problems.append(Problem(f"{path}.address", item.address,
                                    _strip_echo(item.address, exc) + _entity_hint(item, comm)))
            continue
        registers = _item_registers(item, addr, path, problems)
        try:
            check_span(addr, registers)
        except ValueError as exc:
            message = str(exc).removeprefix(f"{addr}: ")
            problems.append(Problem(f"{path}.address", item.address, message))
        if item.read_cycle == 0 and comm.framing != "wrapped-report":
            problems.append(Problem(
                f"{path}.readCycle", 0,
                "0 means not polled, updated by wrapped reports only, which needs framing "
                f"'wrapped-report' (framing is {comm.framing!r}): use {MS_RANGE.describe()} ms, "
                "or leave it out for the device's readCycle"))
        problems += _report_problems(item, comm, path, inherited_checked)
        if len(problems) > before:
            continue
        one = ParsedItem(
            item=item,
            address=addr,
            data_type=item.device_data_type,
            converted_type=item.converted_data_type,
            data_format=item.data_format or comm.data_format,
            byte_swap16=comm.byte_swap16 if item.byte_swap16 is None else item.byte_swap16,
            data_format64=item.data_format64 or comm.data_format64,
            registers=registers,
            quantity=item.quantity,
            multiplier=item.data_multiplier,
            deadband=item.deadband,
            encoding=item.encoding or comm.encoding,
        )
        # the codec's check depends on everything but the name: check each shape once
        shape = (addr.area, addr.bit, one.data_type, one.data_format, one.byte_swap16,
                 one.data_format64, one.quantity, one.multiplier, one.converted_type,
                 one.deadband, one.encoding, *scaling_shape(item))
        if shape not in checked:
            spec = one.value_spec()
            try:
                check_spec(spec, addr.area)
            except ValueError as exc:
                problems.append(_codec_problem(exc, spec, item, path))
                continue
            checked.add(shape)
        _warn_smart_cast(one.value_spec(), path)
        parsed.append(one)
    parsed = link_scale_factors(parsed, items, problems)
    if problems:
        raise ConfigError(problems)
    return parsed


_ITEM_CHECKS = field_checks(ItemFields)


def _report_problems(item: DeviceAddressItem, comm: DriverModbusRtuParameter, path: str,
                     inherited_checked: set[str]) -> list[Problem]:
    """reportMode/reportEvery against the item's scan rate (docs/reporting.md): a period
    report repeats the last read, so it needs reads at least as often as the period."""
    rate = comm.read_cycle if item.read_cycle is None else item.read_cycle
    own = item.report_every
    if own is not None and item.report_mode == "cycle":
        return [Problem(f"{path}.reportEvery", own, "reportMode 'cycle' reports every read "
                        "already: leave reportEvery out, or use reportMode 'change'")]
    if own is not None and rate <= 0:
        what = "on demand" if rate == ON_DEMAND else "updated by wrapped reports only"
        return [Problem(f"{path}.reportEvery", own, f"the item is not polled (readCycle "
                        f"{rate}: {what}), so there is no read to report again: leave "
                        "reportEvery out")]
    every = own if own is not None else comm.report_every
    mode = item.report_mode or ("change" if own is not None else comm.report_mode)
    if every is None or rate <= 0 or every >= rate or mode == "cycle":
        return []
    where = f"{path}.reportEvery" if own is not None else "communication.reportEvery"
    if where in inherited_checked:
        return []
    inherited_checked.add(where)
    return [Problem(where, every, f"shorter than the scan rate of item {item.name!r} "
                    f"({rate} ms): a period report repeats the last read, so use {rate} or "
                    "more, or reportMode 'cycle' to report every read")]


def _entity_hint(item: DeviceAddressItem, comm: DriverModbusRtuParameter) -> str:
    """A hint when an address the options refuse is a Modicon entity number."""
    if comm.address_prefix == "entity" or ":" in item.address:
        return ""
    try:
        addr = parse_address(item.address, "entity")
    except ValueError:
        return ""
    return f" (with addressPrefix 'entity' it is the entity number of {addr})"


def _codec_problem(
    exc: ValueError, spec: ValueSpec, item: DeviceAddressItem, path: str
) -> Problem:
    """codec.check_spec's "item 'x': <field> <value> is not allowed (<why>)" as a
    Problem at the item's JSON key."""
    text = str(exc).removeprefix(f"item {spec.name!r}: ")
    fields: dict[str, tuple[str, Any]] = {
        "quantity": ("quantity", spec.quantity),
        "data type": ("deviceDataType", spec.data_type.value),
        "bit": ("address", item.address),
        "dataMultiplier": ("dataMultiplier", spec.multiplier),
        "convertedDataType": (
            "convertedDataType",
            None if spec.converted_type is None else spec.converted_type.value,
        ),
        "deadband": ("deadband", spec.deadband),
        **scaling_fields(spec),
        "encoding": ("encoding", spec.encoding),
    }
    head, sep, why = text.partition(" is not allowed (")
    for field, (key, value) in fields.items():
        if sep and head.startswith(f"{field} "):
            return Problem(f"{path}.{key}", value, f"not allowed: {why.removesuffix(')')}")
    return Problem(path, NO_VALUE, text)
