"""Modicon entity numbers (addressPrefix "entity"): both forms, every table, the errors,
and a round trip of every offset of every table."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.datatypes import Area
from edgemodbus.protocol.address import (
    Address,
    address_regex,
    format_address,
    format_entity,
    parse_address,
)

HR, IR, CO, DI = Area.HOLDING_REGISTER, Area.INPUT_REGISTER, Area.COIL, Area.DISCRETE_INPUT


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("40001", Address(HR, 0)),
        ("49999", Address(HR, 9998)),
        ("400001", Address(HR, 0)),
        ("465536", Address(HR, 65535)),
        ("30001", Address(IR, 0)),
        ("300010", Address(IR, 9)),
        ("10001", Address(DI, 0)),
        ("165536", Address(DI, 65535)),
        ("00001", Address(CO, 0)),
        ("000001", Address(CO, 0)),
        ("1", Address(CO, 0)),
        ("0017", Address(CO, 16)),
        ("9999", Address(CO, 9998)),
        ("40001.15", Address(HR, 0, 15)),
        ("300001.0", Address(IR, 0, 0)),
        (" 40010 ", Address(HR, 9)),
        ("hr:0", Address(HR, 0)),  # typed addresses as under function-code
        ("3:5", Address(HR, 5)),
        ("4:5", Address(IR, 5)),
    ],
)
def test_entity_numbers(text: str, expected: Address) -> None:
    assert parse_address(text, "entity") == expected
    assert re.match(address_regex("entity"), text)


def test_base_applies_to_typed_addresses_only() -> None:
    assert parse_address("40001", "entity", 1) == Address(HR, 0)
    assert parse_address("hr:1", "entity", 1) == Address(HR, 0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("40000", "'40000': entity number out of range: holding registers are 40001..49999 "
                  "(5 digits) or 400001..465536 (6 digits)"),
        ("465537", "'465537': entity number out of range: holding registers are "
                   "40001..49999 (5 digits) or 400001..465536 (6 digits)"),
        ("300000", "'300000': entity number out of range: input registers are 30001..39999 "
                   "(5 digits) or 300001..365536 (6 digits)"),
        ("0", "'0': entity number out of range: coils are 00001..09999 (5 digits) or "
              "000001..065536 (6 digits)"),
        ("10000", "'10000': entity number out of range: discrete inputs are 10001..19999 "
                  "(5 digits) or 100001..165536 (6 digits)"),
        ("20001", "'20001': table digit '2' is not a Modbus table (use 0 coil, 1 discrete "
                  "input, 3 input register, 4 holding register)"),
        ("700001", "'700001': table digit '7' is not a Modbus table (use 0 coil, 1 discrete "
                   "input, 3 input register, 4 holding register)"),
        ("4000001", "'4000001': an entity number has 5 digits (40001..49999) or 6 "
                    "(400001..465536), fewer for coils (1 = 00001)"),
        ("10001.1", "'10001.1': a bit index is only allowed on hr/ir registers"),
        ("40001.16", "'40001.16': bit 16 out of range 0..15"),
        ("4x001", "'4x001': entity number '4x001' is not a decimal number "
                  "(use e.g. 40001, 400001, or hr:0)"),
    ],
)
def test_errors_name_the_text_and_the_range(text: str, message: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_address(text, "entity")
    assert str(info.value) == message
    assert not re.match(address_regex("entity"), text)


def test_every_offset_of_every_table_round_trips() -> None:
    """Exhaustive: 4 tables x 65536 offsets, 6-digit form; the 5-digit form where it
    reaches (offsets 0..9998)."""
    for area in Area:
        for offset in range(65536):
            addr = Address(area, offset)
            assert parse_address(format_entity(addr), "entity") == addr
            if offset < 9999:
                assert parse_address(format_entity(addr, six_digits=False), "entity") == addr
    with pytest.raises(ValueError, match="has no 5-digit entity number"):
        format_entity(Address(HR, 9999), six_digits=False)


@given(
    area=st.sampled_from(list(Area)),
    offset=st.integers(0, 65535),
    bit=st.none() | st.integers(0, 15),
    six=st.booleans(),
)
def test_entity_round_trip_property(area: Area, offset: int, bit: int | None,
                                    six: bool) -> None:
    addr = Address(area, offset, None if area.is_bit else bit)
    if not six and offset >= 9999:
        six = True
    text = format_entity(addr, six_digits=six)
    assert len(text.partition(".")[0]) == (6 if six else 5)
    assert parse_address(text, "entity") == addr
    assert re.match(address_regex("entity"), text)
    for prefix, base in (("function-code", 0), ("modicon", 1), ("entity", 1)):
        assert parse_address(format_address(addr, prefix, base), prefix, base) == addr


@given(text=st.from_regex(r"\A[0-9]{1,7}(\.[0-9]{1,2})?\Z"))
def test_regex_accepts_exactly_what_the_parser_accepts(text: str) -> None:
    try:
        parse_address(text, "entity")
        accepted = True
    except ValueError:
        accepted = False
    assert bool(re.match(address_regex("entity"), text)) is accepted, text


def _items(*addresses: str) -> list[dict[str, str]]:
    return [{"name": f"t{i}", "address": a, "deviceDataType": "UInt16"}
            for i, a in enumerate(addresses)]


def test_device_file_switch() -> None:
    cfg = em.load_device_config({"communication": {"addressPrefix": "entity"},
                                 "addressList": _items("40001", "300005", "hr:7")})
    assert [str(p.address) for p in cfg.parsed_items()] == ["hr:0", "ir:4", "hr:7"]


def test_device_file_error_names_field_value_and_range() -> None:
    with pytest.raises(ConfigError) as info:
        em.load_device_config({"communication": {"addressPrefix": "entity"},
                               "addressList": _items("40001", "465537")})
    assert [str(p) for p in info.value.problems] == [
        "addressList[1].address '465537': entity number out of range: holding registers "
        "are 40001..49999 (5 digits) or 400001..465536 (6 digits)"]


def test_without_the_switch_an_entity_number_is_refused_with_a_hint() -> None:
    with pytest.raises(ConfigError) as info:
        em.load_device_config({"addressList": _items("400001")})
    (problem,) = info.value.problems
    assert problem.path == "addressList[0].address"
    assert "out of range 0..65535" in str(problem)
    assert "with addressPrefix 'entity' it is the entity number of hr:0" in str(problem)
