"""edgemodbus.codec.jsonable, the one conversion of values to JSON: whatever it is given
(nested dicts, lists and tuples of every kind of value an item or a counter holds), the
result is strict JSON and says the same thing; NaN and the infinities are told apart
from null ("no value"), and a Float item's value is written as float32."""

from __future__ import annotations

import json
import math
import struct
from datetime import date, datetime, timedelta, timezone
from typing import Any, NoReturn

from hypothesis import example, given, settings
from hypothesis import strategies as st

from edgemodbus.codec import (
    Float32,
    ValueSpec,
    encode,
    float32_short,
    float32_text,
    json_bytes,
    json_text,
    json_value,
    jsonable,
    normalize_value,
)
from edgemodbus.datatypes import DataType

NON_FINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}

float32s = st.integers(0, 2**32 - 1).map(
    lambda bits: Float32(struct.unpack("<f", struct.pack("<I", bits))[0]))
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    float32s,
    st.text(max_size=8),
    st.sampled_from(["NaN", "Infinity", "-Infinity", "null", "nan"]),  # text, not numbers
    st.binary(max_size=8),
    st.binary(max_size=8).map(bytearray),
    st.datetimes(timezones=st.just(timezone(timedelta(hours=8)))),
    st.datetimes(),
    st.dates(),
)
keys = st.one_of(st.text(max_size=4), st.sampled_from(["NaN", "Infinity", "null"]))
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.lists(inner, max_size=4).map(tuple),
        st.dictionaries(keys, inner, max_size=4),
    ),
    max_leaves=12,
)


def _strict(text: str | bytes) -> Any:
    """JSON parsed strictly: the bare NaN, Infinity and -Infinity that Python's json
    accepts are not JSON (RFC 8259 section 6)."""
    def refuse(constant: str) -> NoReturn:
        raise AssertionError(f"{constant} is not strict JSON: {text!r}")

    return json.loads(text, parse_constant=refuse)


def _same(original: Any, converted: Any) -> None:
    """``converted`` carries ``original`` as the documented rules say."""
    if isinstance(original, float):
        if not math.isfinite(original):
            assert isinstance(converted, str) and converted in NON_FINITE
            got = NON_FINITE[converted]
            assert got == original or (math.isnan(got) and math.isnan(original))
            return
        assert type(converted) is float
        if isinstance(original, Float32):  # its shortest float32 text, the same float32
            assert repr(converted) == float32_text(original)
            assert struct.pack("<f", converted) == struct.pack("<f", original)
        else:
            assert converted == original
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
    assert _strict(text) == converted
    _same(value, converted)


@settings(max_examples=300, deadline=None)
@given(scalars)
def test_json_value_is_jsonable_of_one_value(value: Any) -> None:
    assert json.dumps(json_value(value)) == json.dumps(jsonable(value))


def test_the_rules_on_examples() -> None:
    when = datetime(2026, 1, 18, 12, 16, 58, 250000, tzinfo=timezone.utc)
    given_ = {"a": [math.nan, -math.inf, math.inf, 1.5e-7, True, 3, None],
              "b": (b"\x00\xff", when), "c": Float32(69.74495697021484)}
    assert jsonable(given_) == {
        "a": ["NaN", "-Infinity", "Infinity", 1.5e-7, True, 3, None],
        "b": ["00ff", "2026-01-18T12:16:58.250000+00:00"],
        "c": 69.74496,
    }


@settings(max_examples=300, deadline=None)
@given(values, st.booleans())
@example({"NaN": 1}, False)  # the old test's `"NaN" not in text` failed on this key
@example({"x": ["Infinity", math.inf, None]}, True)
def test_json_text_is_the_same_conversion(value: Any, indent: bool) -> None:
    """json_bytes / json_text (orjson, with the careful stdlib path for what orjson
    refuses) write exactly what jsonable says, as strict JSON (whatever text the keys
    and strings hold)."""
    text = json_text(value, indent=indent)
    assert json_bytes(value, indent=indent) == text.encode()
    assert _strict(text) == _strict(json.dumps(jsonable(value)))


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.text(max_size=4), scalars, max_size=6))
def test_converted_values_are_written_once_the_same(row: dict[str, Any]) -> None:
    """A payload built from json_value (northbound/mqtt/payload.py) written without the
    check for NaN says the same as the checked one."""
    ready = {k: json_value(v) for k, v in row.items()}
    assert json_bytes(ready, converted=True) == json_bytes(row)


@settings(max_examples=500, deadline=None)
@given(st.one_of(st.floats(), float32s))
def test_what_json_carries_writes_back_the_same_registers(value: float) -> None:
    """A float as JSON carries it (a number, or "NaN" / "Infinity" / "-Infinity"), handed
    back to a write as an MQTT command hands it, encodes to the registers the value
    came from: a Float item's text is its float32, a Double's its double (a NaN is a NaN:
    JSON carries neither its sign nor its payload bits)."""
    sent = _strict(json_text({"value": value}))["value"]
    kind = DataType.FLOAT if isinstance(value, Float32) else DataType.DOUBLE
    spec = ValueSpec("x", kind)
    back = normalize_value("x", kind, sent)
    if math.isnan(value):
        assert sent == "NaN" and math.isnan(back)
    else:
        assert encode(spec, back) == encode(spec, value), (value, sent)


def test_json_text_on_examples() -> None:
    when = datetime(2026, 1, 18, 12, 16, 58, 250000, tzinfo=timezone(timedelta(seconds=30)))
    given_ = {"a": [math.nan, 1e300, -0.0, None, -math.inf], "b": b"\x00\xff", "c": when,
              1: 2**63, "f": Float32(0.10000000149011612)}
    assert json_bytes(given_) == (
        b'{"a":["NaN",1e+300,-0.0,null,"-Infinity"],"b":"00ff",'
        b'"c":"2026-01-18T12:16:58.250000+00:00:30","1":9223372036854775808,"f":0.1}')
    # past 64 bits orjson refuses: the standard library's encoder, the same values
    assert _strict(json_bytes({**given_, 1: 2**70})) == {
        "a": ["NaN", 1e300, -0.0, None, "-Infinity"], "b": "00ff",
        "c": "2026-01-18T12:16:58.250000+00:00:30", "1": 2**70, "f": 0.1}
    assert json_text({"s": "é"}) == '{"s":"é"}'  # UTF-8, not \u escapes
    assert json_text([1], indent=True) == "[\n  1\n]"
    # a payload without null is written once: Float32 through orjson's default
    assert json_bytes([Float32(69.74495697021484), 2.5]) == b"[69.74496,2.5]"
    assert json_bytes([Float32(math.nan), Float32(math.inf)]) == b'["NaN","Infinity"]'
    assert float32_short(Float32(1e-45)) == 1e-45
