"""``--slaves`` text (simulate, scan, demo): one parser (issue 24: ``simulate --slaves
1-300`` was a traceback, ``--slaves abc`` "invalid _parse_ids value")."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.protocol.rtu import parse_slave_ids


def reference(text: str, low: int, high: int) -> list[int] | None:
    """An independent reading: a regular expression per part; None when refused."""
    ids: list[int] = []
    parts = [p.strip() for p in text.split(",") if p.strip()]
    for part in parts:
        m = re.fullmatch(r"([+-]?\d+)(?:-(\d+))?", part)
        if m is None:
            return None
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        if not (low <= a <= b <= high):
            return None
        ids += [i for i in range(a, b + 1) if i not in ids]
    return ids or None


@pytest.mark.parametrize(("text", "message"), [
    ("1-300", "'1-300' is outside 1..247 or reversed (allowed: ids 1..247 and ranges"),
    ("abc", "'abc' is not a number or range"),
    ("1,x", "'1,x': 'x' is not a number or range"),
    ("5-2", "'5-2' is outside 1..247 or reversed"),
    (",", "',': no slave ids"),
])
def test_refusals_name_the_part(text: str, message: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_slave_ids(text)
    assert str(info.value).startswith(message), str(info.value)


@given(st.lists(st.one_of(st.integers(-3, 260).map(str),
                          st.tuples(st.integers(0, 260), st.integers(0, 260))
                          .map(lambda t: f"{t[0]}-{t[1]}"),
                          st.sampled_from(["x", "", " 7 ", "1-", "-"])), max_size=5),
       st.sampled_from([(1, 247), (0, 255)]))
def test_same_as_a_reference_reading(parts: list[str], bounds: tuple[int, int]) -> None:
    text = ",".join(parts)
    want = reference(text, *bounds)
    try:
        got = parse_slave_ids(text, *bounds)
    except ValueError:
        assert want is None, text
        return
    assert got == want, text
