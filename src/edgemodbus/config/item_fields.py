"""The fields of one tag as a device file gives them, and their checks: :class:`ItemFields`,
the validator behind :class:`~edgemodbus.config.items.DeviceAddressItem` (which keeps the
validated values compactly, see items.py).  Limits are the codec's and the address
parser's own.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from datetime import datetime
from typing import Annotated, Any, ClassVar

from pydantic import Field, field_serializer, field_validator, model_validator

from ..codec import MAX_QUANTITY
from ..datatypes import DataFormat, DataFormat64, DataType, ItemStatus
from ..protocol.address import ENTITY_TABLES, parse_address
from .base import (
    MAX_MS,
    MS_RANGE,
    Model,
    OptionalMs,
    Range,
    as_number,
    check_encoding,
    lower_literal,
    parse_enum_ci,
    parse_format,
)
from .communication import ReportMode
from .compat import NG_POINT_KEYS, iso_timestamp, ng_point
from .problems import WrongType

ON_DEMAND = -1  # an item's readCycle -1: never polled, read when asked (docs/reporting.md)
_DEMAND_WORDS = ("demand", "ondemand")


class ItemFields(Model):
    """The fields of one tag, checked: what a :class:`DeviceAddressItem` is built from (a
    passing object, never kept).  ``value``, ``status``, ``updateTs`` and
    ``errorReason`` are the seed's fields: a file may give their first state.
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
        """Keys in their canonical spelling, NG's point keys translated; anything but
        an object is refused (a fields dict of an item passes as it is)."""
        if not isinstance(data, Mapping):
            raise WrongType("must be an object ({...})")
        data = cls.normalize_keys(data, cls._where)
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


