"""The listen-port and DTU access keys (issue #14): defaults, limits, source allow-lists,
the registration key (a secret nowhere shown), their rules, and what the driver builds
from them for the listener (PortSettings, DtuAccess; no socket is opened here)."""

from __future__ import annotations

import json
import logging
import typing
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from edgemodbus.config import (
    ConfigError,
    DeviceConfig,
    DriverModbusRtuParameter,
    load_communication,
    load_device_config,
)
from edgemodbus.config.listen import KEY_EXAMPLE, key_bytes, network, networks
from edgemodbus.descriptor import driver_descriptor
from edgemodbus.driver import dtu_access, port_settings
from edgemodbus.line.registration import DUPLICATE_POLICIES, DtuAccess, PortSettings

SECRET = "Hunter2-s3cret"
PATTERN = r"ID:(\d+);KEY:(?P<key>\w+)"


def server(**extra: Any) -> dict[str, Any]:
    return {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
            "listenPort": 9502, "dtuId": "861234567890123", "registration": "regex",
            "registrationPattern": PATTERN, **extra}


def errors_of(comm: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": comm})
    return [str(p) for p in info.value.problems]


# ----------------------------------------------------------------------------- each key

# (key, attribute, default, a good value, a bad value, what the error says is allowed)
KEYS: list[tuple[str, str, Any, Any, Any, str]] = [
    ("registrationMaxBytes", "registration_max_bytes", 256, 1024, 0, "must be 1..65536"),
    ("registrationMaxBytes", "registration_max_bytes", 256, 65536, 65537, "must be 1..65536"),
    ("registrationByteRate", "registration_byte_rate", 1024, 0, -1, "must be 0..100000000"),
    ("registrationByteRate", "registration_byte_rate", 1024, 100_000_000, 100_000_001,
     "must be 0..100000000"),
    ("maxUnregistered", "max_unregistered", 512, 1, 0, "must be 1..1000000"),
    ("maxUnregistered", "max_unregistered", 512, 1_000_000, 1_000_001, "must be 1..1000000"),
    ("maxUnregisteredPerSource", "max_unregistered_per_source", 64, 8, 0,
     "must be 1..1000000"),
    ("idFlipLimit", "id_flip_limit", 5, 1000, 1001, "must be 1..1000"),
    ("idFlipLimit", "id_flip_limit", 5, 1, 0, "must be 1..1000"),
    ("idFlipWindow", "id_flip_window", 60000, 1, 0, "must be 1..86400000"),
    ("idFlipWindow", "id_flip_window", 60000, 86_400_000, 86_400_001, "must be 1..86400000"),
    ("duplicateId", "duplicate_id", "keep-existing", "replace", "first",
     "must be 'keep-existing' or 'replace'"),
    ("listenAllowFrom", "listen_allow_from", (), ["10.0.0.0/8"], ["10.0.0.0/33"],
     "must be an IPv4 or IPv6 network in CIDR notation or a single address"),
    ("dtuAllowFrom", "dtu_allow_from", (), ["2001:db8::/32"], ["2001:db8::/129"],
     "must be an IPv4 or IPv6 network in CIDR notation or a single address"),
]


@pytest.mark.parametrize(("key", "attr", "default", "good", "bad", "allowed"), KEYS)
def test_each_key_default_good_and_bad_value(key: str, attr: str, default: Any, good: Any,
                                             bad: Any, allowed: str) -> None:
    assert getattr(DriverModbusRtuParameter(), attr) == default
    loaded = getattr(DriverModbusRtuParameter.model_validate(server(**{key: good})), attr)
    assert loaded == (tuple(good) if isinstance(good, list) else good)
    (line,) = errors_of(server(**{key: bad}))
    shown = f"communication.{key}[0] {bad[0]!r}: " if isinstance(bad, list) \
        else f"communication.{key} {bad!r}: "
    assert line.startswith(shown + allowed), line


def test_the_registration_key_default_and_a_good_value() -> None:
    assert DriverModbusRtuParameter().registration_key.get_secret_value() == ""
    p = DriverModbusRtuParameter.model_validate(server(registrationKey=SECRET))
    assert isinstance(p.registration_key, SecretStr)
    assert p.registration_key.get_secret_value() == SECRET


def test_duplicate_id_is_one_of_the_listener_s_policies_in_any_case() -> None:
    assert typing.get_args(DriverModbusRtuParameter.model_fields["duplicate_id"].annotation) \
        == DUPLICATE_POLICIES
    p = DriverModbusRtuParameter.model_validate({"duplicateId": " Keep-Existing "})
    assert p.duplicate_id == "keep-existing"


# ----------------------------------------------------------------------------- allow-lists


@pytest.mark.parametrize(("given", "normalised"), [
    ("10.0.0.0/8", "10.0.0.0/8"),
    ("192.168.1.7", "192.168.1.7/32"),  # a bare address is one host
    (" 172.16.0.0/12 ", "172.16.0.0/12"),
    ("0.0.0.0/0", "0.0.0.0/0"),
    ("2001:DB8::/32", "2001:db8::/32"),
    ("2001:db8::7", "2001:db8::7/128"),
    ("::/0", "::/0"),
])
def test_networks_v4_and_v6_are_normalised(given: str, normalised: str) -> None:
    assert network(given) == normalised
    p = DriverModbusRtuParameter.model_validate({"listenAllowFrom": [given],
                                                 "dtuAllowFrom": [given]})
    assert p.listen_allow_from == p.dtu_allow_from == (normalised,)


def test_an_allow_list_may_be_one_text_separated_by_commas() -> None:
    p = DriverModbusRtuParameter.model_validate(
        {"listenAllowFrom": "10.0.0.0/8, 192.168.1.7\t2001:db8::/32,"})
    assert p.listen_allow_from == ("10.0.0.0/8", "192.168.1.7/32", "2001:db8::/32")
    assert DriverModbusRtuParameter.model_validate({"dtuAllowFrom": ""}).dtu_allow_from == ()


NOT_A_NETWORK = ("must be an IPv4 or IPv6 network in CIDR notation or a single address, "
                 "e.g. 10.0.0.0/8, 192.168.1.7, 2001:db8::/32")


@pytest.mark.parametrize(("bad", "why"), [
    ("10.0.0.256", NOT_A_NETWORK),
    ("10.0.0.0/33", NOT_A_NETWORK),
    ("gateway.local", NOT_A_NETWORK),
    ("2001:db8::g", NOT_A_NETWORK),
    ("", NOT_A_NETWORK),
    ("10.1.2.3/8", "has host bits set: use 10.0.0.0/8, or the single address 10.1.2.3"),
    ("2001:db8::1/32", "has host bits set: use 2001:db8::/32, or the single address "
                       "2001:db8::1"),
])
def test_a_bad_network_names_field_value_and_what_is_allowed(bad: str, why: str) -> None:
    for key in ("listenAllowFrom", "dtuAllowFrom"):
        assert errors_of(server(**{key: ["10.0.0.0/8", bad]})) == [
            f"communication.{key}[1] {bad!r}: {why}"]


@pytest.mark.parametrize("bad", [5, None, {"a": 1}, ["10.0.0.0/8", 7]])
def test_an_allow_list_of_the_wrong_type_is_refused_whole(bad: Any) -> None:
    assert errors_of({"listenAllowFrom": bad}) == [
        f"communication.listenAllowFrom {bad!r}: must be a list of networks (an IPv4 or IPv6 "
        "network in CIDR notation or a single address, e.g. 10.0.0.0/8, 192.168.1.7, "
        "2001:db8::/32), or one text of them separated by commas"]


def test_networks_for_the_listener_are_sorted_unique_and_checked_again() -> None:
    assert networks(["10.0.0.7", "::1", "10.0.0.7/32", "10.0.0.0/8"], "listenAllowFrom") == (
        "10.0.0.0/8", "10.0.0.7/32", "::1/128")
    with pytest.raises(ConfigError) as info:
        networks(["10.0.0.0/8", "10.0.0.0/99"], "dtuAllowFrom")
    assert str(info.value) == f"communication.dtuAllowFrom[1] '10.0.0.0/99': {NOT_A_NETWORK}"


# ----------------------------------------------------------------------------- rules


def test_registration_length_must_fit_in_registration_max_bytes() -> None:
    ok = server(registration="text", registrationLength=256, registrationMaxBytes=256)
    assert DriverModbusRtuParameter.model_validate(ok).registration_length == 256
    assert errors_of(server(registration="text", registrationLength=300)) == [
        "communication.registrationLength 300: must be at most registrationMaxBytes (256): "
        "the registration would never arrive in full"]
    assert errors_of(server(registrationLength=65, registrationMaxBytes=64)) == [
        "communication.registrationLength 65: must be at most registrationMaxBytes (64): "
        "the registration would never arrive in full"]


def test_the_key_needs_registration_regex_and_a_key_group() -> None:
    good = DriverModbusRtuParameter.model_validate(server(registrationKey=SECRET))
    assert good.registration_key.get_secret_value() == SECRET
    named_id = server(registrationPattern=r"(?P<key>\w+)@(?P<id>\d+)", registrationKey=SECRET)
    assert DriverModbusRtuParameter.model_validate(named_id).registration_pattern
    assert errors_of(server(registration="text", registrationKey=SECRET)) == [
        "communication.registrationKey '**********': needs registration 'regex' and a "
        f"registrationPattern with a group named key, e.g. {KEY_EXAMPLE}; registration is "
        "'text'"]
    assert errors_of(server(registrationPattern=r"ID:(\d+)", registrationKey=SECRET)) == [
        r"communication.registrationPattern 'ID:(\\d+)': registrationKey needs a group named "
        f"key, e.g. {KEY_EXAMPLE}"]
    # the whole match would be the id, the key in it (and in dtuId)
    assert errors_of(server(registrationPattern=r"(?P<key>\w+)", registrationKey=SECRET)) == [
        r"communication.registrationPattern '(?P<key>\\w+)': besides the group named key, "
        f"the id needs a group (named id, or any other), e.g. {KEY_EXAMPLE}"]
    # a key group without a key configured is no error (the key is not checked)
    assert DriverModbusRtuParameter.model_validate(server()).registration_key.get_secret_value() \
        == ""


def test_the_listen_rules_apply_in_listen_mode_only_like_the_other_listen_keys() -> None:
    # registrationPattern, dtuId ... are not checked on other transports: neither are these
    for transport in ("rtu", "rtu-over-tcp", "tcp"):
        p = DriverModbusRtuParameter.model_validate(
            {"transport": transport, "registration": "text", "registrationKey": SECRET,
             "registrationLength": 1024, "registrationPattern": "("})
        assert p.registration_key.get_secret_value() == SECRET
    # ...while a value's own form is checked whatever the transport (as ranges are)
    assert errors_of({"transport": "rtu", "listenAllowFrom": ["x"]})[0].startswith(
        "communication.listenAllowFrom[0] 'x': must be")
    assert errors_of({"transport": "rtu", "registrationMaxBytes": 0}) == [
        "communication.registrationMaxBytes 0: must be 1..65536"]


def test_a_key_that_is_not_latin1_is_refused_without_showing_it() -> None:
    key = SECRET + "\u20ac"
    assert errors_of(server(registrationKey=key)) == [
        "communication.registrationKey '**********': must be Latin-1 text (the registration "
        "packet is read as Latin-1, one character per byte)"]
    assert key_bytes(SecretStr("k\xe9y")) == b"k\xe9y"


# ----------------------------------------------------------------------------- the secret


def shown(text: str) -> None:
    assert SECRET not in text, text


def test_the_key_is_in_no_repr_str_dump_or_descriptor() -> None:
    cfg = load_device_config({"communication": server(registrationKey=SECRET)})
    comm = cfg.communication
    for text in (repr(cfg), str(cfg), repr(comm), str(comm), repr(comm.registration_key),
                 json.dumps(cfg.to_dict()), cfg.model_dump_json(), str(cfg.model_dump()),
                 comm.model_dump_json(), json.dumps(driver_descriptor())):
        shown(text)
    assert cfg.to_dict()["communication"]["registrationKey"] == "**********"
    assert DriverModbusRtuParameter().to_dict()["registrationKey"] == ""  # none: nothing masked
    params = {p["name"]: p for p in driver_descriptor()["parameter"]}
    assert params["registrationKey"]["defaultValue"] == ""
    assert params["registrationKey"]["controlType"] == "password"
    assert params["listenAllowFrom"]["defaultValue"] == ""
    assert params["listenAllowFrom"]["type"] == "string"


def test_the_key_loads_from_a_device_file_and_round_trips_when_asked(tmp_path: Path) -> None:
    path = tmp_path / "dtu.json"
    path.write_text(json.dumps({"communication": server(registrationKey=SECRET)}), "utf-8")
    cfg = load_device_config(path)
    assert cfg.communication.registration_key.get_secret_value() == SECRET
    assert load_communication(server(registrationKey=SECRET)).registration_key \
        == cfg.communication.registration_key
    # to_dict masks; to_dict(secrets=True) loads back to an equal model (a file written back)
    assert load_device_config(cfg.to_dict(secrets=True)) == cfg
    masked = load_device_config(cfg.to_dict())
    assert masked != cfg and masked.communication.registration_key.get_secret_value() \
        == "**********"
    other = load_device_config({"communication": server(registrationKey=SECRET + "x")})
    assert other.to_dict() == cfg.to_dict()  # hence reload compares with secrets=True
    assert other.to_dict(secrets=True) != cfg.to_dict(secrets=True)


@pytest.mark.parametrize("comm", [
    server(registration="text", registrationKey=SECRET),  # a rule
    server(registrationKey=SECRET + "\u20ac"),  # its own check
    server(registrationKey=SECRET, registration_key=SECRET + "x"),  # given twice
    server(registrationKey=SECRET, baudRate=5, registrationLength=999),  # others' errors
])
def test_no_error_shows_the_key(comm: dict[str, Any],
                                caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": comm, "unknownKey": SECRET[:3]})
    shown(str(info.value))
    for direct in (DriverModbusRtuParameter, DeviceConfig):
        data = comm if direct is DriverModbusRtuParameter else {"communication": comm}
        with pytest.raises(ValueError) as raw:  # pydantic's own error text, too
            direct.model_validate(data)
        shown(str(raw.value))
        shown(repr(raw.value))
    shown(caplog.text)


@pytest.mark.parametrize("bad", [123456, 12.5, True, [SECRET], {"k": SECRET}])
def test_a_key_of_the_wrong_type_is_refused_unshown(bad: Any) -> None:
    (line,) = errors_of(server(registrationKey=bad))
    assert line == ("communication.registrationKey: must be a string (the value given, of "
                    f"type {type(bad).__name__}, is not shown: a secret)")
    with pytest.raises(ValueError) as raw:
        DriverModbusRtuParameter.model_validate(server(registrationKey=bad))
    for value in ("123456", "12.5", SECRET):
        assert value not in str(raw.value)


def test_a_null_key_is_no_secret_and_is_refused_as_missing_text() -> None:
    (line,) = errors_of(server(registrationKey=None))
    assert line.startswith("communication.registrationKey None: ") and "string" in line


# ----------------------------------------------------------------------------- the driver


def test_port_settings_carry_every_port_key() -> None:
    p = DriverModbusRtuParameter.model_validate(server(
        registrationMaxBytes=128, registrationByteRate=0, maxUnregistered=100,
        maxUnregisteredPerSource=4, listenAllowFrom=["2001:db8::/32", "10.0.0.9"],
        duplicateId="replace", idFlipLimit=3, idFlipWindow=1500,
        registrationTimeout=2500, heartbeat="HB", engine="thread", loopThreads=3))
    assert port_settings(p) == PortSettings(
        host="127.0.0.1", port=9502, registration="regex", pattern=PATTERN, length=None,
        timeout=2.5, heartbeat=b"HB", max_bytes=128, byte_rate=0, max_unregistered=100,
        max_per_source=4, allow_from=("10.0.0.9/32", "2001:db8::/32"),
        duplicate_id="replace", flip_limit=3, flip_window=1.5, engine="thread", loop_threads=3)
    defaults = port_settings(DriverModbusRtuParameter.model_validate(server()))
    # auto: the registry's default engine, the loop (line/dtu_registry.py)
    assert (defaults.engine, defaults.loop_threads) == (None, None)
    assert (defaults.max_bytes, defaults.byte_rate, defaults.max_unregistered,
            defaults.max_per_source, defaults.allow_from, defaults.duplicate_id,
            defaults.flip_limit, defaults.flip_window) == (256, 1024, 512, 64, (), "keep-existing",
                                                           5, 60.0)


def test_devices_listing_one_allow_list_differently_agree_on_the_port() -> None:
    a = port_settings(DriverModbusRtuParameter.model_validate(
        server(listenAllowFrom=["10.0.0.0/8", "192.168.1.7"])))
    b = port_settings(DriverModbusRtuParameter.model_validate(
        server(listenAllowFrom="192.168.1.7/32, 10.0.0.0/8, 10.0.0.0/8")))
    assert a.differences(b) == []
    c = port_settings(DriverModbusRtuParameter.model_validate(server(idFlipLimit=9)))
    assert c.differences(a) == [
        "listenAllowFrom ('10.0.0.0/8', '192.168.1.7/32') (the port has ())",
        "idFlipLimit 5 (the port has 9)"]


def test_dtu_access_carries_the_allow_list_and_the_key_as_bytes() -> None:
    p = DriverModbusRtuParameter.model_validate(server(
        dtuAllowFrom=["10.9.0.0/16", "2001:DB8::1"], registrationKey=SECRET))
    access = dtu_access(p)
    assert access == DtuAccess(allow_from=("10.9.0.0/16", "2001:db8::1/128"),
                               key=SECRET.encode("latin-1"))
    shown(repr(access))
    assert dtu_access(DriverModbusRtuParameter.model_validate(server())) == DtuAccess()


def test_values_changed_after_loading_are_checked_again_without_showing_the_key() -> None:
    p = DriverModbusRtuParameter.model_validate(server())
    p.listen_allow_from = ("10.0.0.0/40",)
    with pytest.raises(ConfigError, match=r"communication\.listenAllowFrom\[0\] "
                                          r"'10\.0\.0\.0/40': must be an IPv4"):
        port_settings(p)
    p = DriverModbusRtuParameter.model_validate(server())
    p.registration_key = SecretStr(SECRET + "\u20ac")
    with pytest.raises(ConfigError) as info:
        dtu_access(p)
    assert str(info.value) == ("communication.registrationKey '**********': must be Latin-1 "
                               "text (the registration packet is read as Latin-1, one "
                               "character per byte)")
