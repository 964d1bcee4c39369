"""serve ``allowFrom`` (server and unit): IPv4 networks or addresses, normalised; a
bad entry names the field, the value and what is allowed."""

from __future__ import annotations

from typing import Any

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.serve import ServeSettings
from edgemodbus.serve.settings import ipv4_masks


def errors(data: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        ServeSettings.load(data)
    return [str(p) for p in info.value.problems]


def test_lists_are_normalised_and_become_address_mask_pairs() -> None:
    s = ServeSettings.load({"allowFrom": "10.0.0.0/8, 127.0.0.1", "units": [
        {"unitId": 1, "device": "m", "allowFrom": ["192.168.1.0/24"]}]})
    assert s.allow_from == ("10.0.0.0/8", "127.0.0.1/32")
    assert s.units[0].allow_from == ("192.168.1.0/24",)
    assert ipv4_masks(s.allow_from) == [(0x0A000000, 0xFF000000), (0x7F000001, 0xFFFFFFFF)]


@pytest.mark.parametrize(("value", "error"), [
    (["10.0.0.300/8"], "serve.allowFrom[0] '10.0.0.300/8': must be an IPv4 or IPv6 network "
     "in CIDR notation or a single address, e.g. 10.0.0.0/8, 192.168.1.7, 2001:db8::/32"),
    (["10.0.0.1/8"], "serve.allowFrom[0] '10.0.0.1/8': has host bits set: use 10.0.0.0/8, "
     "or the single address 10.0.0.1"),
    (["127.0.0.1", "fd00::/8"], "serve.allowFrom[1] 'fd00::/8': the server listens on IPv4 "
     "only: use IPv4 networks or addresses, e.g. 10.0.0.0/8, 192.168.1.7"),
])
def test_bad_entries_are_named(value: Any, error: str) -> None:
    assert errors({"allowFrom": value}) == [error]
    unit_error = error.replace("serve.allowFrom", "serve.units[0].allowFrom")
    assert errors({"units": [{"unitId": 1, "device": "m", "allowFrom": value}]}) == [unit_error]


def test_at_most_32_networks() -> None:
    nets = [f"10.0.{i}.0/24" for i in range(33)]
    problems = errors({"allowFrom": nets})
    assert len(problems) == 1 and problems[0].startswith("serve.allowFrom ")
    assert problems[0].endswith("at most 32 networks, not 33")
