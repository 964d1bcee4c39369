"""The engineering units keys of an item (offset, rawMin/rawMax/engMin/engMax, clamp,
scaleFactor): each bad value is a config error naming the key, the value and what is
allowed; good ones reach the codec's spec, with one table of scale factors per device."""

from __future__ import annotations

from typing import Any

import pytest

from edgemodbus.config import ConfigError, load_device_config, validate_items

SF = {"name": "W_SF", "address": "hr:1", "deviceDataType": "Int16"}


def device(*items: dict[str, Any]) -> dict[str, Any]:
    return {"organization": {"deviceCode": "d"}, "communication": {"comPort": "/dev/ttyS0"},
            "addressList": list(items)}


def item(**keys: Any) -> dict[str, Any]:
    return {"name": "W", "address": "hr:0", "deviceDataType": "Int16", **keys}


def errors_of(*items: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config(device(*items))
    return [str(p) for p in info.value.problems]


@pytest.mark.parametrize(("items", "expected"), [
    ((item(offset="abc"),), "addressList[0].offset 'abc': must be a finite number"),
    ((item(offset=True),), "addressList[0].offset True: must be a finite number"),
    ((item(rawMin="1e999"),), "addressList[0].rawMin"),
    ((item(rawMin=0),), "addressList[0].rawMax None: not allowed: rawMin, rawMax, engMin and "
                        "engMax all four, or none (missing: rawMax, engMin, engMax)"),
    ((item(rawMin=3, rawMax=3, engMin=0, engMax=1),),
     "addressList[0].rawMax 3.0: not allowed: a number other than rawMin (3.0)"),
    ((item(rawMin=0, rawMax=3, engMin=1, engMax=1),),
     "addressList[0].engMax 1.0: not allowed: a number other than engMin (1.0)"),
    ((item(rawMin=0, rawMax=3, engMin=0, engMax=1, dataMultiplier=0.1),),
     "addressList[0].dataMultiplier 0.1: not allowed: a range (rawMin..engMax) maps the raw "
     "value alone: leave dataMultiplier out, or fold it into engMin/engMax"),
    ((item(rawMin=0, rawMax=3, engMin=0, engMax=1, offset=2),),
     "addressList[0].offset 2.0: not allowed: a range (rawMin..engMax) maps the raw value "
     "alone: leave offset out"),
    ((item(clamp=True),), "addressList[0].clamp True: not allowed: clamp needs rawMin, rawMax, "
                          "engMin and engMax"),
    ((item(deviceDataType="String", quantity=2, offset=1),),
     "addressList[0].offset 1.0: not allowed: String values are not scaled (numeric types only)"),
    ((item(address="coil:0", deviceDataType="Boolean", rawMin=0, rawMax=1, engMin=0, engMax=5),),
     "addressList[0].rawMin 0.0: not allowed: Boolean values are not scaled"),
    ((item(scaleFactor=7),), "addressList[0].scaleFactor 7: must be the name of an Int16 item "
                             "of the same device"),
    ((item(scaleFactor="nope"),), "addressList[0].scaleFactor 'nope': no item of that name in "
                                  "this device's addressList"),
    ((item(scaleFactor="W"),), "addressList[0].scaleFactor 'W': an item is not its own scale "
                               "factor"),
    ((item(scaleFactor="W_SF"), {**SF, "deviceDataType": "UInt16"}),
     "addressList[0].scaleFactor 'W_SF': that item is UInt16 at hr:1; a scale factor is an "
     "Int16 register (SunSpec sunssf)"),
    ((item(scaleFactor="W_SF"), {**SF, "dataMultiplier": 10}),
     "addressList[0].scaleFactor 'W_SF': that item is scaled itself"),
    ((item(scaleFactor="W_SF"), {**SF, "address": "hr:1.2", "deviceDataType": "Boolean"}),
     "addressList[0].scaleFactor 'W_SF': that item is Boolean at hr:1.2"),
    ((item(scaleFactor="W_SF"), {**SF, "isEnable": False}),
     "addressList[0].scaleFactor 'W_SF': that item is disabled (isEnable false)"),
    ((item(scaleFactor="W_SF", deviceDataType="String", quantity=2), SF),
     "addressList[0]"),
])
def test_bad_scaling_keys_are_config_errors(items: tuple[dict[str, Any], ...],
                                            expected: str) -> None:
    errors = errors_of(*items)
    assert any(e.startswith(expected) for e in errors), errors


def test_good_keys_reach_the_codec_spec_with_one_factor_table_per_device() -> None:
    items = [item(scaleFactor="W_SF"), SF,
             {"name": "Hz", "address": "hr:2", "deviceDataType": "UInt16", "scale_factor": "W_SF"},
             {"name": "T", "address": "hr:3", "deviceDataType": "Int16", "offset": "-40",
              "dataMultiplier": 0.1},
             {"name": "I", "address": "hr:4", "deviceDataType": "UInt16", "rawMin": 0,
              "rawMax": 27648, "engMin": 4, "engMax": 20, "clamp": True}]
    specs = {}
    for _ in range(2):
        cfg = load_device_config(device(*items))
        parsed = validate_items(cfg.address_list, cfg.communication)
        specs[len(specs)] = {p.name: p.value_spec() for p in parsed}
    one, two = specs[0], specs[1]
    assert one["W"].factors is one["W_SF"].factors is one["Hz"].factors is not None
    assert one["W"].factors is not two["W"].factors  # one table per device
    assert one["W_SF"].holds_factor == "W_SF" and one["Hz"].scale_factor == "W_SF"
    assert (one["T"].offset, one["T"].multiplier) == (-40.0, 0.1)
    assert one["I"].raw_range == (0, 27648) and one["I"].eng_range == (4, 20)
    assert one["I"].clamp and one["I"].factors is None
    assert one["W"] != two["W"]  # specs of two devices never share a table


def test_a_disabled_item_needs_no_factor() -> None:
    cfg = load_device_config(device(item(scaleFactor="gone", isEnable=False)))
    assert cfg.address_list[0].scale_factor == "gone"
