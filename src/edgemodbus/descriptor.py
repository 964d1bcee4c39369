"""The driver descriptor (the seed's descriptor JSON), generated so that it cannot drift.

Parameters come from :class:`~edgemodbus.config.DriverModbusRtuParameter`'s fields
(their defaults, ranges, choices and descriptions; an allow-list is one text of networks
separated by commas, a secret's default is never shown) and their UI labels in
:mod:`edgemodbus.config.labels` (label, category, controlType, options, visibleWhen,
dataSource); ``addressParameter`` lists, the same way, the optional fields of an address
item (:class:`~edgemodbus.config.DeviceAddressItem`) that have labels there
(``ITEM_LABELS``: the item's scan rate, ``readCycle``; its engineering units keys,
``offset``, ``rawMin``..``engMax``, ``clamp``, ``scaleFactor``: docs/engineering-units.md).
The address regex and examples come from :mod:`edgemodbus.protocol.address`;
``presets`` lists the device templates on the search path (name, description, source:
:mod:`edgemodbus.config.templates`), which a device file names with ``"template"``.
"""

from __future__ import annotations

import enum
import types
import typing
from typing import Any, Literal

from pydantic import SecretStr
from pydantic.fields import FieldInfo

from .config import Choice, DeviceAddressItem, DriverModbusRtuParameter, Parity, Range
from .config.labels import ITEM_LABELS, LABELS
from .config.templates import find_templates
from .datatypes import Area, DataType
from .protocol.address import (
    Address,
    address_regex,
    check_base,
    check_prefix,
    format_entity,
    parse_address,
    type_number,
)

DRIVER_TYPE = "DriverModbusRtu"

EXAMPLE_KEYS: dict[str, Area] = {
    "coil": Area.COIL,
    "discreteInput": Area.DISCRETE_INPUT,
    "holdingRegister": Area.HOLDING_REGISTER,
    "inputRegister": Area.INPUT_REGISTER,
}

_AREA_TITLES = {
    Area.COIL: "Coil",
    Area.DISCRETE_INPUT: "Discrete Input",
    Area.HOLDING_REGISTER: "Holding Register",
    Area.INPUT_REGISTER: "Input Register",
}


def driver_descriptor(prefix: str = "function-code", base: int = 0) -> dict[str, Any]:
    """The descriptor JSON (a dict) for the address options ``prefix`` and ``base``."""
    prefix = check_prefix(prefix)
    base = check_base(base)
    return {
        "protocolCategory": "Generic",
        "driverType": DRIVER_TYPE,
        "description": "Modbus RTU driver (serial RTU, RTU over TCP, Modbus TCP)",
        "supportedDataTypes": [t.value for t in DataType],
        "addressRegex": address_regex(prefix, base),
        "supportsPresets": True,
        "presets": [t.summary() for t in find_templates()],
        "allowManualAddress": True,
        "hasBuiltInAddresses": False,
        "supportsDynamicBrowse": False,
        "addressList": [],
        "addressExamples": _examples(prefix, base),
        "parameter": parameters(prefix, base),
        "addressParameter": address_parameters(),
    }


def _examples(prefix: str, base: int) -> dict[str, str]:
    if prefix == "entity":
        return _entity_examples(base)
    examples = {key: f"{type_number(area, prefix)}:00001" for key, area in EXAMPLE_KEYS.items()}
    for key, area in EXAMPLE_KEYS.items():  # the examples must parse to their area
        if parse_address(examples[key], prefix, base).area is not area:
            raise RuntimeError(f"address example {key} {examples[key]!r} is not a {area}")
    numbering = " ".join(
        f"{type_number(area, prefix)}={_AREA_TITLES[area]}"
        for area in sorted(_AREA_TITLES, key=lambda a: type_number(a, prefix))
    )
    scheme = "按读功能码编号" if prefix == "function-code" else "Modicon 编号"
    offsets = "0..65535,协议地址(0 基)" if base == 0 else "1..65536,1 基(addressBase 1)"
    examples["note"] = (
        f"格式为 [<类型>:]<偏移>[.<位>],类型 {numbering}({scheme});"
        "也可写 coil/c、di/discreteinput、hr/holding、ir/input(不区分大小写),省略类型即 hr;"
        f"偏移为十进制 {offsets},可带前导零;.<位> (0..15) 仅用于 hr/ir 寄存器"
    )
    return examples


def _entity_examples(base: int) -> dict[str, str]:
    """addressPrefix entity: the first entity of each table, 6-digit form."""
    examples = {key: format_entity(Address(area, 0)) for key, area in EXAMPLE_KEYS.items()}
    for key, area in EXAMPLE_KEYS.items():  # the examples must parse to their area
        if parse_address(examples[key], "entity", base) != Address(area, 0):
            raise RuntimeError(f"address example {key} {examples[key]!r} is not a {area}")
    typed = "0..65535,协议地址(0 基)" if base == 0 else "1..65536,1 基(addressBase 1)"
    examples["note"] = (
        "Modicon 实体编号:首位为表 0=Coil 1=Discrete Input 3=Input Register "
        "4=Holding Register,其后为从 1 起的编号;五位 40001..49999 或六位 400001..465536"
        "(40001 与 400001 均为保持寄存器 0),不足五位为线圈(1 即 00001);"
        ".<位> (0..15) 仅用于 3/4 表;也可写 <类型>:<偏移>,类型按读功能码编号"
        f"(3=Holding Register,4=Input Register),偏移 {typed}"
    )
    return examples


def parameters(prefix: str = "function-code", base: int = 0) -> list[dict[str, Any]]:
    """One descriptor entry per communication parameter, in field order."""
    in_force: dict[str, Any] = {"addressPrefix": prefix, "addressBase": base}
    order: dict[str, int] = {}
    entries = []
    for name, field in DriverModbusRtuParameter.model_fields.items():
        ui = LABELS.get(name)
        if ui is None:
            raise TypeError(f"DriverModbusRtuParameter.{name}: no UI labels in config/labels.py")
        entries.append(_entry(name, field, ui, order, in_force))
    return entries


def address_parameters() -> list[dict[str, Any]]:
    """One descriptor entry per labelled field of an address item, in field order."""
    fields = DeviceAddressItem.model_fields
    for name in ITEM_LABELS:
        if name not in fields:
            raise TypeError(f"config/labels.py ITEM_LABELS: DeviceAddressItem has no field {name}")
    order: dict[str, int] = {}
    return [_entry(name, field, ITEM_LABELS[name], order, {})
            for name, field in fields.items() if name in ITEM_LABELS]


def _entry(
    name: str, field: FieldInfo, ui: dict[str, Any], order: dict[str, int],
    in_force: dict[str, Any],
) -> dict[str, Any]:
    """The descriptor entry of one model field (``order``: entries so far per category)."""
    key = field.alias or name
    category = str(ui["category"])
    order[category] = order.get(category, 0) + 1
    entry: dict[str, Any] = {
        "defaultValue": in_force.get(key, _ui_value(field.default)),
        "description": field.description or "",
        "label": ui["label"],
        "name": key,
        "orderNo": order[category],
        "type": ui.get("type") or _ui_type(field),
        "category": category,
        "controlType": ui["controlType"],
    }
    options = ui.get("options", _options(field))
    if options is not None:
        entry["options"] = options
    for meta in field.metadata:
        if isinstance(meta, Range):
            entry["min"] = _plain(meta.lo)
            if meta.hi is not None:
                entry["max"] = _plain(meta.hi)
    for extra in ("visibleWhen", "dataSource"):
        if extra in ui:
            entry[extra] = ui[extra]
    return entry


def _plain(x: float) -> int | float:
    return int(x) if float(x).is_integer() else x


def _ui_value(value: Any) -> Any:
    """A default as the UI shows it: parity as its number, an enum as its value, a list
    (the allow-lists: a text box) as one text separated by commas, a secret never."""
    if isinstance(value, SecretStr):
        return ""
    if isinstance(value, tuple):
        return ", ".join(str(v) for v in value)
    if isinstance(value, Parity):
        return value.number
    if isinstance(value, enum.Enum):
        return value.value
    return value


def _base_types(field: FieldInfo) -> list[Any]:
    annotation = field.annotation
    origin = typing.get_origin(annotation)
    if origin is typing.Union or origin is types.UnionType:
        return [a for a in typing.get_args(annotation) if a is not type(None)]
    return [annotation]


def _ui_type(field: FieldInfo) -> str:
    (kind,) = _base_types(field)
    if kind is bool:
        return "bool"
    if kind is int:
        return "int"
    if kind is float:
        return "double"
    return "string"


def _options(field: FieldInfo) -> list[Any] | None:
    for meta in field.metadata:
        if isinstance(meta, Choice):
            return list(meta.values)
    (kind,) = _base_types(field)
    if typing.get_origin(kind) is Literal:
        return list(typing.get_args(kind))
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        return [_ui_value(m) for m in kind]
    return None
