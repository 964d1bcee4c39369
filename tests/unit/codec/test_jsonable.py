"""edgemodbus.codec.jsonable, the one conversion of values to JSON: whatever it is given
(nested dicts, lists and tuples of every kind of value an item or a counter holds), the
result is strict JSON and says the same thing."""

from __future__ import annotations

import json
import math
from datetime import date, datetime, timedelta, timezone
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus.codec import json_bytes, json_text, jsonable

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.binary(max_size=8),
    st.binary(max_size=8).map(bytearray),
    st.datetimes(timezones=st.just(timezone(timedelta(hours=8)))),
    st.datetimes(),
    st.dates(),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.lists(inner, max_size=4).map(tuple),
        st.dictionaries(st.text(max_size=4), inner, max_size=4),
    ),
    max_leaves=12,
)


def _same(original: Any, converted: Any) -> None:
    """``converted`` carries ``original`` as the documented rules say."""
    if isinstance(original, float):
        assert converted == original if math.isfinite(original) else converted is None
        if math.isfinite(original):
            assert math.copysign(1, converted) == math.copysign(1, original)
    elif isinstance(original, dict):
        assert list(converted) == list(original)
        for key, item in original.items():
            _same(item, converted[key])
    elif isinstance(original, (list, tuple)):
        assert isinstance(converted, list) and len(converted) == len(original)
        for a, b in zip(original, converted, strict=True):
            _same(a, b)
    elif isinstance(original, (bytes, bytearray)):
        assert converted == bytes(original).hex()
    elif isinstance(original, date):  # datetime too
        assert converted == original.isoformat()
        assert type(original).fromisoformat(converted) == original
    else:
        assert converted is original


@settings(max_examples=300, deadline=None)
@given(values)
def test_result_is_strict_json_that_says_the_same(value: Any) -> None:
    converted = jsonable(value)
    text = json.dumps(converted, allow_nan=False)  # raises on NaN or an infinity
    assert json.loads(text) == converted
    _same(value, converted)


def test_the_rules_on_examples() -> None:
    when = datetime(2026, 1, 18, 12, 16, 58, 250000, tzinfo=timezone.utc)
    given_ = {"a": [math.nan, -math.inf, 1.5e-7, True, 3], "b": (b"\x00\xff", when)}
    assert jsonable(given_) == {
        "a": [None, None, 1.5e-7, True, 3],
        "b": ["00ff", "2026-01-18T12:16:58.250000+00:00"],
    }


@settings(max_examples=300, deadline=None)
@given(values, st.booleans())
def test_json_text_is_the_same_conversion(value: Any, indent: bool) -> None:
    """json_bytes / json_text (orjson, with the careful stdlib path for what orjson
    refuses) write exactly what jsonable says, as strict JSON."""
    text = json_text(value, indent=indent)
    assert json_bytes(value, indent=indent) == text.encode()
    assert json.loads(text) == json.loads(json.dumps(jsonable(value)))
    assert "NaN" not in text and "Infinity" not in text


def test_json_text_on_examples() -> None:
    when = datetime(2026, 1, 18, 12, 16, 58, 250000, tzinfo=timezone(timedelta(seconds=30)))
    given_ = {"a": [math.nan, 1e300, -0.0], "b": b"\x00\xff", "c": when, 1: 2**63}
    assert json_bytes(given_) == (
        b'{"a":[null,1e+300,-0.0],"b":"00ff","c":"2026-01-18T12:16:58.250000+00:00:30",'
        b'"1":9223372036854775808}')
    # past 64 bits orjson refuses: the standard library's encoder, the same values
    assert json.loads(json_bytes({**given_, 1: 2**70})) == {
        "a": [None, 1e300, -0.0], "b": "00ff", "c": "2026-01-18T12:16:58.250000+00:00:30",
        "1": 2**70}
    assert json_text({"s": "é"}) == '{"s":"é"}'  # UTF-8, not \u escapes
    assert json_text([1], indent=True) == "[\n  1\n]"
