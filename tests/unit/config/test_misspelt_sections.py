"""A misspelt key is an error in every config section, the newer ones too (#24 "A typo in
a key changes values silently").

The sections are found by walking the config models from the two files' roots (the
device file's DeviceConfig, the gateway file's GatewayConfig): every field whose type is
a section (a model with a key table, alone, optional or in a list) is a section at that
path.  For every key of every section (fields and the compatibility aliases of
config/keys.py's tables, which key_table() holds), each one-edit typo that is no known
key of any section and no UI key is loaded at its path through the file's own loader;
the error must name the section's path, the typo and "did you mean <a key of that
section>?".  A section added later without the check fails here without a new line in
this file.  UI keys stay warnings (test_config_limits.py checks the seed's).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, DeviceConfig, load_device_config
from edgemodbus.config.base import KeyRules
from edgemodbus.config.compat import norm_key
from edgemodbus.config.item_model import DeviceAddressItem
from edgemodbus.config.keys import UI_KEYS, allowed_distance
from edgemodbus.gateway.config import GatewayConfig, load_gateway_config

Section = tuple[str, type, Callable[[dict[str, Any]], object]]


def _sections_in(annotation: Any) -> Iterator[tuple[type, bool]]:
    """The section classes an annotation holds, and whether each sits in a list."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        yield from _sections_in(typing.get_args(annotation)[0])
    elif origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            yield from _sections_in(arg)
    elif origin in (list, tuple):
        for arg in typing.get_args(annotation):
            for cls, _ in _sections_in(arg):
                yield cls, True
    elif isinstance(annotation, type) and hasattr(annotation, "key_table"):
        yield annotation, False


def walk(root: type, load: Callable[[dict[str, Any]], object]) -> list[Section]:
    """(path, class, loader) of every section under ``root``; a list's section has the
    path ``key[0]``."""
    found: list[Section] = [("", root, load)]
    todo: list[tuple[str, type]] = [("", root)]
    while todo:
        path, cls = todo.pop()
        for name, field in getattr(cls, "model_fields", {}).items():
            for sub, listed in _sections_in(field.annotation):
                key = (field.alias or name) + ("[0]" if listed else "")
                sub_path = f"{path}.{key}" if path else key
                found.append((sub_path, sub, load))
                todo.append((sub_path, sub))
    return found


def _load_device(data: dict[str, Any]) -> object:
    return load_device_config(data)


def _load_gateway(data: dict[str, Any]) -> object:
    return load_gateway_config(data)


SECTIONS = walk(DeviceConfig, _load_device) + walk(GatewayConfig, _load_gateway)


def _every_key() -> frozenset[str]:
    """Every section's keys (normalised) and the UI keys: an edit that lands on one of
    them is no typo of the key it came from."""
    keys = set(UI_KEYS) | set(DeviceAddressItem.key_table())
    todo: list[type] = [KeyRules]
    while todo:
        cls = todo.pop()
        todo += cls.__subclasses__()
        if getattr(cls, "model_fields", None):
            keys |= set(cls.key_table())  # type: ignore[attr-defined]
    return frozenset(keys)


EVERY_KEY = _every_key()


def test_the_walk_finds_the_sections_added_after_the_did_you_mean_work() -> None:
    paths = {path for path, _, _ in SECTIONS}
    for expected in ("communication", "addressList[0]", "actions[0].parameters[0]",
                     "mqtt", "mqtt.tls", "mqtt.storeAndForward", "mqtt.sparkplug",
                     "serve", "serve.units[0]", "metrics", "console", "console.users[0]",
                     "console.tls", "fleet", "fleet.lease"):
        assert expected in paths, sorted(paths)
    comm = DeviceConfig.model_fields["communication"].annotation
    table = comm.key_table()  # type: ignore[union-attr]
    for key in ("engine", "loopThreads", "reportMode", "reportEvery", "alternates",
                "connections", "failoverAfter"):
        assert norm_key(key) in table, key
    item_table = DeviceAddressItem.key_table()
    for key in ("offset", "rawMin", "rawMax", "engMin", "engMax", "scaleFactor",
                "byteSwap16", "dataFormat64"):
        assert norm_key(key) in item_table, key


def one_edit(word: str, at: int, edit: str, letter: str) -> str:
    at = min(at, len(word) - 1)
    if edit == "drop":
        return word[:at] + word[at + 1:]
    if edit == "double":
        return word[:at] + word[at] + word[at:]
    if edit == "change":
        return word[:at] + letter + word[at + 1:]
    if edit == "insert":
        return word[:at] + letter + word[at:]
    at = min(at, len(word) - 2)
    return word[:at] + word[at + 1] + word[at] + word[at + 2:]


def placed(path: str, key: str) -> dict[str, Any]:
    """A file with ``{key: 1}`` at the section ``path`` (lists as one element)."""
    value: Any = {key: 1}
    for part in reversed([p for p in path.split(".") if p]):
        name, listed, _ = part.partition("[0]")
        value = {name: [value] if listed else value}
    return value  # type: ignore[no-any-return]


def check_typo(path: str, cls: type, load: Callable[[dict[str, Any]], object],
               typo: str) -> None:
    table: dict[str, str] = cls.key_table()  # type: ignore[attr-defined]
    with pytest.raises(ConfigError) as info:
        load(placed(path, typo))
    where = f"{path}.{typo}" if path else typo
    lines = [str(p) for p in info.value.problems]
    meant = [line for line in lines if line.startswith(f"{where}: unknown key: did you mean ")]
    assert meant, (path, typo, lines)
    named = meant[0].split("did you mean ", 1)[1].split("?", 1)[0]
    assert norm_key(named) in table, (path, typo, named)


KEYS = [(path, cls, load, key) for path, cls, load in SECTIONS
        for key in sorted(cls.key_table()) if allowed_distance(key) >= 1]  # type: ignore[attr-defined]


@settings(max_examples=400, deadline=None)
@given(case=st.sampled_from(KEYS), at=st.integers(0, 40),
       edit=st.sampled_from(["drop", "double", "change", "insert", "swap"]),
       letter=st.sampled_from("abcdefghijklmnopqrstuvwxyz0123456789"))
def test_a_one_edit_typo_of_any_key_of_any_section_is_an_error(
        case: tuple[str, type, Callable[[dict[str, Any]], object], str], at: int, edit: str,
        letter: str) -> None:
    path, cls, load, key = case
    typo = one_edit(key, at, edit, letter)
    if typo == key or typo in EVERY_KEY or len(typo) < 3:
        return
    check_typo(path, cls, load, typo)


@pytest.mark.parametrize(("path", "typo", "meant"), [
    ("fleet", "instanceI", "instanceId"),
    ("fleet", "loadBalancer", "loadBalancers"),
    ("fleet.lease", "leaseM", "leaseMs"),
    ("console", "maxConection", "maxConnections"),
    ("mqtt.tls", "caFiel", "caFile"),
    ("serve.units[0]", "unitdI", "unitId"),
    ("communication", "engnie", "engine"),
    ("communication", "loopThread", "loopThreads"),
    ("communication", "reportEvry", "reportEvery"),
    ("communication", "connectons", "connections"),
    ("communication", "alternate", "alternates"),
    ("addressList[0]", "rawMn", "rawMin"),
    ("addressList[0]", "ofset", "offset"),
    ("addressList[0]", "scaleFacter", "scaleFactor"),
])
def test_the_newer_keys_by_hand(path: str, typo: str, meant: str) -> None:
    device = path.split(".")[0] in ("communication", "addressList[0]")
    load = _load_device if device else _load_gateway
    with pytest.raises(ConfigError) as info:
        load(placed(path, typo))
    assert f"{path}.{typo}: unknown key: did you mean {meant}?" in str(info.value)
