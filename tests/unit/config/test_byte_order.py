"""The byte order keys of a device file (docs/device-files.md "Byte order"): ``dataFormat`` orders
values of two or more registers, ``byteSwap16`` swaps one-register values (NG's
``byteOrder: LittleEndian`` sets it), ``dataFormat64`` orders 64-bit values apart; each
per device and per item.  Values are decoded through the specs the loaded items give."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from edgemodbus import load_device_config
from edgemodbus._ffi import Block
from edgemodbus.codec import BlockDecoder, encode
from edgemodbus.config import ConfigError, validate_items
from edgemodbus.datatypes import Area, DataFormat, DataFormat64


def specs(comm: dict[str, Any], items: list[dict[str, Any]]) -> dict[str, Any]:
    cfg = load_device_config({"communication": comm, "addressList": items})
    return {p.name: p.value_spec() for p in validate_items(cfg.address_list, cfg.communication)}


def decode(spec: Any, registers: list[int]) -> object:
    decoder = BlockDecoder(Area.HOLDING_REGISTER, len(registers), [(0, spec)])
    return decoder.decode_values(Block.from_values(registers, bits=False))[0]


def errors_of(source: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config(source)
    return [str(p) for p in info.value.problems]


ITEMS = [
    {"name": "i16", "address": "hr:0", "deviceDataType": "Int16"},
    {"name": "u32", "address": "hr:1", "deviceDataType": "UInt32"},
    {"name": "u64", "address": "hr:3", "deviceDataType": "UInt64"},
    {"name": "bit", "address": "hr:7.3", "deviceDataType": "Boolean"},
]


def test_data_format_leaves_a_one_register_value_alone() -> None:
    """The Pascal.Edge contract: a device file with dataFormat DCBA reads its Int16 as
    the register, big-endian (main swapped it: 0x3412 read 0x1234 with status Ok)."""
    got = specs({"dataFormat": "DCBA"}, ITEMS)
    assert decode(got["i16"], [0x1234]) == 0x1234
    assert encode(got["i16"], 0x1234) == [0x1234]
    assert decode(got["u32"], [0x7856, 0x3412]) == 0x12345678
    assert decode(got["u64"], [0xF0DE, 0xBC9A, 0x7856, 0x3412]) == 0x123456789ABCDEF0
    assert decode(got["bit"], [1 << 3]) is True


def test_byte_swap16_per_device_and_per_item() -> None:
    got = specs({"dataFormat": "CDAB", "byteSwap16": True},
                [*ITEMS, {"name": "plain", "address": "hr:8", "deviceDataType": "UInt16",
                          "byteSwap16": False}])
    assert decode(got["i16"], [0x3412]) == 0x1234
    assert encode(got["i16"], 0x1234) == [0x3412]
    assert decode(got["plain"], [0x3412]) == 0x3412
    assert decode(got["bit"], [1 << 11]) is True  # bit 3 after the swap
    assert decode(got["u32"], [0x5678, 0x1234]) == 0x12345678  # not touched by it
    item = specs({}, [{**ITEMS[0], "byteSwap16": True}])["i16"]
    assert decode(item, [0x3412]) == 0x1234


@pytest.mark.parametrize(
    ("order", "registers"),
    [
        ("ABCDEFGH", [0x0102, 0x0304, 0x0506, 0x0708]),
        ("EFGHABCD", [0x0506, 0x0708, 0x0102, 0x0304]),  # Kepware: first DWord low
        ("GHEFCDAB", [0x0708, 0x0506, 0x0304, 0x0102]),
        ("CDABGHEF", [0x0304, 0x0102, 0x0708, 0x0506]),
        ("HGFEDCBA", [0x0807, 0x0605, 0x0403, 0x0201]),
        ("FEHGBADC", [0x0605, 0x0807, 0x0201, 0x0403]),
    ],
)
def test_data_format64_orders_64_bit_values_apart(order: str, registers: list[int]) -> None:
    got = specs({"dataFormat": "BADC", "dataFormat64": order.lower()}, ITEMS)
    assert got["u64"].data_format64 is DataFormat64(order)
    assert decode(got["u64"], registers) == 0x0102030405060708
    assert encode(got["u64"], 0x0102030405060708) == registers
    assert decode(got["u32"], [0x3412, 0x7856]) == 0x12345678  # dataFormat BADC still
    per_item = specs({}, [{**ITEMS[2], "dataFormat64": order}])["u64"]
    assert decode(per_item, registers) == 0x0102030405060708


def test_item_keys_override_the_device_one_by_one() -> None:
    comm = {"dataFormat": "CDAB", "dataFormat64": "EFGHABCD", "byteSwap16": True}
    got = specs(comm, [{**ITEMS[2], "dataFormat": "ABCD"},
                       {**ITEMS[1], "dataFormat64": "ABCDEFGH"}])
    # the item's dataFormat does not replace the device's dataFormat64
    assert got["u64"].data_format is DataFormat.ABCD
    assert got["u64"].data_format64 is DataFormat64.EFGHABCD and got["u64"].byte_swap16
    assert decode(got["u32"], [0x5678, 0x1234]) == 0x12345678


def test_ng_byte_order_little_endian_swaps_16_bit_values() -> None:
    """NG defines byteOrder per register: LittleEndian keeps swapping a UInt16."""
    cfg = load_device_config({"communication": {"byteOrder": "LittleEndian"},
                              "addressList": ITEMS})
    assert cfg.communication.data_format is DataFormat.BADC
    assert cfg.communication.byte_swap16 is True
    got = specs({"byteOrder": 1, "wordOrder": 1}, ITEMS)
    assert decode(got["i16"], [0x3412]) == 0x1234
    assert decode(got["u32"], [0x7856, 0x3412]) == 0x12345678
    assert specs({"byteOrder": "BigEndian"}, ITEMS)["i16"].byte_swap16 is False
    assert specs({"byteOrder": "LittleEndian", "byteSwap16": "true"}, ITEMS)["i16"].byte_swap16


def test_bad_values_name_the_key_the_value_and_what_is_allowed() -> None:
    assert errors_of({"communication": {"byteOrder": "LittleEndian", "byteSwap16": False}}) == [
        "communication.byteSwap16 False: disagrees with byteOrder 'LittleEndian'"
    ]
    (problem,) = errors_of({"communication": {"dataFormat64": "ABDC"}})
    assert problem.startswith("communication.dataFormat64 'ABDC': ")
    assert "EFGHABCD" in problem and "ABCDEFGH" in problem
    (problem,) = errors_of({"communication": {},
                            "addressList": [{**ITEMS[2], "dataFormat64": "CDAB"}]})
    assert problem.startswith("addressList[0].dataFormat64 'CDAB': ")
    (problem,) = errors_of({"communication": {"byteSwap16": "maybe"}})
    assert problem.startswith("communication.byteSwap16 'maybe': ")


def test_keys_round_trip_through_to_dict() -> None:
    cfg = load_device_config({"communication": {"byteSwap16": True, "dataFormat64": "EFGHABCD"},
                              "addressList": [{**ITEMS[0], "byteSwap16": False,
                                               "dataFormat64": "GHEFCDAB"}]})
    comm = cfg.communication.to_dict()
    assert (comm["byteSwap16"], comm["dataFormat64"]) == (True, "EFGHABCD")
    item = cfg.address_list[0].to_dict()
    assert (item["byteSwap16"], item["dataFormat64"]) == (False, "GHEFCDAB")
    again = load_device_config({"communication": comm, "addressList": [item]})
    assert again.communication.data_format64 is DataFormat64.EFGHABCD


def test_the_readme_table_of_64_bit_orders_is_what_the_codec_does() -> None:
    """docs/device-files.md "Byte order": each row's registers, with the letters as the bytes 01..08
    of 0x0102030405060708, are what the codec writes and reads for that dataFormat64."""
    doc = (Path(__file__).resolve().parents[3] / "docs" / "device-files.md").read_text("utf-8")
    section = doc.split("## Byte order", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| ([A-H]{8}) \| ([A-H] [A-H]) \| ([A-H] [A-H]) \| ([A-H] [A-H]) "
                      r"\| ([A-H] [A-H]) \|", section, re.M)
    assert sorted(order for order, *_ in rows) == sorted(f.value for f in DataFormat64)
    for order, *cells in rows:
        registers = [int("".join(f"0{ord(c) - 64}" for c in cell.split()), 16) for cell in cells]
        assert "".join(cells).replace(" ", "") == order
        spec = specs({"dataFormat64": order}, ITEMS)["u64"]
        assert encode(spec, 0x0102030405060708) == registers, order
        assert decode(spec, registers) == 0x0102030405060708
