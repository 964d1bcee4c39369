"""datatypes.enum_value: an enum member's value, anything else as it is."""

from __future__ import annotations

import pytest

from edgemodbus.datatypes import Area, DataFormat, DeviceDriverStatus, ItemStatus, enum_value


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        (ItemStatus.OK, "Ok"),
        (DeviceDriverStatus.RECONNECTING, "Reconnecting"),
        (Area.INPUT_REGISTER, 4),
        (DataFormat.CDAB, DataFormat.CDAB.value),
        ("Ok", "Ok"),
        (7, 7),
        (None, None),
    ],
)
def test_member_or_raw_value(given: object, expected: object) -> None:
    got = enum_value(given)
    assert got == expected and type(got) is type(expected)
