"""Config validation sweep: the config's limits are the codec's, planner's and address
parser's; every error shows path, value given and what is allowed; organisation
overrides mean what communication's fields mean; one line per problem."""

from __future__ import annotations

import logging
import types
import typing
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import SecretStr

from edgemodbus import codec
from edgemodbus.codec import BlockDecoder
from edgemodbus.config import (
    ConfigError,
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    Range,
    load_device_config,
    validate_items,
    validate_parameters,
)
from edgemodbus.datatypes import Area, DataType
from edgemodbus.poll import planner
from edgemodbus.poll.items import ItemState
from edgemodbus.poll.poller import Poller
from edgemodbus.poll.sink import BatchCallback, ItemCallback
from edgemodbus.protocol import address, limits


def errors_of(source: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config(source)
    return [str(p) for p in info.value.problems]


def field_range(model: type[Any], name: str) -> Range:
    (rng,) = [m for m in model.model_fields[name].metadata if isinstance(m, Range)]
    return rng


class NoHost:
    """The sink of a poller that is built and never started: nothing is delivered."""

    def item_callback(self) -> ItemCallback | None:
        return None

    def batch_callback(self) -> BatchCallback | None:
        return None

    def snapshot_due(self) -> None:
        raise AssertionError("a poller that was never started ended a cycle")


# ----------------------------------------------------------------------------- one source of truth


def test_limits_are_the_limits_of_the_layers_that_use_them() -> None:
    assert field_range(DeviceAddressItem, "quantity").hi == codec.MAX_QUANTITY
    comm = DriverModbusRtuParameter
    assert field_range(comm, "max_block_read_register_count").hi == limits.MAX_READ_REGISTERS
    assert field_range(comm, "max_block_read_bit_count").hi == limits.MAX_READ_BITS
    assert comm.model_fields["max_block_read_bit_count"].default == limits.MAX_READ_BITS
    assert field_range(comm, "max_merge_address_gap").hi == address.MAX_OFFSET
    # the layers agree among themselves on the protocol's limits (protocol/limits.py)
    capped = planner.make_limits(max_registers=10**6, max_bits=10**6)
    assert (capped.registers, capped.bits) == (limits.MAX_READ_REGISTERS, limits.MAX_READ_BITS)
    assert limits.max_read(Area.HOLDING_REGISTER) == codec.MAX_QUANTITY
    assert address.MAX_OFFSET == limits.MAX_ADDRESS


def test_quantity_above_what_one_read_holds_is_refused_at_load() -> None:
    top = codec.MAX_QUANTITY
    ok = load_device_config({"addressList": [
        {"name": "s", "address": "hr:1", "deviceDataType": "String", "quantity": top}]})
    assert ok.parsed_items()[0].registers == top
    assert errors_of({"addressList": [
        {"name": "s", "address": "hr:1", "deviceDataType": "String", "quantity": top + 1}]}) == [
        f"addressList[0].quantity {top + 1}: must be 1..{top}"
    ]


@pytest.mark.parametrize(("item", "expected"), [
    ({"deviceDataType": "String", "quantity": 2, "dataMultiplier": 2},
     "addressList[0].dataMultiplier 2.0: not allowed: String values take no multiplier, use 1"),
    ({"deviceDataType": "Boolean", "dataMultiplier": 10},
     "addressList[0].dataMultiplier 10.0: not allowed: Boolean values take no multiplier, use 1"),
    ({"deviceDataType": "Int16", "convertedDataType": "DateTime"},
     "addressList[0].convertedDataType 'DateTime': not allowed: a numeric type, Boolean or "
     "String"),
    ({"deviceDataType": "Char", "convertedDataType": "Int16"},
     "addressList[0].convertedDataType 'Int16': not allowed: Char values are not converted"),
    ({"deviceDataType": "String", "quantity": 2, "encoding": "base64"},
     "addressList[0].encoding 'base64': unknown text encoding (use a codec Python knows, "
     "e.g. utf-8, gbk)"),
])
def test_codec_rules_are_config_errors(item: dict[str, Any], expected: str) -> None:
    assert errors_of({"addressList": [{"name": "x", "address": "hr:1", **item}]}) == [expected]


def test_bytes_codecs_are_not_text_encodings() -> None:
    assert errors_of({"communication": {"encoding": "base64"}}) == [
        "communication.encoding 'base64': unknown text encoding (use a codec Python knows, "
        "e.g. utf-8, gbk)"
    ]


@pytest.mark.parametrize(("comm", "expected"), [
    ({"transport": "rtu", "framing": "wrapped-report"},
     "communication.framing 'wrapped-report': needs transport rtu-over-tcp, "
     "rtu-over-tcp-server or mqtt-dtu, not 'rtu'"),
    ({"transport": "tcp", "echo": True},
     "communication.echo True: a Modbus TCP (MBAP) link has no request echo; the option is "
     "for RTU lines"),
])
def test_line_combinations_the_driver_refuses_are_config_errors(
    comm: dict[str, Any], expected: str
) -> None:
    assert errors_of({"communication": comm}) == [expected]


# Items the config accepts must be items the driver can build: the codec's check, the
# plan and its decoders (found a String with a multiplier, a DateTime conversion, a
# quantity of 200 and a bytes encoding that the config let through).
ITEM = st.fixed_dictionaries(
    {
        "name": st.just("x"),
        "address": st.sampled_from(["hr:10", "ir:7", "coil:3", "di:4", "hr:5.3", "hr:65534"]),
        "deviceDataType": st.sampled_from([t.value for t in DataType]),
    },
    optional={
        "quantity": st.integers(0, 300),
        "dataMultiplier": st.sampled_from([1, 2, 0.1, -1]),
        "convertedDataType": st.sampled_from(["", *(t.value for t in DataType)]),
        "deadband": st.sampled_from([0, 0.5]),
        "encoding": st.sampled_from(["utf-8", "gbk", "base64", "rot13", "latin-1"]),
        "dataFormat": st.sampled_from(["ABCD", "DCBA"]),
    },
)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(items=st.lists(ITEM, min_size=1, max_size=3))
def test_what_the_config_accepts_the_driver_can_build(items: list[dict[str, Any]]) -> None:
    items = [{**it, "name": f"x{i}"} for i, it in enumerate(items)]
    try:
        cfg = load_device_config({"addressList": items})
    except ConfigError as exc:
        for problem in exc.problems:  # every refusal names an item's field
            assert problem.path.startswith("addressList["), problem
        return
    parsed = cfg.parsed_items()
    for p in parsed:
        state = ItemState(p)
        BlockDecoder(state.area, state.size, [(0, state.spec)])
        assert state.spec == p.value_spec()  # the config checked the spec the driver uses
    Poller(NoHost(), "d", cfg.communication, parsed, logging.getLogger("test"))


def test_items_changed_after_loading_are_checked_again() -> None:
    cfg = load_device_config({"addressList": [
        {"name": "s", "address": "hr:1", "deviceDataType": "String", "quantity": 4},
        {"name": "f", "address": "hr:9", "deviceDataType": "Float", "deadband": 1}]})
    s, f = cfg.address_list
    s.quantity = 200
    f.deadband = -1
    with pytest.raises(ConfigError) as info:
        validate_items(cfg.address_list, cfg.communication)
    assert [str(p) for p in info.value.problems] == [
        "addressList[0].quantity 200: must be 1..125",
        "addressList[1].deadband -1: must be 0 or more",
    ]


def test_parameters_changed_after_loading_are_checked_again() -> None:
    comm = DriverModbusRtuParameter()
    org = DeviceOrganizationParameter()
    comm.max_block_read_register_count = 126
    org.read_cycle = -5
    with pytest.raises(ConfigError) as info:
        validate_parameters(org, comm)
    assert [str(p) for p in info.value.problems] == [
        "organization.readCycle -5: must be 0..86400000",
        "communication.maxBlockReadRegisterCount 126: must be 1..125",
    ]
    validate_parameters(None, DriverModbusRtuParameter())


# ----------------------------------------------------------------------------- values shown


def _fields(model: type[Any]) -> list[tuple[str, str, Any]]:
    """Fields whose values errors show (a secret's never: tests/unit/config/
    test_listen_config.py checks its type errors)."""
    return [(name, f.alias or name, f.annotation) for name, f in model.model_fields.items()
            if f.annotation is not Any and f.annotation is not SecretStr]


SECTIONS = [
    ("communication", DriverModbusRtuParameter),
    ("organization", DeviceOrganizationParameter),
    ("addressList[0]", DeviceAddressItem),
]


def _kinds(annotation: Any) -> set[Any]:
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    args = typing.get_args(annotation) if union else (annotation,)
    return {a for a in args if a is not type(None)}


def _wrong_values(annotation: Any) -> list[Any]:
    """Values of the wrong type for a field: a list and an object for every field, and
    for numbers true, text and (whole numbers) a fraction; for flags a number."""
    kinds = _kinds(typing.get_args(annotation)[0] if typing.get_origin(annotation)
                   is typing.Annotated else annotation)
    values: list[Any] = [[1, 2]]
    if not any(typing.get_origin(k) is dict or k is dict for k in kinds):
        values.append({"a": 1})
    if kinds <= {int, float}:
        values += [True, "fast"]
        if kinds == {int}:
            values.append(1.5)
    if kinds == {bool}:
        values.append(5)
    return values


CASES = [
    (section, key, value)
    for section, model in SECTIONS
    for _, key, annotation in _fields(model)
    for value in _wrong_values(annotation)
]


@pytest.mark.parametrize(("section", "key", "value"), CASES)
def test_every_type_error_shows_path_value_and_what_is_allowed(
    section: str, key: str, value: Any
) -> None:
    item = {"name": "a", "address": "hr:1", "deviceDataType": "Int16"}
    doc: dict[str, Any] = {"communication": {}, "organization": {}, "addressList": [item]}
    target = item if section.startswith("addressList") else doc[section]
    target[key] = value
    problems = errors_of(doc)
    assert len(problems) == 1, problems
    (line,) = problems
    head = f"{section}.{key} {value!r}: "
    assert line.startswith(head), line
    why = line.removeprefix(head)
    assert why.startswith(("must be", "use ", "unknown ")), line
    assert "Input should" not in why and "a valid" not in why, line


def test_pydantic_type_errors_are_translated() -> None:
    assert errors_of({"organization": {"readCycle": [1]}}) == [
        "organization.readCycle [1]: must be a whole number 0..86400000"
    ]
    assert errors_of({"communication": {"readCycle": None, "stopBits": True}}) == [
        "communication.stopBits True: must be 1 or 2",
        "communication.readCycle None: must be a whole number 0..86400000",
    ]
    assert errors_of({"communication": {"useTcp": "maybe", "comPort": 5}}) == [
        "communication.comPort 5: must be a string",
        "communication.useTcp 'maybe': must be true or false",
    ]
    assert errors_of({"organization": {"createdAt": "yesterday", "metadata": [1]}}) == [
        "organization.createdAt 'yesterday': must be a date and time, e.g. 2026-01-18T12:06:26Z",
        "organization.metadata [1]: must be an object ({...})",
    ]
    assert errors_of({"communication": [1]}) == ["communication [1]: must be an object ({...})"]
    long = list(range(100))
    (line,) = errors_of({"addressList": [long]})
    assert line.startswith("addressList[0] [0, 1, 2, ") and "...: must be an object" in line


def test_numbers_given_as_text_or_whole_floats_still_load() -> None:
    comm = DriverModbusRtuParameter.model_validate({"readCycle": "250", "baudRate": 19200.0})
    assert (comm.read_cycle, comm.baud_rate) == (250, 19200)
    it = DeviceAddressItem.model_validate(
        {"name": "a", "address": "hr:1", "deviceDataType": "Float", "dataMultiplier": "0.5"})
    assert it.data_multiplier == 0.5


# ----------------------------------------------------------------------------- numeric addresses


@pytest.mark.parametrize("comm", [{}, {"addressBase": 1}, {"addressPrefix": "modicon"}])
def test_a_number_as_address_means_the_same_as_its_text(comm: dict[str, Any]) -> None:
    def parsed(addr: Any) -> Any:
        cfg = load_device_config({"communication": comm, "addressList": [
            {"name": "a", "address": addr, "deviceDataType": "Int16"}]})
        return cfg.parsed_items()[0].address

    assert parsed(100) == parsed("100")
    assert parsed(65535) == parsed("65535")
    assert DeviceAddressItem(name="a", address=7, device_data_type=DataType.INT16).address == "7"


@pytest.mark.parametrize("value", [100.0, 100.5, True, None, [100]])
def test_a_fraction_a_flag_or_nothing_is_not_an_address(value: Any) -> None:
    assert errors_of({"addressList": [
        {"name": "a", "address": value, "deviceDataType": "Int16"}]}) == [
        f"addressList[0].address {value!r}: must be a string like 'hr:100' "
        "(or a whole number: an offset)"
    ]


def test_a_number_out_of_range_is_refused_like_its_text() -> None:
    assert errors_of({"addressList": [
        {"name": "a", "address": 70000, "deviceDataType": "Int16"}]}) == [
        "addressList[0].address 70000: offset 70000 out of range 0..65535"
    ]


# ----------------------------------------------------------------------------- organisation


OVERRIDES = [("read_cycle", "readCycle"), ("connect_timeout", "connectTimeout"),
             ("reconnect_interval", "reconnectInterval")]


@pytest.mark.parametrize(("name", "key"), OVERRIDES)
def test_organization_overrides_take_what_communication_takes(name: str, key: str) -> None:
    rng = field_range(DriverModbusRtuParameter, name)
    assert field_range(DeviceOrganizationParameter, name) == rng
    lo, hi = int(rng.lo), int(rng.hi or 0)
    for value in (lo, hi):
        cfg = load_device_config({"organization": {key: value}})
        assert getattr(cfg.effective_parameters(), name) == value
        assert getattr(load_device_config({"communication": {key: value}}).communication,
                       name) == value
    for value in (lo - 1, hi + 1):
        assert errors_of({"organization": {key: value}}) == [
            f"organization.{key} {value}: must be {rng.describe()}"
        ]
        assert errors_of({"communication": {key: value}}) == [
            f"communication.{key} {value}: must be {rng.describe()}"
        ]


def test_organization_read_cycle_zero_is_report_only() -> None:
    cfg = load_device_config({
        "organization": {"readCycle": 0},
        "communication": {"transport": "rtu-over-tcp", "framing": "wrapped-report"},
    })
    params = cfg.effective_parameters()
    assert params.read_cycle == 0 and cfg.communication.read_cycle == 1000
    device = Poller(NoHost(), "d", params, [], logging.getLogger("test"))
    assert device.report_only


# ----------------------------------------------------------------------------- one line each


def test_a_failed_load_tells_unknown_keys_in_the_error_not_as_warnings(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    problems = errors_of({
        "colour": "red",
        "communication": {"baudRate": 300},
        "addressList": [{"name": "a", "addr": "hr:1", "deviceDataType": "Int16"},
                        {"name": "s", "address": "hr:2", "deviceDataType": "String",
                         "qty": 2}],
    })
    assert problems == [
        "communication.baudRate 300: must be 1200..921600",
        "addressList[0].address: required (the unknown key 'addr' was ignored)",
        "<root>: unknown key 'colour' ignored",
        "addressList[1]: unknown key 'qty' ignored",
    ]
    assert [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"] == []
    # once the rest is right the misspelt quantity is the one problem, told once
    assert errors_of({"addressList": [
        {"name": "s", "address": "hr:2", "deviceDataType": "String", "qty": 2}]}) == [
        "addressList[0].quantity: String needs quantity (its length in registers) "
        "(the unknown key 'qty' was ignored)"
    ]
    assert [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"] == []


def test_a_good_load_warns_once_per_unknown_key(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    load_device_config({"communication": {"Speed": 1}, "addressList": [
        {"name": "a", "address": "hr:1", "deviceDataType": "Int16", "Gain": 2}]})
    assert [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"] == [
        "communication: unknown key 'Speed' ignored",
        "addressList[0]: unknown key 'Gain' ignored",
    ]
    caplog.clear()
    DeviceConfig.model_validate({"bogus": 1})  # outside a load: logged at once
    assert [r.getMessage() for r in caplog.records] == ["<root>: unknown key 'bogus' ignored"]
