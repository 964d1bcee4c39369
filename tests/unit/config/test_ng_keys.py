"""NG Gateway's own keys (seed ng-gateway-modbus-driver.zh.md, 2.1-2.3) load through the
compatibility layer and plan to the same blocks as the native spelling; Smart Cast
quantities load with one warning per item."""

from __future__ import annotations

import logging
from typing import Any

import pytest

from edgemodbus import load_device_config
from edgemodbus.config import ConfigError
from edgemodbus.datatypes import DataFormat, DataType
from edgemodbus.poll.schedule import build_plan

# The seed's point table (2.3, 3.1): functionCode, 0-based address, quantity, dataType,
# scale; its Smart Cast example (Float32, quantity 1, scale 0.1); channel keys (2.1).
NG_DEVICE: dict[str, Any] = {
    "communication": {
        "connection": {"kind": "rtu", "port": "/dev/ttyUSB0", "baudRate": 9600,
                       "dataBits": 8, "stopBits": 1, "parity": "None"},
        "byteOrder": "BigEndian",
        "wordOrder": "LittleEndian",
        "maxGap": 10,
        "maxBatch": 100,
        "slaveId": 1,
    },
    "points": [
        {"name": "Temperature", "key": "temp", "functionCode": 3, "address": 0,
         "quantity": 1, "dataType": "Float32", "scale": 0.1},
        {"key": "power", "functionCode": "ReadHoldingRegisters", "address": 8,
         "quantity": 2, "dataType": "Float32"},
        {"key": "energy", "functionCode": 3, "address": 20, "quantity": 4, "dataType": "Int64"},
        {"key": "status", "functionCode": 4, "address": 5, "quantity": 1, "dataType": "UInt16"},
        {"key": "run", "functionCode": 1, "address": 3, "quantity": 1, "dataType": "Boolean"},
        {"key": "alarm", "functionCode": 2, "address": 7, "quantity": 1, "dataType": "Boolean"},
        {"key": "model", "functionCode": "0x03", "address": 200, "quantity": 5,
         "dataType": "String", "scale": None},
    ],
}

NATIVE_DEVICE: dict[str, Any] = {
    "communication": {
        "transport": "rtu", "comPort": "/dev/ttyUSB0", "baudRate": 9600, "dataBits": 8,
        "stopBits": 1, "parity": "None", "dataFormat": "CDAB",
        "maxMergeAddressGap": 10, "maxBlockReadRegisterCount": 100,
        "maxBlockReadBitCount": 100, "slaveId": 1,
    },
    "addressList": [
        {"name": "Temperature", "address": "hr:0", "quantity": 1, "deviceDataType": "Float",
         "dataMultiplier": 0.1},
        {"name": "power", "address": "hr:8", "quantity": 2, "deviceDataType": "Float"},
        {"name": "energy", "address": "hr:20", "quantity": 4, "deviceDataType": "Int64"},
        {"name": "status", "address": "ir:5", "quantity": 1, "deviceDataType": "UInt16"},
        {"name": "run", "address": "coil:3", "quantity": 1, "deviceDataType": "Boolean"},
        {"name": "alarm", "address": "di:7", "quantity": 1, "deviceDataType": "Boolean"},
        {"name": "model", "address": "hr:200", "quantity": 5, "deviceDataType": "String"},
    ],
}


def blocks(cfg: Any) -> list[tuple[Any, ...]]:
    parsed = cfg.parsed_items()
    return [
        (b.area, b.start, b.count, tuple(parsed[p.key].name for p in b.pieces))
        for b in build_plan(parsed, cfg.effective_parameters())
    ]


def test_an_ng_device_loads_and_plans_like_the_native_one(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, "edgemodbus.config"):
        ng = load_device_config(NG_DEVICE)
    assert not [r for r in caplog.records if "unknown" in r.getMessage().lower()]
    native = load_device_config(NATIVE_DEVICE)
    assert ng.communication == native.communication
    assert ng.communication.data_format is DataFormat.CDAB
    assert [it.to_dict() for it in ng.address_list] == [
        it.to_dict() for it in native.address_list
    ]
    assert blocks(ng) == blocks(native)
    assert len(blocks(ng)) == 5  # hr 0..23 merged (gap <= 10), hr 200, ir, coil, di
    temp = ng.address_list[0]
    assert (temp.name, temp.device_data_type, temp.data_multiplier) == (
        "Temperature", DataType.FLOAT, 0.1)


def test_ng_tcp_connection_and_numeric_orders() -> None:
    cfg = load_device_config({
        "communication": {"connection": {"kind": "tcp", "host": "10.0.0.5", "port": 1502},
                          "byteOrder": 1, "wordOrder": 0},
        "addressList": [],
    })
    comm = cfg.communication
    assert (comm.transport, comm.tcp_host, comm.tcp_port, comm.use_tcp) == (
        "tcp", "10.0.0.5", 1502, True)
    assert comm.data_format is DataFormat.BADC


@pytest.mark.parametrize(
    ("comm", "point", "expected"),
    [
        ({"connection": {"kind": "udp"}}, None, "connection.kind 'udp': use tcp"),
        ({"connection": {"kind": "tcp", "baudRate": 9600}}, None,
         "connection.baudrate 9600: not a tcp connection key"),
        ({"connection": {"kind": "tcp", "host": "a"}, "tcpHost": "b"}, None,
         "connection.host 'a': disagrees with tcpHost 'b'"),
        ({}, {"key": "x", "functionCode": 6, "address": 1, "dataType": "Int16"},
         "functionCode 6: a point is read with 1 (ReadCoils)"),
        ({}, {"key": "x", "functionCode": 3, "address": "ir:1", "dataType": "Int16"},
         "address 'ir:1': with functionCode give the offset alone"),
        ({}, {"key": "x", "address": 1, "dataType": "Int16", "deviceDataType": "Int32"},
         "dataType 'Int16' disagrees with deviceDataType 'Int32'"),
    ],
)
def test_ng_keys_errors_name_the_key(
    comm: dict[str, Any], point: dict[str, Any] | None, expected: str
) -> None:
    with pytest.raises(ConfigError) as err:
        load_device_config({"communication": comm, "points": [point] if point else []})
    assert expected in str(err.value)


def test_smart_cast_quantities_load_with_one_warning_per_item(
    caplog: pytest.LogCaptureFixture,
) -> None:
    device = {"addressList": [
        {"name": "ng_i16_q4", "address": "hr:0", "deviceDataType": "Int16", "quantity": 4},
        {"name": "ng_f_q1", "address": "hr:4", "deviceDataType": "Float", "quantity": 1},
        {"name": "ng_plain", "address": "hr:5", "deviceDataType": "Int32"},
    ]}
    with caplog.at_level(logging.WARNING, "edgemodbus.config"):
        cfg = load_device_config(device)
        cfg.parsed_items()
        load_device_config(device)
    texts = [r.getMessage() for r in caplog.records if "Smart Cast" in r.getMessage()]
    assert texts == [
        "addressList[0] ('ng_i16_q4'): Smart Cast: Int16 from 4 registers: read as Int64 "
        "and narrowed to Int16 (a value outside -32768..32767 makes the item Invalid)",
        "addressList[1] ('ng_f_q1'): Smart Cast: Float from 1 register: read as Int16 "
        "and widened to Float",
    ]
    assert [p.registers for p in cfg.parsed_items()] == [4, 1, 2]


# --- NG's maxBatch: default 100, and it bounds coil and discrete-input reads (#24) ----------

@pytest.mark.parametrize("communication", [
    {"maxGap": 10},  # an NG key, no maxBatch: NG's default
    {"connection": {"kind": "tcp", "host": "127.0.0.1"}},
])
def test_ng_keyed_files_default_max_batch_to_100(communication: dict[str, Any]) -> None:
    comm = load_device_config({"communication": communication}).communication
    assert comm.max_block_read_register_count == 100  # it was 120
    assert comm.max_block_read_bit_count == 100  # it was 2000
    points = load_device_config({"points": [
        {"key": "a", "functionCode": 3, "address": 0, "dataType": "UInt16"}]}).communication
    assert (points.max_block_read_register_count, points.max_block_read_bit_count) == (100, 100)
    native = load_device_config({"communication": {"maxMergeAddressGap": 10}}).communication
    assert (native.max_block_read_register_count, native.max_block_read_bit_count) == (120, 2000)


def test_max_batch_bounds_coils_and_discrete_inputs_as_registers() -> None:
    """NG: maxBatch is "寄存器数/线圈数", registers or coils of one read."""
    points = [{"key": f"c{fc}_{i}", "functionCode": fc, "address": i, "dataType": "Boolean"}
              for fc in (1, 2) for i in range(0, 150, 10)]
    cfg = load_device_config({"communication": {"maxBatch": 50, "maxGap": 10},
                              "points": points})
    spans = [(area.short_name, count) for area, _, count, _ in blocks(cfg)]
    assert spans and all(count <= 50 for _, count in spans), spans
    assert {name for name, _ in spans} == {"coil", "di"} and len(spans) == 6, spans
    # an explicit bit count stays
    cfg = load_device_config({"communication": {"maxBatch": 50, "maxBlockReadBitCount": 2000},
                              "points": points})
    assert cfg.communication.max_block_read_bit_count == 2000
    assert len(blocks(cfg)) == 2
