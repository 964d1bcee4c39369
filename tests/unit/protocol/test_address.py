"""Address grammar: parse results, prefix/base options, exact error messages, span check."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.datatypes import Area
from edgemodbus.protocol.address import (
    Address,
    address_regex,
    check_span,
    parse_address,
    type_number,
)

HR, IR, CO, DI = Area.HOLDING_REGISTER, Area.INPUT_REGISTER, Area.COIL, Area.DISCRETE_INPUT


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("coil:5", Address(CO, 5)),
        ("c:5", Address(CO, 5)),
        ("1:00001", Address(CO, 1)),
        ("di:7", Address(DI, 7)),
        ("DiscreteInput:7", Address(DI, 7)),
        ("2:0", Address(DI, 0)),
        ("hr:100", Address(HR, 100)),
        ("holding:100", Address(HR, 100)),
        ("3:00005", Address(HR, 5)),
        ("3:0099", Address(HR, 99)),
        ("ir:9", Address(IR, 9)),
        ("INPUT:9", Address(IR, 9)),
        ("4:65535", Address(IR, 65535)),
        ("200", Address(HR, 200)),
        ("00000", Address(HR, 0)),
        ("hr:100.3", Address(HR, 100, 3)),
        ("ir:1.15", Address(IR, 1, 15)),
        ("3:1.0", Address(HR, 1, 0)),
        ("  Hr:12  ", Address(HR, 12)),
        ("\thr:12\n", Address(HR, 12)),
    ],
)
def test_parse_function_code_prefix(text: str, expected: Address) -> None:
    assert parse_address(text) == expected


def test_modicon_prefix_swaps_3_and_4_only() -> None:
    assert parse_address("3:00005", "modicon") == Address(IR, 5)
    assert parse_address("4:00005", "modicon") == Address(HR, 5)
    assert parse_address("1:00005", "modicon") == Address(CO, 5)
    assert parse_address("2:00005", "modicon") == Address(DI, 5)
    assert parse_address("hr:5", "modicon") == Address(HR, 5)
    assert parse_address("ir:5", "modicon") == Address(IR, 5)
    assert type_number(HR, "modicon") == "4"
    assert type_number(HR) == "3"


def test_base_one_shifts_offsets_and_rejects_zero() -> None:
    assert parse_address("hr:1", base=1) == Address(HR, 0)
    assert parse_address("4:65536", base=1) == Address(IR, 65535)
    with pytest.raises(ValueError, match=r"offset 0 out of range 1\.\.65536"):
        parse_address("hr:0", base=1)
    with pytest.raises(ValueError, match=r"offset 65537 out of range"):
        parse_address("hr:65537", base=1)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "5:100",
            "'5:100': unknown type '5' "
            "(use coil|c|1, di|discreteinput|2, hr|holding|3, ir|input|4)",
        ),
        ("hr:70000", "'hr:70000': offset 70000 out of range 0..65535"),
        ("hr:65536", "'hr:65536': offset 65536 out of range 0..65535"),
        ("coil:5.1", "'coil:5.1': a bit index is only allowed on hr/ir registers"),
        ("di:5.1", "'di:5.1': a bit index is only allowed on hr/ir registers"),
        ("hr:1.16", "'hr:1.16': bit 16 out of range 0..15"),
        ("", "'': empty address (use [type:]offset[.bit], e.g. 'hr:100')"),
        ("hr:", "'hr:': offset '' is not a decimal number"),
        ("hr:1:2", "'hr:1:2': offset '1:2' is not a decimal number"),
        ("hr:-1", "'hr:-1': offset '-1' is not a decimal number"),
        ("hr:1_000", "'hr:1_000': offset '1_000' is not a decimal number"),
        ("hr:\u0661\u0662", "'hr:\u0661\u0662': offset '\u0661\u0662' is not a decimal number"),
        ("hr:1.", "'hr:1.': bit '' is not a decimal number"),
        (
            "hr :1",
            "'hr :1': unknown type 'hr ' "
            "(use coil|c|1, di|discreteinput|2, hr|holding|3, ir|input|4)",
        ),
        (
            "03:1",
            "'03:1': unknown type '03' "
            "(use coil|c|1, di|discreteinput|2, hr|holding|3, ir|input|4)",
        ),
    ],
)
def test_errors_name_text_and_rule(text: str, message: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_address(text)
    assert str(info.value) == message


def test_modicon_error_lists_modicon_numbers() -> None:
    with pytest.raises(ValueError, match=r"hr\|holding\|4, ir\|input\|3"):
        parse_address("x:1", "modicon")


def test_bad_options_rejected() -> None:
    with pytest.raises(ValueError, match="address prefix 'iec'"):
        parse_address("hr:1", "iec")
    with pytest.raises(ValueError, match="address base 2"):
        parse_address("hr:1", base=2)


def test_non_ascii_letters_do_not_lower_into_types() -> None:
    # U+0130 lowers to 'i' + combining dot: non-ASCII tokens are never type names.
    with pytest.raises(ValueError, match="unknown type"):
        parse_address("\u0130r:1")


def test_str_is_canonical() -> None:
    assert str(Address(HR, 100, 3)) == "hr:100.3"
    assert str(Address(CO, 5)) == "coil:5"
    assert str(Address(DI, 0)) == "di:0"
    assert str(Address(IR, 65535)) == "ir:65535"


@given(
    area=st.sampled_from(list(Area)),
    offset=st.integers(0, 65535),
    bit=st.none() | st.integers(0, 15),
)
def test_str_round_trips(area: Area, offset: int, bit: int | None) -> None:
    addr = Address(area, offset, None if area.is_bit else bit)
    assert parse_address(str(addr)) == addr
    assert parse_address(str(addr), "modicon") == addr


def test_check_span() -> None:
    check_span(Address(HR, 65532), 4)
    check_span(Address(CO, 65535), 1)
    with pytest.raises(ValueError, match=r"hr:65533: 4 registers from here run past"):
        check_span(Address(HR, 65533), 4)
    with pytest.raises(ValueError, match="at least 1"):
        check_span(Address(HR, 0), 0)


@pytest.mark.parametrize("prefix", ["function-code", "modicon"])
@pytest.mark.parametrize("base", [0, 1])
@given(
    text=st.text(alphabet="0123456789:.hHrRiI cC1lL\t", max_size=12)
    | st.from_regex(r"\A(hr|ir|coil|di|[0-6]):[0-9]{1,6}(\.[0-9]{1,2})?\Z"),
)
def test_regex_matches_iff_parser_accepts(prefix: str, base: int, text: str) -> None:
    pattern = re.compile(address_regex(prefix, base))
    try:
        parse_address(text, prefix, base)
        accepted = True
    except ValueError:
        accepted = False
    assert bool(pattern.match(text)) is accepted, text
