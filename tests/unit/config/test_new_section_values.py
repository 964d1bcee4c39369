"""The config values of the surfaces that came after issue #25 (docs/fault-checklist.md
"Config values of the fleet, console and loop engine"): ``fleet`` and ``fleet.lease``,
``console``, a device's ``engine`` and ``loopThreads``.  Property: any JSON value for one
of them (huge, tiny, NaN, text, true, nested lists and objects) is either taken as
exactly what the field allows, or refused with a ConfigError naming the field, the value
(a secret: not shown) and what is allowed; never another exception."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, load_device_config
from edgemodbus.config.limits import MAX_TEXT
from edgemodbus.gateway.config import load_gateway_config

LEASE = {"url": "redis://127.0.0.1:6379/0", "leaseMs": 6000}
DTU = {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1", "listenPort": 9502,
       "dtuId": "861234567890123", "registration": "regex",
       "registrationPattern": r"ID:(\d+)"}


def whole(lo: int, hi: int, optional: bool = False) -> Callable[[Any], bool]:
    """A whole number lo..hi (JSON integer, integral float or numeric text, not a bool);
    null too for an ``optional`` field (left out)."""
    def ok(value: Any) -> bool:
        if value is None:
            return optional
        if isinstance(value, str):
            try:
                value = float(value.strip())
            except ValueError:
                return False
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        return math.isfinite(value) and float(value).is_integer() and lo <= value <= hi
    return ok


# (path of the field, a document with value v there, what the field allows)
NUMERIC: list[tuple[str, Callable[[Any], dict[str, Any]], Callable[[Any], bool]]] = [
    ("fleet.lease.leaseMs", lambda v: {"fleet": {"lease": {**LEASE, "leaseMs": v}}},
     whole(1000, 600_000)),
    ("fleet.lease.renewMs", lambda v: {"fleet": {"lease": {**LEASE, "renewMs": v}}},
     whole(100, 2000, optional=True)),
    ("fleet.lease.marginMs", lambda v: {"fleet": {"lease": {**LEASE, "marginMs": v}}},
     whole(0, 3000, optional=True)),
    ("console.port", lambda v: {"console": {"port": v}}, whole(0, 65535)),
    ("console.maxStreams", lambda v: {"console": {"maxStreams": v, "maxConnections": 4096}},
     whole(1, 1000)),
    ("console.maxConnections", lambda v: {"console": {"maxConnections": v, "maxStreams": 1}},
     whole(2, 4096)),
    ("communication.loopThreads", lambda v: {"communication": {**DTU, "loopThreads": v}},
     whole(1, 1024, optional=True)),
]

json_scalars = st.one_of(
    st.none(), st.booleans(),
    st.integers(), st.integers(-2**70, 2**70), st.sampled_from([0, -1, 1, 10**12, 10**9]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20), st.sampled_from(["", "10", " 1500 ", "1e3", "x" * 5000]))
json_values = st.recursive(json_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=5), inner, max_size=3)),
    max_leaves=8)


def names(message: str, path: str) -> bool:
    """Whether ``message`` names the field at ``path``: "console.host '': ..." from the
    field's check, or "console: host '0' ..." from a check across the section's fields."""
    parent, _, key = path.rpartition(".")
    return path in message or f"{parent}: {key}" in message


def load(doc: dict[str, Any]) -> Any:
    """The gateway file or device file ``doc`` loaded as its JSON text."""
    if "communication" in doc:
        return load_device_config(doc)
    return load_gateway_config(json.dumps(doc, allow_nan=True))


def refused(doc: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as info:
        load(doc)
    return str(info.value)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(NUMERIC), json_values)
def test_a_numeric_field_takes_its_range_or_names_field_value_and_range(
        case: tuple[str, Callable[[Any], dict[str, Any]], Callable[[Any], bool]],
        value: Any) -> None:
    path, doc, allowed = case
    if allowed(value):
        load(doc(value))
        return
    message = refused(doc(value))
    assert names(message, path), message
    assert "must be" in message or "at most" in message, message


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(["fleet.instanceId", "fleet.loadBalancers", "fleet.lease.url",
                        "fleet.lease.keyPrefix", "console.host", "console.token",
                        "communication.engine"]), json_values)
def test_text_and_list_fields_refuse_with_the_field_and_never_raise_otherwise(
        path: str, value: Any) -> None:
    section, *rest = path.split(".")
    if section == "communication":
        doc: dict[str, Any] = {"communication": {**DTU, rest[0]: value}}
    elif rest[0] == "lease":
        doc = {"fleet": {"lease": {**LEASE, rest[1]: value}}}
    else:
        doc = {section: {rest[0]: value}}
    try:
        load(doc)
    except ConfigError as exc:
        assert names(str(exc), path), exc
        assert len(str(exc)) < 2000  # a value is shown shortened
        if path == "console.token" and isinstance(value, str) and len(value) >= 16:
            assert value not in str(exc)  # a secret is never shown


@pytest.mark.parametrize("path, doc", [
    ("console.token", {"console": {"token": "t" * (MAX_TEXT + 1)}}),
    ("fleet.lease.url", {"fleet": {"lease": {**LEASE, "url": "redis://" + "h" * 5000}}}),
    ("fleet.instanceId", {"fleet": {"instanceId": "i" * 100_000}}),
    ("fleet.loadBalancers", {"fleet": {"loadBalancers": ["10.0.0.1"] * 65}}),
])
def test_huge_values_are_refused_by_length(path: str, doc: dict[str, Any]) -> None:
    """A 30 MB secret was taken: the length check of strings runs after a secret is
    wrapped, and did not see it (config/secret.py checks it now)."""
    message = refused(doc)
    assert path in message and ("at most" in message or "characters" in message), message
    assert "t" * 100 not in message


@pytest.mark.parametrize("value", [True, False, 1.5, "1.5", [], {}, [[6000]], {"ms": 6000}])
def test_lease_times_refuse_true_and_nested_values(value: Any) -> None:
    """leaseMs true was taken as 1 (pydantic's bounds, not the config's Range); marginMs
    true was taken as 1 ms."""
    for key in ("leaseMs", "renewMs", "marginMs"):
        message = refused({"fleet": {"lease": {**LEASE, key: value}}})
        assert f"fleet.lease.{key}" in message and "must be a whole number" in message, \
            message


@pytest.mark.parametrize("host", ["", "   "])
def test_an_empty_console_host_is_refused_naming_the_field(host: str) -> None:
    """It was taken, and the console's start failed with getaddrinfo's "Name or service
    not known" (no field named)."""
    message = refused({"console": {"host": host}})
    assert message.startswith(f"console.host {host!r}: empty"), message
