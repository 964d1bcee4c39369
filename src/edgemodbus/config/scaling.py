"""The engineering units keys of an item (docs/engineering-units.md): ``offset``,
``rawMin/rawMax/engMin/engMax`` with ``clamp``, and ``scaleFactor``, which names another
item of the same device: checked here across the address list, and the device's
:class:`ScaleFactors` table attached to the items that hold or use a factor."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Protocol, TypeVar

from ..codec import ScaleFactors, ValueSpec, check_spec
from ..datatypes import DataType
from ..protocol.address import Address
from .problems import Problem


class DeviceAddressItem(Protocol):
    """What this module reads of an item (config/items.py's DeviceAddressItem)."""

    @property
    def name(self) -> str: ...
    @property
    def address(self) -> str: ...
    @property
    def is_enable(self) -> bool: ...
    @property
    def data_multiplier(self) -> float: ...
    @property
    def offset(self) -> float: ...
    @property
    def raw_min(self) -> float | None: ...
    @property
    def raw_max(self) -> float | None: ...
    @property
    def eng_min(self) -> float | None: ...
    @property
    def eng_max(self) -> float | None: ...
    @property
    def clamp(self) -> bool: ...
    @property
    def scale_factor(self) -> str | None: ...


class ParsedItem(Protocol):
    """What this module reads of a parsed item (config/items.py's ParsedItem, a frozen
    dataclass with a ``factors`` field)."""

    @property
    def item(self) -> DeviceAddressItem: ...
    @property
    def address(self) -> Address: ...
    @property
    def data_type(self) -> DataType: ...
    @property
    def converted_type(self) -> DataType | None: ...
    @property
    def quantity(self) -> int | None: ...
    def value_spec(self, name: str | None = None) -> ValueSpec: ...


_P = TypeVar("_P", bound=ParsedItem)

__all__ = ["ScaleFactors", "link_scale_factors", "scaling_fields", "scaling_keys",
           "scaling_shape"]


def scaling_keys(item: DeviceAddressItem, factors: ScaleFactors | None) -> dict[str, Any]:
    """The ValueSpec arguments of ``item``'s scaling keys.  Without ``factors`` (the
    item checked alone, before the address list is) its scaleFactor is left out."""
    rr = er = None
    if item.raw_min is not None or item.raw_max is not None or item.eng_min is not None \
            or item.eng_max is not None:
        rr, er = (item.raw_min, item.raw_max), (item.eng_min, item.eng_max)
    keys: dict[str, Any] = {"offset": item.offset, "raw_range": rr, "eng_range": er,
                            "clamp": item.clamp}
    if factors is not None:
        keys["factors"] = factors
        if item.scale_factor is not None:
            keys["scale_factor"] = item.scale_factor
        if item.name in factors.names:
            keys["holds_factor"] = item.name
    return keys


def scaling_shape(item: DeviceAddressItem) -> tuple[Any, ...]:
    """What the item's scaling adds to the shape its spec is checked once per."""
    return (item.offset, item.raw_min, item.raw_max, item.eng_min, item.eng_max, item.clamp)


def scaling_fields(spec: ValueSpec) -> dict[str, tuple[str, Any]]:
    """check_spec's field words -> (the item's key, its value) for the scaling keys."""
    rr, er = spec.raw_range or (None, None), spec.eng_range or (None, None)
    return {
        "offset": ("offset", spec.offset),
        "rawMin/rawMax": ("rawMin", rr[0]),
        "engMin/engMax": ("engMin", er[0]),
        "rawMin": ("rawMin", rr[0]),
        "rawMax": ("rawMax", rr[1]),
        "engMin": ("engMin", er[0]),
        "engMax": ("engMax", er[1]),
        "clamp": ("clamp", spec.clamp),
        "scaleFactor": ("scaleFactor", spec.scale_factor),
    }


def _factor_problem(source: ParsedItem | None, name: str, disabled: bool) -> str | None:
    """Why the item named ``name`` cannot be a scale factor (None: it can)."""
    if source is None:
        return ("no item of that name in this device's addressList (allowed: the name of "
                "an Int16 item of the same device)" if not disabled else
                "that item is disabled (isEnable false): enable it or leave scaleFactor out")
    item = source.item
    if source.data_type is not DataType.INT16 or source.address.bit is not None or \
            source.quantity not in (None, 1) or source.address.area.is_bit:
        return (f"that item is {source.data_type.value} at {item.address}; a scale factor "
                "is an Int16 register (SunSpec sunssf)")
    if (item.scale_factor is not None or item.offset or item.raw_min is not None
            or item.raw_max is not None or item.data_multiplier != 1):
        return "that item is scaled itself; a scale factor item takes no scaling keys"
    if source.converted_type not in (None, DataType.INT16):
        return (f"that item has convertedDataType {source.converted_type.value}; a scale "
                "factor item keeps its Int16 value")
    return None


def link_scale_factors(
    parsed: list[_P], items: Sequence[DeviceAddressItem], problems: list[Problem]
) -> list[_P]:
    """Check every ``scaleFactor`` against the device's items (it names an enabled Int16
    item that is not scaled itself), then give the items that hold or use a factor the
    device's one table; appends a Problem per bad item."""
    users = [p for p in parsed if p.item.scale_factor is not None]
    if not users:
        return parsed
    by_name = {p.item.name: p for p in parsed}
    path_of = {id(item): f"addressList[{i}]" for i, item in enumerate(items)}
    disabled = {item.name for item in items if not item.is_enable}
    names: list[str] = []
    bad = False
    for p in users:
        name = p.item.scale_factor
        assert name is not None
        if not p.item.is_enable:
            continue  # not polled nor written: it needs no factor
        why = ("an item is not its own scale factor" if name == p.item.name
               else _factor_problem(None if name in disabled else by_name.get(name), name,
                                    name in disabled))
        if why is not None:
            problems.append(Problem(f"{path_of.get(id(p.item), 'addressList[]')}.scaleFactor",
                                    name, why))
            bad = True
            continue
        names.append(name)
    if bad or not names:
        return parsed
    factors = ScaleFactors(names)
    linked: list[_P] = []
    for p in parsed:
        if (p.item.is_enable and p.item.scale_factor in factors.names) or \
                p.item.name in factors.names:
            p = replace(p, factors=factors)  # type: ignore[type-var]
            spec = p.value_spec()
            try:
                check_spec(spec, p.address.area)
            except ValueError as exc:
                problems.append(Problem(path_of.get(id(p.item), "addressList[]"), p.item.name,
                                        str(exc)))
        linked.append(p)
    return linked
