"""Address list items: :class:`DeviceAddressItem` (one tag as loaded), :class:`ParsedItem`
(an item checked against the communication options) and :func:`validate_items`.

Limits are those of the layers that use the values (one source of truth): item
quantities come from the codec, offsets and bits from the address parser, and
:func:`validate_items` runs the codec's own item check.
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, ClassVar

from pydantic import Field, field_serializer, field_validator, model_validator

from ..codec import MAX_QUANTITY, SMART_CAST_TYPES, ValueSpec, check_spec, smart_cast
from ..datatypes import Area, DataFormat, DataFormat64, DataType, ItemStatus
from ..protocol.address import ENTITY_TABLES, Address, check_span, parse_address
from .base import (
    MAX_MS,
    MS_RANGE,
    OptionalMs,
    Range,
    SlotModel,
    as_number,
    check_encoding,
    field_checks,
    lower_literal,
    parse_enum_ci,
    parse_format,
    recheck,
    slot_model,
)
from .communication import DriverModbusRtuParameter, ReportMode
from .compat import NG_POINT_KEYS, iso_timestamp, ng_point
from .problems import NO_VALUE, ConfigError, Problem, WrongType
from .scaling import (
    ScaleFactors,
    link_scale_factors,
    scaling_fields,
    scaling_keys,
    scaling_shape,
)

_log = logging.getLogger("edgemodbus.config")
ON_DEMAND = -1  # an item's readCycle -1: never polled, read when asked (docs/reporting.md)


@slot_model
class DeviceAddressItem(SlotModel):
    """One tag.  ``value``, ``status``, ``update_ts`` and ``error_reason`` are runtime
    state set by the driver's worker thread: assignment is not validated (cheap).

    A slotted pydantic dataclass (see :class:`SlotModel`): a gateway holds one per tag,
    and a BaseModel's ``__dict__`` and fields-set made up most of a tag's memory.
    Repeated text (address, description, unit, encoding) is interned: the same
    addresses recur on every device of a kind."""

    _where: ClassVar[str] = "addressList[]"

    name: str
    address: str
    device_data_type: DataType
    converted_data_type: DataType | None = None
    data_multiplier: float = 1.0
    description: str = ""
    unit: str = ""
    update_ts: datetime | None = None
    status: ItemStatus = ItemStatus.UNKNOWN
    is_enable: bool = True
    address_changed: bool = False
    data_format: DataFormat | None = None
    byte_swap16: bool | None = None
    data_format64: DataFormat64 | None = None
    quantity: Annotated[int | None, Range(1, MAX_QUANTITY)] = None
    deadband: Annotated[float | None, Range(0)] = None
    encoding: str | None = None
    read_cycle: Annotated[int | None, Range(ON_DEMAND, MAX_MS)] = Field(
        default=None,
        description="This item's scan rate (ms), default the device's readCycle; items of "
        "different rates are never read in one request; 0 = not polled, updated by "
        "wrapped reports only (framing wrapped-report); -1 or \"demand\" = never polled, "
        "read only when asked (docs/reporting.md)",
    )
    report_mode: ReportMode | None = Field(
        default=None, description="change or cycle; default the device's reportMode")
    report_every: OptionalMs = Field(
        default=None, description="Report an unchanged item again once its last report is "
        "this old (ms, at least its scan rate); default the device's reportEvery")
    offset: float = Field(default=0.0, description="Added to the value after dataMultiplier "
                          "(value = raw x 10^sf x dataMultiplier + offset; "
                          "docs/engineering-units.md)")
    raw_min: float | None = Field(default=None, description="Range scaling: the raw value "
                                  "that reads as engMin (rawMin, rawMax, engMin, engMax: "
                                  "all four or none)")
    raw_max: float | None = Field(default=None, description="Range scaling: the raw value "
                                  "that reads as engMax")
    eng_min: float | None = Field(default=None, description="Range scaling: the value at rawMin")
    eng_max: float | None = Field(default=None, description="Range scaling: the value at rawMax")
    clamp: bool = Field(default=False, description="Range scaling: a raw value outside "
                        "rawMin..rawMax reads as the nearest of engMin/engMax (false: the "
                        "item is Invalid)")
    scale_factor: str | None = Field(default=None, description="The name of an Int16 item "
                                     "of the same device holding sf: value x 10^sf "
                                     "(SunSpec *_SF); -10..10, 0x8000 = not implemented")
    value: Any = None
    error_reason: str | None = None

    _extra_keys: ClassVar[tuple[str, ...]] = NG_POINT_KEYS

    @model_validator(mode="before")
    @classmethod
    def _accept_keys(cls, data: Any) -> Any:
        # by name: pydantic binds ``cls`` to the class before slots=True remade it
        data = DeviceAddressItem.accept_keys(data)
        return ng_point(data) if isinstance(data, dict) else data

    @field_validator("read_cycle", mode="before")
    @classmethod
    def _read_cycle(cls, value: Any) -> Any:
        if isinstance(value, str) and value.strip().lower().replace("-", "") in _DEMAND_WORDS:
            return ON_DEMAND
        if isinstance(value, int) and not isinstance(value, bool) and value < ON_DEMAND:
            raise ValueError(f"must be -1 (\"demand\": read only when asked), 0 (wrapped "
                             f"reports only) or {MS_RANGE.describe()} ms")
        return value

    @field_validator("report_mode", mode="before")
    @classmethod
    def _report_mode(cls, value: Any) -> Any:
        return lower_literal(value)

    @field_validator("address", "description", "unit")
    @classmethod
    def _intern(cls, value: str) -> str:
        return sys.intern(value)

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("an item needs a non-empty name")
        return value

    @field_validator("address", mode="before")
    @classmethod
    def _address_text(cls, value: Any) -> Any:
        """A JSON number is the offset it spells (100 means "100", i.e. hr:100)."""
        if isinstance(value, int) and not isinstance(value, bool):
            return str(value)
        if not isinstance(value, str):
            raise WrongType("must be a string like 'hr:100' (or a whole number: an offset)")
        return value

    @field_validator("data_multiplier", mode="before")
    @classmethod
    def _multiplier_number(cls, value: Any) -> Any:
        return as_number(value, False, False, "a finite number other than 0")

    @field_validator("offset", mode="before")
    @classmethod
    def _offset_number(cls, value: Any) -> Any:
        return as_number(value, False, False, "a finite number")

    @field_validator("raw_min", "raw_max", "eng_min", "eng_max", mode="before")
    @classmethod
    def _range_number(cls, value: Any) -> Any:
        return as_number(value, False, True, "a finite number")

    @field_validator("offset", "raw_min", "raw_max", "eng_min", "eng_max")
    @classmethod
    def _finite(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @field_validator("scale_factor", mode="before")
    @classmethod
    def _factor_name(cls, value: Any) -> Any:
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        if not isinstance(value, str):
            raise WrongType("must be the name of an Int16 item of the same device")
        return value

    @field_validator("address")
    @classmethod
    def _address(cls, value: str) -> str:
        # Syntax only: prefix/base live in communication (checked by validate_items).
        try:
            parse_address(value)
        except ValueError as exc:
            try:
                parse_address(value, base=1)
            except ValueError:
                if not _entity_like(value):
                    raise ValueError(_strip_echo(value, exc)) from None
            # a bare number: an entity number under addressPrefix entity, whose own
            # message (its table's range) validate_items gives with the options
        return value
        return value

    @field_validator("device_data_type", mode="before")
    @classmethod
    def _device_type(cls, value: Any) -> Any:
        return DataType.parse(value) if isinstance(value, str) else value

    @field_validator("converted_data_type", mode="before")
    @classmethod
    def _converted_type(cls, value: Any) -> Any:
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        return DataType.parse(value) if isinstance(value, str) else value

    @field_validator("data_format", mode="before")
    @classmethod
    def _format(cls, value: Any) -> Any:
        if isinstance(value, str) and not value.strip():
            return None
        return parse_format(value)

    @field_validator("data_format64", mode="before")
    @classmethod
    def _format64(cls, value: Any) -> Any:
        if isinstance(value, str) and not value.strip():
            return None
        return parse_format(value, DataFormat64)

    @field_validator("status", mode="before")
    @classmethod
    def _status(cls, value: Any) -> Any:
        return parse_enum_ci(ItemStatus, value)

    @field_validator("data_multiplier")
    @classmethod
    def _multiplier(cls, value: float) -> float:
        if not math.isfinite(value) or value == 0:
            raise ValueError("must be a finite number other than 0")
        return value

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, value: str | None) -> str | None:
        return None if value is None or not value.strip() else sys.intern(check_encoding(value))

    @field_validator("update_ts", mode="before")
    @classmethod
    def _ts(cls, value: Any) -> Any:
        return iso_timestamp(value)

    @field_serializer("converted_data_type")
    def _ser_converted(self, value: DataType | None) -> str:
        return "" if value is None else value.value


def _entity_like(text: str) -> bool:
    """A bare decimal number of at most 6 digits whose first is a table digit, with or
    without ``.bit``: the shape of an entity number (its range is checked later)."""
    number, _, bit = text.strip().partition(".")
    return (number.isascii() and number.isdigit() and len(number) <= 6
            and number.zfill(5)[0] in ENTITY_TABLES and (not bit or bit.isdigit()))


def _strip_echo(text: str, exc: ValueError) -> str:
    """parse_address's message without its leading ``'text': `` (the path shows it)."""
    message = str(exc)
    return message.removeprefix(f"{text!r}: ")


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


def validate_items(
    items: Sequence[DeviceAddressItem], comm: DriverModbusRtuParameter
) -> list[ParsedItem]:
    """Check every item against ``comm`` (address prefix/base, type vs area, quantity,
    span, unique names), against its own field limits again (an item may have been
    changed after it was loaded) and against the codec's check of the spec the driver
    will build; return them parsed, in order.  Raises one ConfigError listing every
    problem with its path (``addressList[3].address`` ...)."""
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


_ITEM_CHECKS = field_checks(DeviceAddressItem)
_DEMAND_WORDS = ("demand", "ondemand")


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
