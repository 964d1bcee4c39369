"""Bare numbers that read as an offset but look like Modicon entity numbers (issue 24:
``40001`` planned silently as holding register 40001)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.datatypes import Area
from edgemodbus.protocol.address import Address, entity_lookalike, entity_notice, parse_address


def test_the_issue_cases() -> None:
    assert entity_lookalike("40001", "function-code") == Address(Area.HOLDING_REGISTER, 0)
    assert entity_lookalike("30001", "modicon") == Address(Area.INPUT_REGISTER, 0)
    assert entity_lookalike("10017", "function-code") == Address(Area.DISCRETE_INPUT, 16)
    assert entity_lookalike(" 40010.3 ", "function-code") == Address(Area.HOLDING_REGISTER, 9, 3)
    for text, prefix in [("40001", "entity"), ("hr:40001", "function-code"),
                         ("3:40001", "function-code"), ("00005", "function-code"),
                         ("20001", "function-code"), ("4001", "function-code"),
                         ("40000", "function-code"), ("100", "function-code")]:
        assert entity_lookalike(text, prefix) is None, (text, prefix)
    assert entity_notice("40001", parse_address("40001"), Address(Area.HOLDING_REGISTER, 0)) \
        == ("address '40001' is read as holding register 40001 (hr:40001); as a Modicon "
            "entity number it would be holding register 0 (hr:0)")


@given(st.integers(0, 99999), st.sampled_from(["function-code", "modicon"]))
def test_a_notice_exactly_for_five_digit_entity_numbers(number: int, prefix: str) -> None:
    """Independent rule: 5 digits, first 1, 3 or 4, entity part 1..9999 -> the entity's
    address; everything else none.  The offset reading stays valid either way."""
    text = f"{number:05d}" if number >= 10000 else str(number)
    got = entity_lookalike(text, prefix)
    table = {"1": Area.DISCRETE_INPUT, "3": Area.INPUT_REGISTER, "4": Area.HOLDING_REGISTER}
    if len(text) == 5 and text[0] in table and int(text[1:]) >= 1:
        assert got == Address(table[text[0]], int(text[1:]) - 1)
        assert parse_address(text, prefix) == Address(Area.HOLDING_REGISTER, number)
    else:
        assert got is None
