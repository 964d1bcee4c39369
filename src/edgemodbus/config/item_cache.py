"""The address lists of device files loaded before, by their JSON: a gateway folder of
5,000 files made from one template validates the list's items once (pydantic, keys)
and gives every other file fresh items equal to them (docs/scale.md, "Starting
thousands of devices").

Only what came from JSON text is looked up (a file, or a str of JSON): its values are
plain JSON values, so the list's JSON text (NaN and Infinity written as such, keys in
their order) is the whole input of the items' validation, and an equal text gives
equal items.  Lists from Python objects (a dict handed to ``load_device_config``) are
validated as they are.  A list is kept only once its file loaded without a problem and
without an unknown key in its items (a later file with the same list would not be told
them); its items were unread (no ``value`` or ``status`` in the file).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

from ..codec.shared import SharedCache
from .item_model import UNREAD, DeviceAddressItem

MAX_KEY_CHARS = 1 << 18
"""The longest list text kept (about 1,000 items; at most 16 lists are kept): a larger
list is validated each time."""

_LISTS: SharedCache[tuple[DeviceAddressItem, ...]] = SharedCache(keep=16, weak=False)

# set while a device file's JSON text is loaded (load_device_config)
_from_json: ContextVar[bool] = ContextVar("edgemodbus_items_from_json", default=False)
# the key of the list of the load under way, kept by its after-validator (device.py)
_pending: ContextVar[str | None] = ContextVar("edgemodbus_items_pending", default=None)


@contextmanager
def json_source(from_json: bool) -> Iterator[None]:
    """While a device file is loaded: whether its data is decoded JSON text."""
    token = _from_json.set(from_json)
    pending = _pending.set(None)
    try:
        yield
    finally:
        _pending.reset(pending)
        _from_json.reset(token)


def list_key(items: list[Any]) -> str | None:
    """The key of a raw ``addressList`` of JSON text, None when it is not looked up."""
    if not _from_json.get():
        return None
    try:
        key = json.dumps(items, ensure_ascii=False, separators=(",", ":"))
    except (TypeError, ValueError):
        return None
    return key if len(key) <= MAX_KEY_CHARS else None


def cached_items(key: str) -> list[DeviceAddressItem] | None:
    """Fresh items equal to those of the list validated under ``key``, or None."""
    protos = _LISTS.peek(key)
    if protos is None:
        return None
    return [proto.model_copy() for proto in protos]


def expect(key: str | None) -> None:
    """The list of the load under way is ``key``'s (None: not to be kept)."""
    _pending.set(key)


def keep(items: Sequence[DeviceAddressItem]) -> None:
    """The load under way validated ``items`` (its whole file is valid): keep unbound
    copies of them under the key :func:`expect` was given, if the items are unread."""
    key = _pending.get()
    if key is None:
        return
    _pending.set(None)
    if all(item.reading is UNREAD for item in items):
        _LISTS.get(key, lambda: tuple(item.model_copy() for item in items))
