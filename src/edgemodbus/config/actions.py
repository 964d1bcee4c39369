"""Actions (NG's ``Action``): named groups of writes with parameters, in the device file.

An action names a function code (5, 6, 15 or 16, or NG's names) and parameters; each
parameter sets one item of the address list.  Keys follow NG's (``name``,
``functionCode``, ``inputParameters`` with ``key``/``name``, ``dataType``, ``required``,
``defaultValue``, ``minValue``, ``maxValue``); ``parameters``, ``type`` and ``default``
are accepted too (compat.py).  NG's own form, ``functionCode`` with ``address`` and
``quantity`` and no parameters, writes the value given when it runs (poll/actions.py).
:func:`validate_actions` checks them against the items: docs/device-files.md, "Actions".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any, ClassVar

from pydantic import Field, field_validator, model_validator

from ..codec import normalize_value
from ..datatypes import Area, DataType
from ..protocol.address import MAX_OFFSET
from ..protocol.limits import MAX_WRITE_BITS, MAX_WRITE_REGISTERS
from .base import Model, Range
from .compat import (
    NG_ACTION_KEYS,
    NG_PARAMETER_KEYS,
    function_code,
    ng_action,
    ng_action_parameter,
)
from .items import ParsedItem
from .limits import MAX_NAME
from .problems import NO_VALUE, ConfigError, Problem

ACTION_FUNCTIONS: dict[int, tuple[Area, str]] = {
    5: (Area.COIL, "WriteSingleCoil: one request per coil"),
    6: (Area.HOLDING_REGISTER, "WriteSingleRegister: one request per register"),
    15: (Area.COIL, "WriteMultipleCoils: neighbouring coils in one request"),
    16: (Area.HOLDING_REGISTER, "WriteMultipleRegisters: neighbouring registers in one request"),
}
"""Function codes an action may use (MODBUS Application Protocol v1.1b3, 6.5, 6.6, 6.11,
6.12): the area they write and how requests are made."""

_FUNCTION_NAMES = ", ".join(
    f"{code} ({why.partition(':')[0]})" for code, (_, why) in ACTION_FUNCTIONS.items()
)

PARAMETER_TYPES: tuple[DataType, ...] = (
    DataType.BOOLEAN, DataType.SBYTE, DataType.BYTE, DataType.INT16, DataType.UINT16,
    DataType.INT24, DataType.UINT24, DataType.INT32, DataType.UINT32, DataType.INT64,
    DataType.UINT64, DataType.FLOAT, DataType.DOUBLE, DataType.STRING,
)
"""Types a parameter may declare (the value a caller passes is checked against it)."""


class ActionParameter(Model):
    """One parameter: the item it sets, its type, whether it is required, its default
    and bounds."""

    _where: ClassVar[str] = "actions[].parameters[]"
    _max_lengths: ClassVar[dict[str, int]] = {"name": MAX_NAME, "item": MAX_NAME}
    _extra_keys: ClassVar[tuple[str, ...]] = NG_PARAMETER_KEYS

    name: str
    item: str
    data_type: DataType | None = None
    required: bool | None = None
    default_value: Any = None
    min_value: float | None = None
    max_value: float | None = None
    description: str = ""

    @model_validator(mode="before")
    @classmethod
    def _ng(cls, data: Any) -> Any:
        if isinstance(data, dict):
            return ng_action_parameter(cls.normalize_keys(data, cls._where))
        return data

    @field_validator("name", "item")
    @classmethod
    def _text(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be empty")
        return value

    @field_validator("data_type", mode="before")
    @classmethod
    def _type(cls, value: Any) -> Any:
        if value is None or (isinstance(value, str) and not value.strip()):
            return None
        found = DataType.parse(value) if isinstance(value, str) else value
        if found not in PARAMETER_TYPES:
            raise ValueError(f"{found.value} is not a parameter type (use one of "
                             f"{', '.join(t.value for t in PARAMETER_TYPES)})")
        return found

    @field_validator("min_value", "max_value")
    @classmethod
    def _bound(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @property
    def is_required(self) -> bool:
        """Required unless it has a default (NG's ``required``, when given, wins)."""
        return self.default_value is None if self.required is None else self.required


ACTION_QUANTITY: dict[int, int] = {5: MAX_WRITE_BITS, 15: MAX_WRITE_BITS, 6: MAX_WRITE_REGISTERS,
                                   16: MAX_WRITE_REGISTERS}
"""Most coils/registers an address action (NG's ``address`` + ``quantity``) writes: one
FC15/FC16 request's (MODBUS Application Protocol v1.1b3, 6.11, 6.12); FC05/FC06 send one
request per coil/register, bounded alike."""

ACTION_VALUE = "value"
"""The run-time parameter of an address action: the coils or registers to write."""


class DeviceAction(Model):
    """A named group of writes: its function code and parameters, or (NG's form) its
    function code, ``address`` and ``quantity``, the value given when it runs."""

    _where: ClassVar[str] = "actions[]"
    _max_lengths: ClassVar[dict[str, int]] = {"name": MAX_NAME}
    _extra_keys: ClassVar[tuple[str, ...]] = NG_ACTION_KEYS

    name: str
    function_code: int = 16
    parameters: list[ActionParameter] = Field(default_factory=list)
    # NG's form: the first coil/register (protocol, 0-based) and how many; the value is
    # given when the action runs (parameter "value")
    address: Annotated[int | None, Range(0, MAX_OFFSET)] = None
    quantity: Annotated[int | None, Range(1, max(ACTION_QUANTITY.values()))] = None
    command: str = ""
    description: str = ""

    @model_validator(mode="before")
    @classmethod
    def _ng(cls, data: Any) -> Any:
        if isinstance(data, dict):
            return ng_action(cls.normalize_keys(data, cls._where))
        return data

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("an action needs a non-empty name")
        return value

    @field_validator("function_code", mode="before")
    @classmethod
    def _function(cls, value: Any) -> Any:
        code = function_code(value)
        if code not in ACTION_FUNCTIONS:
            raise ValueError(f"use {_FUNCTION_NAMES}")
        return code

    @model_validator(mode="after")
    def _address_form(self) -> DeviceAction:
        if self.address is None:
            if self.quantity is not None:
                raise ValueError("quantity goes with address (NG's form: functionCode, "
                                 "address, quantity; the value is given when it runs)")
            return self
        if self.parameters:
            raise ValueError("give address (NG's form: the value is given when it runs) or "
                             "parameters (each sets an item), not both")
        count = self.count
        most = ACTION_QUANTITY[self.function_code]
        if count > most:
            raise ValueError(f"quantity {count}: functionCode {self.function_code} writes at "
                             f"most {most} {'coils' if self.area.is_bit else 'registers'}")
        if self.address + count > MAX_OFFSET + 1:
            raise ValueError(f"address {self.address} + quantity {count} runs past "
                             f"{MAX_OFFSET}, the last address")
        return self

    @property
    def area(self) -> Area:
        return ACTION_FUNCTIONS[self.function_code][0]

    @property
    def count(self) -> int:
        """Coils or registers an address action writes (quantity, default 1)."""
        return 1 if self.quantity is None else self.quantity


def validate_actions(actions: Sequence[DeviceAction], items: Sequence[ParsedItem]) -> None:
    """Check the actions against the parsed address list: unique names, every parameter's
    item present, in the area of the action's function code, a whole coil or register
    item (not a bit of a register), written once per action; bounds in order; defaults
    of the parameter's type.  Raises one ConfigError listing every problem."""
    problems: list[Problem] = []
    by_name = {p.name: p for p in items}
    seen: dict[str, int] = {}
    for i, action in enumerate(actions):
        path = f"actions[{i}]"
        if action.name in seen:
            problems.append(Problem(f"{path}.name", action.name,
                                    f"duplicate action name (also actions[{seen[action.name]}])"))
        seen.setdefault(action.name, i)
        if not action.parameters and action.address is None:
            problems.append(Problem(f"{path}.parameters", NO_VALUE,
                                    "an action needs at least one parameter, or an address "
                                    "(NG's form: functionCode, address, quantity)"))
        names: dict[str, int] = {}
        targets: dict[str, int] = {}
        fc = action.function_code
        area = action.area
        for k, param in enumerate(action.parameters):
            where = f"{path}.parameters[{k}]"
            if param.name in names:
                first = names[param.name]
                problems.append(Problem(f"{where}.name", param.name,
                                        f"duplicate parameter (also parameters[{first}])"))
            names.setdefault(param.name, k)
            if param.item in targets:
                problems.append(Problem(f"{where}.item", param.item,
                                        f"already set by parameters[{targets[param.item]}]"))
            targets.setdefault(param.item, k)
            parsed = by_name.get(param.item)
            if parsed is None:
                problems.append(Problem(f"{where}.item", param.item,
                                        "no item of that name in the address list"))
                continue
            if parsed.address.area is not area:
                problems.append(Problem(
                    f"{where}.item", param.item,
                    f"is {parsed.item.address} ({parsed.address.area.short_name}), but "
                    f"functionCode {fc} writes {'coils' if area.is_bit else 'holding registers'}"))
                continue
            if parsed.address.bit is not None:
                problems.append(Problem(
                    f"{where}.item", param.item,
                    f"is a bit of a register ({parsed.item.address}): an action writes whole "
                    "registers; write the bit with write_address"))
                continue
            if (param.min_value is not None and param.max_value is not None
                    and param.min_value > param.max_value):
                problems.append(Problem(f"{where}.minValue", param.min_value,
                                        f"is above maxValue {param.max_value}"))
            if param.default_value is not None:
                kind = param.data_type or parsed.converted_type or (
                    DataType.DOUBLE if parsed.multiplier != 1 and parsed.data_type.is_numeric
                    else parsed.data_type)
                try:
                    normalize_value("defaultValue", kind, param.default_value)
                except ValueError as exc:
                    problems.append(Problem(f"{where}.defaultValue", param.default_value,
                                            str(exc).removeprefix("defaultValue: ")))
    if problems:
        raise ConfigError(problems)
