"""Driver descriptor: generated from the model and the address grammar, and truthful."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, DeviceAddressItem, DriverModbusRtuParameter
from edgemodbus.config.base import load_model
from edgemodbus.config.labels import ITEM_LABELS, LABELS
from edgemodbus.datatypes import Area, DataType
from edgemodbus.descriptor import EXAMPLE_KEYS, driver_descriptor
from edgemodbus.protocol.address import parse_address

SEED = json.loads(
    (Path(__file__).resolve().parents[2] / "data" / "seed-descriptor.json").read_text("utf-8")
)
OPTIONS = [("function-code", 0), ("modicon", 0), ("function-code", 1), ("modicon", 1),
           ("entity", 0), ("entity", 1)]


def parses(text: str, prefix: str = "function-code", base: int = 0) -> bool:
    try:
        parse_address(text, prefix, base)
    except ValueError:
        return False
    return True


def test_shape_matches_the_seed_and_is_json() -> None:
    desc = driver_descriptor()
    assert set(SEED) <= set(desc)
    assert json.loads(json.dumps(desc)) == desc
    assert desc["driverType"] == "DriverModbusRtu" and desc["protocolCategory"] == "Generic"
    assert desc["addressList"] == [] and desc["hasBuiltInAddresses"] is False
    assert desc["allowManualAddress"] is True


def test_supported_data_types_are_all_types() -> None:
    assert driver_descriptor()["supportedDataTypes"] == [t.value for t in DataType]
    assert set(SEED["supportedDataTypes"]) <= set(driver_descriptor()["supportedDataTypes"])


def test_parameters_come_from_every_model_field() -> None:
    params = driver_descriptor()["parameter"]
    fields = DriverModbusRtuParameter.model_fields
    assert [p["name"] for p in params] == [f.alias for f in fields.values()]
    for p in params:
        assert p["label"] and p["description"] and p["category"] in ("Connection", "Advanced")
        assert p["type"] in ("string", "int", "bool", "double")
    for category in ("Connection", "Advanced"):
        orders = [p["orderNo"] for p in params if p["category"] == category]
        assert orders == list(range(1, len(orders) + 1))


def test_labels_name_exactly_the_model_fields() -> None:
    # labels.py is keyed by field name: a renamed or removed field leaves no stale label
    assert set(LABELS) == set(DriverModbusRtuParameter.model_fields)


def test_a_field_without_labels_is_refused_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delitem(LABELS, "echo")
    with pytest.raises(TypeError, match=r"DriverModbusRtuParameter\.echo: no UI labels"):
        driver_descriptor()


def test_default_values_load_back_to_the_model_defaults() -> None:
    defaults = DriverModbusRtuParameter()
    for p in driver_descriptor()["parameter"]:
        loaded = DriverModbusRtuParameter.model_validate({p["name"]: p["defaultValue"]})
        name = next(
            n for n, f in DriverModbusRtuParameter.model_fields.items() if f.alias == p["name"]
        )
        assert getattr(loaded, name) == getattr(defaults, name), p["name"]


def test_options_and_ranges_are_accepted_and_hold_the_default() -> None:
    for p in driver_descriptor()["parameter"]:
        values = [o["value"] if isinstance(o, dict) else o for o in p.get("options", [])]
        if values:
            assert p["defaultValue"] in values, p["name"]
        for value in values:
            # (an MQTT DTU's topics need its id)
            DriverModbusRtuParameter.model_validate({"transport": "rtu-over-tcp",
                                                     "dtuId": "d1", p["name"]: value})
        if "min" in p and p["defaultValue"] is not None:
            assert p["min"] <= p["defaultValue"] <= p.get("max", p["defaultValue"])


def test_seed_parameters_keep_their_label_type_category_control() -> None:
    ours = {p["name"]: p for p in driver_descriptor()["parameter"]}
    for seed in SEED["parameter"]:
        mine = ours[seed["name"]]
        for key in ("label", "type", "category", "controlType", "defaultValue"):
            assert mine[key] == seed[key], (seed["name"], key)
        for key in ("dataSource", "visibleWhen"):
            if key in seed:
                assert mine[key] == seed[key], (seed["name"], key)
    seed_order = [p["name"] for p in SEED["parameter"]]
    assert [n for n in ours if n in seed_order] == seed_order
    assert ours["dataBits"]["options"] == [5, 6, 7, 8]  # we accept 5..8, not only 7/8


def test_address_parameters_are_the_seed_file_s_item_fields() -> None:
    # the item's scan rate, in full (tests/data/seed-descriptor.json pins it), then the
    # engineering units keys (docs/engineering-units.md)
    ours = driver_descriptor()["addressParameter"]
    assert ours[: len(SEED["addressParameter"])] == SEED["addressParameter"]
    assert [p["name"] for p in SEED["addressParameter"]] == [
        "readCycle", "reportMode", "reportEvery"]
    scaling = {p["name"]: p for p in ours[len(SEED["addressParameter"]):]}
    assert list(scaling) == ["offset", "rawMin", "rawMax", "engMin", "engMax", "clamp",
                             "scaleFactor"]
    assert {p["category"] for p in scaling.values()} == {"Scaling"}
    assert (scaling["offset"]["type"], scaling["offset"]["defaultValue"]) == ("double", 0.0)
    assert (scaling["clamp"]["type"], scaling["clamp"]["controlType"]) == ("bool", "switch")
    assert scaling["scaleFactor"]["type"] == "string"
    assert all(p["description"] for p in scaling.values())


def test_item_read_cycle_has_the_device_s_range_and_demand_and_loads_its_limits() -> None:
    (item_range,) = DeviceAddressItem.model_fields["read_cycle"].metadata
    (device_range,) = DriverModbusRtuParameter.model_fields["read_cycle"].metadata
    # the device's range, and -1: on demand (docs/reporting.md)
    assert (item_range.lo, item_range.hi) == (-1, device_range.hi)
    assert device_range.lo == 0
    entry = driver_descriptor()["addressParameter"][0]
    assert entry["name"] == "readCycle"
    base = {"name": "x", "address": "hr:1", "deviceDataType": "UInt16"}
    for ok in (entry["min"], entry["max"], entry["defaultValue"]):
        assert DeviceAddressItem.model_validate({**base, "readCycle": ok}).read_cycle == ok
    with pytest.raises(ConfigError, match=r'readCycle -2: must be -1 \("demand": read only '
                       r"when asked\), 0 \(wrapped reports only\) or 1\.\.86400000 ms"):
        load_model(DeviceAddressItem, {**base, "readCycle": -2})
    with pytest.raises(ConfigError, match=r"readCycle 86400001: must be -1\.\.86400000"):
        load_model(DeviceAddressItem, {**base, "readCycle": 86400001})


def test_item_labels_name_item_fields(monkeypatch: pytest.MonkeyPatch) -> None:
    assert set(ITEM_LABELS) <= set(DeviceAddressItem.model_fields)
    monkeypatch.setitem(ITEM_LABELS, "read_cycel", ITEM_LABELS["read_cycle"])
    with pytest.raises(TypeError, match="DeviceAddressItem has no field read_cycel"):
        driver_descriptor()


def test_prefix_and_base_in_force() -> None:
    ours = {p["name"]: p for p in driver_descriptor("modicon", 1)["parameter"]}
    assert ours["addressPrefix"]["defaultValue"] == "modicon"
    assert ours["addressBase"]["defaultValue"] == 1
    with pytest.raises(ValueError, match="address prefix"):
        driver_descriptor("iec")


@pytest.mark.parametrize(("prefix", "base"), OPTIONS)
def test_examples_parse_to_their_area(prefix: str, base: int) -> None:
    examples = driver_descriptor(prefix, base)["addressExamples"]
    assert set(examples) == {*EXAMPLE_KEYS, "note"}
    for key, area in EXAMPLE_KEYS.items():
        assert parse_address(examples[key], prefix, base).area is area
        assert re.match(driver_descriptor(prefix, base)["addressRegex"], examples[key])
    holding = "3=Holding Register" if prefix == "function-code" else "4=Holding Register"
    inputs = "4=Input Register" if prefix == "function-code" else "3=Input Register"
    assert holding in examples["note"] and inputs in examples["note"]
    assert ("1 基" in examples["note"]) is (base == 1)


def test_the_seed_examples_mean_the_modicon_numbering() -> None:
    # The seed's descriptor (3 = input, 4 = holding) is what prefix "modicon" states.
    modicon = driver_descriptor("modicon")["addressExamples"]
    for key in EXAMPLE_KEYS:
        assert modicon[key] == SEED["addressExamples"][key]


# Strings from the grammar's alphabet (valid and invalid), and near-valid addresses.
ALPHABET = "0123456789:. \t\nhHrRiIcCoOlLdDsStTeEnNpPuUgG\u0663_-"
grammarish = st.builds(
    lambda ws1, typ, sep, off, bit, ws2: f"{ws1}{typ}{sep}{off}{bit}{ws2}",
    st.sampled_from(["", " ", "\t", "\n "]),
    st.sampled_from(
        [
            *("", "hr", "HR", "holding", "ir", "Input", "coil", "c", "di", "DiscreteInput"),
            *("0", "1", "2", "3", "4", "5", "03", "x", "h r"),
        ]
    ),
    st.sampled_from([":", "", "::", "."]),
    st.builds(lambda zeros, n: "0" * zeros + str(n), st.integers(0, 3), st.integers(0, 65537))
    | st.from_regex(r"\A[0-9]{0,7}\Z")
    | st.sampled_from(["65535", "65536", "00065535", "0"]),
    st.sampled_from(["", ".", ".0", ".15", ".16", ".015", ".1.2", ".x"]),
    st.sampled_from(["", " ", "\r\n"]),
)
samples = st.text(alphabet=ALPHABET, max_size=16) | grammarish


@pytest.mark.parametrize(("prefix", "base"), OPTIONS)
@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(text=samples)
@example(text="3:00001")
@example(text="hr:65535.15")
@example(text="coil:1.0")
@example(text="hr:1.16")
@example(text="4:1.015 ")
@example(text="0")
@example(text="65536")
def test_regex_accepts_exactly_what_the_parser_accepts(prefix: str, base: int, text: str) -> None:
    regex = driver_descriptor(prefix, base)["addressRegex"]
    assert bool(re.match(regex, text)) is parses(text, prefix, base), repr(text)


def test_generated_samples_include_both_outcomes() -> None:
    seen: set[bool] = set()

    @settings(max_examples=200)
    @given(text=grammarish)
    def collect(text: str) -> None:
        seen.add(parses(text))

    collect()
    assert seen == {True, False}


NODE = shutil.which("node")


@pytest.mark.skipif(NODE is None, reason="node is not installed")
def test_regex_means_the_same_in_javascript() -> None:
    """The UI evaluates the regex in JavaScript: same verdicts as the parser."""
    texts = [
        "3:00001", "hr:1.15", "HR:1.16", " coil:5 ", "coil:5.1", "di:65535", "di:65536",
        "5:1", "ir:00000000", "Input:7", "1:", "", "200", "hr:\u0663", "hr:1\n", "C:0",
        "discreteinput:9", "holding:1.015", "4:1.", "hr:1:2",
    ]  # fmt: skip
    regex = driver_descriptor()["addressRegex"]
    script = (
        "const re = new RegExp(process.argv[1]);"
        "console.log(JSON.stringify(JSON.parse(process.argv[2]).map(t => re.test(t))));"
    )
    out = subprocess.run(
        [str(NODE), "-e", script, regex, json.dumps(texts)],
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    ).stdout
    verdicts: list[Any] = json.loads(out)
    assert verdicts == [parses(t) for t in texts]
    assert True in verdicts and False in verdicts


def test_all_areas_have_an_example_key() -> None:
    assert set(EXAMPLE_KEYS.values()) == set(Area)
