"""DeviceAddressItem: one tag's configuration, compact, with its runtime state read from
the store of the driver that polls it.

A gateway holds one item per tag, so an item is small: its name, address and description
in slots of their own, every other config field in one tuple shared by the items of one
kind (:data:`CONF_FIELDS`, interned), and where its state is.  Its ``value``,
``status``, ``update_ts`` and ``error_reason`` are not the item's: the line worker writes
them into the poller's store (poll/store.py), and the item reads them there (``_store``
and ``_index``).  An item no driver polls yet keeps them in one :class:`ItemReading`
(``_store`` None, ``_index`` the reading): what the file gave, or the last state of the
driver that bound it.  :attr:`DeviceAddressItem.reading` reads the four at once,
consistently (docs/item-store.md).

Validation is :class:`~edgemodbus.config.item_fields.ItemFields`' (pydantic); this class
keeps the BaseModel methods hosts use (``model_validate``, ``model_fields``,
``model_dump``, ``model_copy``, ``to_dict``).  Config fields may be assigned, unvalidated
(``validate_items`` checks them again); so may the runtime fields: the compatibility path
of hosts that build items by hand, a polled item's next read overwrites them.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from datetime import datetime
from typing import Any, ClassVar, Generic, NamedTuple, Protocol, TypeVar, overload

from pydantic import GetCoreSchemaHandler
from pydantic.fields import FieldInfo
from pydantic_core import CoreSchema, core_schema

from ..datatypes import DataFormat, DataFormat64, DataType, ItemStatus
from .item_fields import ItemFields


class ItemReading(NamedTuple):
    """An item's runtime state read at one moment (never a value of one read with the
    status of another)."""

    value: Any
    status: ItemStatus
    update_ts: datetime | None
    error_reason: str | None


UNREAD = ItemReading(None, ItemStatus.UNKNOWN, None, None)
STATUSES = (ItemStatus.UNKNOWN, ItemStatus.OK, ItemStatus.INVALID)
"""The statuses by their code in a store's status array."""


class ValueStore(Protocol):
    """Where a polled item's state is (poll/store.py's ItemStore, as config sees it):
    parallel arrays by index."""

    values: list[Any]
    status: bytearray
    """codes into :data:`STATUSES`"""
    marks: list[tuple[datetime | None, str | None]]
    """(update time, error reason): one pair shared by the items set together"""

    def reading(self, index: int) -> ItemReading: ...
    def assign(self, index: int, which: int, value: Any) -> None: ...


CONF_FIELDS = ("device_data_type", "converted_data_type", "data_multiplier", "unit",
               "is_enable", "address_changed", "data_format", "byte_swap16", "data_format64",
               "quantity", "deadband", "encoding", "read_cycle", "report_mode", "report_every",
               "offset", "raw_min", "raw_max", "eng_min", "eng_max", "clamp", "scale_factor")
"""The config fields kept in the shared tuple, in its order."""
RUNTIME_FIELDS = ItemReading._fields
_OWN_FIELDS = ("name", "address", "description")

_CONFS: dict[tuple[Any, ...], tuple[Any, ...]] = {}
_MAX_CONFS = 4096


def _shared(conf: tuple[Any, ...]) -> tuple[Any, ...]:
    """``conf`` as the one tuple every item of that kind holds (an economy: forgotten
    past :data:`_MAX_CONFS` kinds)."""
    key = (conf, tuple(map(type, conf)))  # 1 == 1.0 == True: kept apart by type
    found = _CONFS.get(key)
    if found is None:
        if len(_CONFS) >= _MAX_CONFS:
            _CONFS.clear()
        found = _CONFS[key] = conf
    return found


def _is_unread(reading: tuple[Any, ...]) -> bool:
    return all(x is y for x, y in zip(reading, UNREAD, strict=True))


MOVING: Any = object()
"""An item's ``_store`` while a store binds it (see DeviceAddressItem.bound)."""

T = TypeVar("T")


class _Conf(Generic[T]):
    """A config field kept in the item's shared tuple."""

    __slots__ = ("at",)

    def __init__(self, at: int) -> None:
        self.at = at

    @overload
    def __get__(self, item: None, owner: type) -> _Conf[T]: ...
    @overload
    def __get__(self, item: DeviceAddressItem, owner: type) -> T: ...
    def __get__(self, item: DeviceAddressItem | None, owner: type) -> T | _Conf[T]:
        if item is None:
            return self
        value: T = item._conf[self.at]
        return value

    def __set__(self, item: DeviceAddressItem, value: T) -> None:
        conf = item._conf
        item._conf = _shared((*conf[:self.at], value, *conf[self.at + 1:]))


class _Runtime(Generic[T]):
    """A runtime field (ItemReading's ``at``): read from the item's store (its values,
    status codes or marks) or, unbound, from its own reading."""

    __slots__ = ("at",)

    def __init__(self, at: int) -> None:
        self.at = at

    @overload
    def __get__(self, item: None, owner: type) -> _Runtime[T]: ...
    @overload
    def __get__(self, item: DeviceAddressItem, owner: type) -> T: ...
    def __get__(self, item: DeviceAddressItem | None, owner: type) -> T | _Runtime[T]:
        if item is None:
            return self
        while True:  # the store and the index of one binding (see bound())
            store = item._store
            index = item._index
            if store is item._store and store is not MOVING:
                break
        if store is None:
            own: T = index[self.at]
            return own
        at = self.at
        if at == 0:
            value: T = store.values[index]
            return value
        if at == 1:
            return STATUSES[store.status[index]]  # type: ignore[return-value]
        mark: T = store.marks[index][at - 2]
        return mark

    def __set__(self, item: DeviceAddressItem, value: T) -> None:
        store, index = item.bound()
        if store is None:
            item._index = item._index._replace(**{RUNTIME_FIELDS[self.at]: value})
        else:
            store.assign(index, self.at, value)


class DeviceAddressItem:
    """One tag (the seed's fields, see :class:`ItemFields` for each): its configuration,
    and its runtime state read from the store of the driver polling it."""

    __slots__ = ("_conf", "_index", "_store", "address", "description", "name")

    model_fields: ClassVar[dict[str, FieldInfo]] = ItemFields.model_fields

    name: str
    address: str
    description: str
    _conf: tuple[Any, ...]
    _store: Any  # a ValueStore, None (unbound), or MOVING while a store binds it
    _index: Any  # the store's index, or (unbound) the item's own ItemReading

    device_data_type = _Conf[DataType](0)
    converted_data_type = _Conf[DataType | None](1)
    data_multiplier = _Conf[float](2)
    unit = _Conf[str](3)
    is_enable = _Conf[bool](4)
    address_changed = _Conf[bool](5)
    data_format = _Conf[DataFormat | None](6)
    byte_swap16 = _Conf[bool | None](7)
    data_format64 = _Conf[DataFormat64 | None](8)
    quantity = _Conf[int | None](9)
    deadband = _Conf[float | None](10)
    encoding = _Conf[str | None](11)
    read_cycle = _Conf[int | None](12)
    report_mode = _Conf[str | None](13)  # docs/reporting.md
    report_every = _Conf[int | None](14)
    offset = _Conf[float](15)  # docs/engineering-units.md
    raw_min = _Conf[float | None](16)
    raw_max = _Conf[float | None](17)
    eng_min = _Conf[float | None](18)
    eng_max = _Conf[float | None](19)
    clamp = _Conf[bool](20)
    scale_factor = _Conf[str | None](21)

    value = _Runtime[Any](0)
    status = _Runtime[ItemStatus](1)
    update_ts = _Runtime[datetime | None](2)
    error_reason = _Runtime[str | None](3)

    def __init__(self, **data: Any) -> None:
        """Keys in any spelling the device file takes; raises a ValidationError (a
        ValueError) naming the field."""
        self._take(ItemFields.model_validate(data))

    def _take(self, fields: ItemFields) -> None:
        self.name = fields.name
        self.address = fields.address
        self.description = fields.description
        self._conf = _shared(tuple(getattr(fields, f) for f in CONF_FIELDS))
        self._store = None
        reading = (fields.value, fields.status, fields.update_ts, fields.error_reason)
        # the usual item has never been read: one shared reading (the tuple is 80 bytes)
        self._index = UNREAD if _is_unread(reading) else ItemReading(*reading)

    @classmethod
    def of(cls, fields: ItemFields) -> DeviceAddressItem:
        """The item of validated ``fields``."""
        item = cls.__new__(cls)
        item._take(fields)
        return item

    @property
    def reading(self) -> ItemReading:
        """value, status, update_ts and error_reason at one moment, from any thread."""
        store, index = self.bound()
        reading: ItemReading = index if store is None else store.reading(index)
        return reading

    def bound(self) -> tuple[ValueStore | None, Any]:
        """(store, index) of one binding, or (None, the item's own reading).  A store
        rebinding the item sets ``_store`` to :data:`MOVING`, then the index, then
        itself: a reader that saw the same store before and after the index has the
        index of that store (never the new index into the old store)."""
        while True:
            store = self._store
            index = self._index
            if store is self._store and store is not MOVING:
                return store, index

    # -- the BaseModel methods -----------------------------------------------------------
    @classmethod
    def model_validate(cls, obj: Any) -> DeviceAddressItem:
        return obj if isinstance(obj, cls) else cls.of(ItemFields.model_validate(obj))

    @classmethod
    def key_table(cls) -> dict[str, str]:
        return ItemFields.key_table()

    @classmethod
    def normalize_keys(cls, data: Mapping[Any, Any], where: str,
                       prefix: str = "") -> dict[str, Any]:
        return ItemFields.normalize_keys(data, where, prefix)

    def fields(self) -> ItemFields:
        """The item as its (unvalidated) fields model, with its current reading."""
        values: dict[str, Any] = {f: getattr(self, f) for f in _OWN_FIELDS}
        values.update(zip(CONF_FIELDS, self._conf, strict=True))
        values.update(self.reading._asdict())
        return ItemFields.model_construct(**values)

    def model_dump(self, **kwargs: Any) -> dict[str, Any]:
        return self.fields().model_dump(**kwargs)

    def to_dict(self) -> dict[str, Any]:
        """camelCase, JSON-able dict (loads back to an equal item)."""
        return self.model_dump(mode="json", by_alias=True)

    def model_copy(self, *, update: Mapping[str, Any] | None = None,
                   deep: bool = False) -> DeviceAddressItem:
        """An unbound copy (deep: of the value too) with the current reading; ``update``
        sets attributes, unvalidated (as BaseModel.model_copy)."""
        copied = DeviceAddressItem.__new__(DeviceAddressItem)
        copied.name, copied.address, copied.description = self.name, self.address, \
            self.description
        copied._conf, copied._store = self._conf, None
        reading = self.reading
        copied._index = copy.deepcopy(reading) if deep else reading
        for name, value in (update or {}).items():
            setattr(copied, name, value)
        return copied

    def __copy__(self) -> DeviceAddressItem:
        return self.model_copy()

    def __deepcopy__(self, memo: dict[int, Any]) -> DeviceAddressItem:
        return self.model_copy(deep=True)

    def __reduce__(self) -> tuple[Any, ...]:
        return DeviceAddressItem.model_validate, (self.model_dump(),)

    def _key(self) -> tuple[Any, ...]:
        return (self.name, self.address, self.description, self._conf, self.reading)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DeviceAddressItem):
            return NotImplemented
        return self._key() == other._key()

    __hash__ = None  # type: ignore[assignment]  # mutable, as the dataclass it replaces

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in self.fields())
        return f"DeviceAddressItem({fields})"

    @classmethod
    def __get_pydantic_core_schema__(cls, source: Any,
                                     handler: GetCoreSchemaHandler) -> CoreSchema:
        """In a model (DeviceConfig.address_list): validated by ItemFields, an item
        taken as it is; dumped as its fields."""

        def build(data: Any, validate: core_schema.ValidatorFunctionWrapHandler) -> Any:
            return data if isinstance(data, cls) else cls.of(validate(data))

        def dump(item: DeviceAddressItem, info: core_schema.SerializationInfo) -> Any:
            return item.model_dump(mode=info.mode, by_alias=info.by_alias)

        return core_schema.no_info_wrap_validator_function(
            build, handler.generate_schema(ItemFields),
            serialization=core_schema.plain_serializer_function_ser_schema(
                dump, info_arg=True))
