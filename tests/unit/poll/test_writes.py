"""Write preparation without I/O: value normalization, encoding and request merging."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.codec import normalize_value
from edgemodbus.datatypes import Area, DataType
from edgemodbus.poll.items import ItemState
from edgemodbus.poll.writes import plan_writes


def make_device(items: list[dict[str, Any]], **comm: Any) -> dict[str, ItemState]:
    """The item states of a device, by name: what plan_writes looks written items up in."""
    cfg = em.load_device_config({"communication": comm, "addressList": items})
    return {p.item.name: ItemState(p) for p in cfg.parsed_items()}


@pytest.mark.parametrize(
    ("dtype", "raw", "expected"),
    [
        (DataType.BOOLEAN, "true", True), (DataType.BOOLEAN, "off", False),
        (DataType.BOOLEAN, 1, True), (DataType.BOOLEAN, b"0", False),
        (DataType.INT16, "12", 12), (DataType.INT16, 12.0, 12), (DataType.INT16, True, 1),
        (DataType.FLOAT, "12.5", 12.5), (DataType.FLOAT, 3, 3),
        (DataType.STRING, '"quoted"', "quoted"), (DataType.STRING, "plain", "plain"),
        (DataType.STRING, 42, "42"),
        (DataType.BINARY, "01 ff", b"\x01\xff"), (DataType.BINARY, [1, 2], b"\x01\x02"),
        (DataType.DATETIME, "2026-01-18T12:16:58Z",
         datetime(2026, 1, 18, 12, 16, 58, tzinfo=timezone.utc)),
        (DataType.DATETIME, 0, datetime(1970, 1, 1, tzinfo=timezone.utc)),
    ],
)
def test_normalize_accepts_what_hosts_send(dtype: DataType, raw: Any, expected: Any) -> None:
    assert normalize_value("item", dtype, raw) == expected


@pytest.mark.parametrize(
    ("dtype", "raw", "fragment"),
    [
        (DataType.BOOLEAN, "maybe", "'maybe' is not a Boolean value"),
        (DataType.BOOLEAN, 2, "2 is not a Boolean value"),
        (DataType.INT16, "abc", "'abc' is not a Int16 value"),
        (DataType.FLOAT, None, "no value given"),
        (DataType.FLOAT, [1], "is not a number"),
        (DataType.BINARY, "xyz", "not binary data"),
        (DataType.DATETIME, "yesterday", "not a DateTime value"),
    ],
)
def test_normalize_rejects_with_item_and_value(dtype: DataType, raw: Any, fragment: str) -> None:
    with pytest.raises(ValueError) as info:
        normalize_value("PumpSpeed", dtype, raw)
    assert "PumpSpeed" in str(info.value) and fragment in str(info.value)


def test_contiguous_registers_merge_into_one_request() -> None:
    dev = make_device([
        {"name": "a", "address": "hr:10", "deviceDataType": "UInt16"},
        {"name": "b", "address": "hr:11", "deviceDataType": "Int32"},
        {"name": "c", "address": "hr:13", "deviceDataType": "Float"},
        {"name": "gap", "address": "hr:20", "deviceDataType": "UInt16"},
        {"name": "c1", "address": "coil:1", "deviceDataType": "Boolean"},
        {"name": "c2", "address": "coil:2", "deviceDataType": "Boolean"},
        {"name": "bit", "address": "hr:30.2", "deviceDataType": "Boolean"},
    ])
    ops = plan_writes(dev, [("c", 1.5), ("a", 7), ("gap", 1), ("b", -2), ("c2", "true"),
                            ("c1", False), ("bit", True)])
    shape = [(op.area, op.address, len(op.registers), op.bits, op.bit) for op in ops]
    assert shape == [
        (Area.COIL, 1, 0, [False, True], None),
        (Area.HOLDING_REGISTER, 10, 5, [], None),
        (Area.HOLDING_REGISTER, 20, 1, [], None),
        (Area.HOLDING_REGISTER, 30, 0, [True], 2),
    ]
    assert ops[1].registers == [7, 0xFFFF, 0xFFFE, 0x3FC0, 0x0000]
    assert [st.item.name for st, _ in ops[1].updates] == ["a", "b", "c"]


def test_bit_in_a_byte_swapped_register_targets_the_raw_bit() -> None:
    dev = make_device([{"name": "bit", "address": "hr:5.3", "deviceDataType": "Boolean",
                        "byteSwap16": True}])
    (op,) = plan_writes(dev, [("bit", 1)])
    assert op.bit == 11  # bit 3 of the byte-swapped register is bit 11 on the wire


def test_data_format_does_not_move_a_bit_of_a_register() -> None:
    """A bit is in one register: dataFormat BADC does not swap it (it used to: bit 11)."""
    dev = make_device([{"name": "bit", "address": "hr:5.3", "deviceDataType": "Boolean",
                        "dataFormat": "BADC"}])
    (op,) = plan_writes(dev, [("bit", 1)])
    assert op.bit == 3


def test_merge_respects_the_fc16_limit() -> None:
    items = [{"name": f"r{i}", "address": f"hr:{i}", "deviceDataType": "UInt16"}
             for i in range(130)]
    dev = make_device(items, maxBlockReadRegisterCount=120)
    ops = plan_writes(dev, [(f"r{i}", i) for i in range(130)])
    assert [len(op.registers) for op in ops] == [123, 7]  # FC16 carries at most 123


def test_bad_writes_name_the_item() -> None:
    dev = make_device([{"name": "ir", "address": "ir:1", "deviceDataType": "UInt16"},
                       {"name": "u", "address": "hr:1", "deviceDataType": "UInt16"}])
    with pytest.raises(ValueError, match="'zzz'"):
        plan_writes(dev, [("zzz", 1)])
    with pytest.raises(ValueError, match="ir: ir:1 is a read-only input register"):
        plan_writes(dev, [("ir", 1)])
    with pytest.raises(ValueError, match="written twice"):
        plan_writes(dev, [("u", 1), ("u", 2)])
    with pytest.raises(ValueError, match=r"u.*-1"):
        plan_writes(dev, [("u", -1)])
    with pytest.raises(ValueError, match="nothing to write"):
        plan_writes(dev, [])
