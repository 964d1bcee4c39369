"""A served device's items as a unit's register image (serve/image.py), without I/O."""

from __future__ import annotations

import pytest

import edgemodbus as em
from edgemodbus._ffi.serve import STATE_INVALID, STATE_VALID, STATE_WRITABLE, ImageRun
from edgemodbus.config import ConfigError, validate_items
from edgemodbus.datatypes import Area, ItemStatus
from edgemodbus.serve import UnitImage


def image(offset: int = 0) -> UnitImage:
    cfg = em.load_device_config({
        "communication": {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1",
                          "tcpPort": 502, "slaveId": 1},
        "addressList": [
            {"name": "u", "address": "hr:10", "deviceDataType": "UInt16"},
            {"name": "f", "address": "hr:11", "deviceDataType": "Float", "dataFormat": "CDAB"},
            {"name": "scaled", "address": "hr:13", "deviceDataType": "Int16",
             "dataMultiplier": 0.1},
            {"name": "b0", "address": "hr:20.0", "deviceDataType": "Boolean"},
            {"name": "b3", "address": "hr:20.3", "deviceDataType": "Boolean"},
            {"name": "c", "address": "coil:5", "deviceDataType": "Boolean"},
            {"name": "i", "address": "ir:0", "deviceDataType": "UInt16"},
            {"name": "off", "address": "hr:30", "deviceDataType": "UInt16", "isEnable": False},
        ],
    })
    params = cfg.effective_parameters()
    return UnitImage(7, "dev", validate_items(list(cfg.address_list), params), offset)


def item(name: str, value: object, status: ItemStatus = ItemStatus.OK) -> em.DeviceAddressItem:
    return em.DeviceAddressItem(name=name, address="hr:0", deviceDataType="UInt16",
                                value=value, status=status)


def test_spans_cover_the_items_plus_the_offset() -> None:
    assert image().spans() == [(5, 1), (0, 0), (10, 11), (0, 1)]
    assert image(offset=1000).spans() == [(1005, 1), (0, 0), (1010, 11), (1000, 1)]


def test_runs_reencode_values_and_mark_invalid_items() -> None:
    img = image()
    w = STATE_VALID | STATE_WRITABLE
    assert img.runs([item("u", 513)]) == [ImageRun(7, 2, 10, w, [513])]
    assert img.runs([item("f", 1.5)]) == [ImageRun(7, 2, 11, w, [0x0000, 0x3FC0])]
    assert img.runs([item("scaled", -1.5)]) == [ImageRun(7, 2, 13, w, [0xFFF1])]
    assert img.runs([item("u", None, ItemStatus.INVALID)]) == [
        ImageRun(7, 2, 10, STATE_INVALID | STATE_WRITABLE, [0])]
    assert img.runs([item("c", True)]) == [ImageRun(7, 0, 5, w, [1])]
    assert img.runs([item("nosuch", 1)]) == []


def test_bit_items_share_their_register_and_are_read_only() -> None:
    img = image()
    # b3 alone is known: the register is still invalid until b0 is
    assert img.runs([item("b3", True)]) == [ImageRun(7, 2, 20, STATE_INVALID, [0x0008])]
    assert img.runs([item("b0", True)]) == [ImageRun(7, 2, 20, STATE_VALID, [0x0009])]
    assert img.write_values(Area.HOLDING_REGISTER, 20, [1]) == 2


def test_write_values_decode_whole_items_only() -> None:
    img = image()
    assert img.write_values(Area.HOLDING_REGISTER, 10, [7, 0x0000, 0x3FC0, 0xFFF1]) == [
        ("u", 7), ("f", 1.5), ("scaled", pytest.approx(-1.5))]
    assert img.write_values(Area.HOLDING_REGISTER, 12, [1]) == 2  # half of f
    assert img.write_values(Area.HOLDING_REGISTER, 10, [1, 2]) == 2  # u and half of f
    assert img.write_values(Area.HOLDING_REGISTER, 30, [1]) == 2  # a disabled item
    assert img.write_values(Area.COIL, 5, [1]) == [("c", True)]
    assert img.write_values(Area.INPUT_REGISTER, 0, [1]) == 2


def test_seed_from_a_snapshot() -> None:
    img = image()
    runs = img.seed({"u": {"value": 9, "status": "Ok"}, "f": {"value": None,
                                                             "status": "Invalid"}})
    assert [r.state & 3 for r in runs] == [STATE_VALID, STATE_INVALID]
    assert runs[0].values == [9]


def test_an_item_pushed_outside_the_address_space_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"item 'u' of 'dev' would be at 65545\.\.65545"):
        image(offset=65535)
