"""Config models: the seed's files load, key spellings, ranges, errors with paths,
overrides, item validation against the communication options."""

from __future__ import annotations

import json
import logging
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.config import (
    ConfigError,
    DeviceAddressItem,
    DeviceConfig,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    Parity,
    Range,
    device_enabled,
    effective_parameters,
    load_communication,
    load_device_config,
    validate_items,
)
from edgemodbus.datatypes import Area, DataFormat, DataType, DeviceDriverStatus, ItemStatus
from edgemodbus.line.endpoint import LineTiming
from edgemodbus.protocol.address import Address

DATA = Path(__file__).resolve().parents[2] / "data"
SEED_DEVICE = DATA / "seed-device.json"
SEED_RTU = DATA / "modbusRtu.json"


def item(name: str, address: str, dtype: str = "Int16", **extra: Any) -> dict[str, Any]:
    return {"name": name, "address": address, "deviceDataType": dtype, **extra}


def errors_of(source: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config(source)
    return [str(p) for p in info.value.problems]


# ----------------------------------------------------------------------------- seed files


def test_seed_device_file_loads() -> None:
    cfg = load_device_config(SEED_DEVICE)
    assert cfg.driver_type == "DriverModbusRtu"
    org = cfg.organization
    assert org.device_code == "Mod002" and org.is_enable is False
    assert org.created_at == datetime(2026, 1, 18, 12, 6, 26, 165781, tzinfo=timezone.utc)
    comm = cfg.communication
    assert comm.use_tcp is True and comm.transport == "rtu-over-tcp"
    assert (comm.tcp_host, comm.tcp_port, comm.slave_id) == ("127.0.0.1", 1502, 2)
    assert comm.parity is Parity.NONE and comm.data_format is DataFormat.ABCD
    assert len(cfg.address_list) == 14
    pooled = cfg.address_list[0]
    assert pooled.name == "pooled" and pooled.device_data_type is DataType.INT16
    assert pooled.converted_data_type is DataType.FLOAT and pooled.data_multiplier == 0.1
    assert pooled.description == "压力传感器\uff08pooled\uff09"
    assert pooled.status is ItemStatus.OK
    # .NET writes 7 fractional digits.
    assert pooled.update_ts == datetime(2026, 1, 18, 12, 16, 58, 964471, tzinfo=timezone.utc)
    assert cfg.address_list[1].converted_data_type is None
    parsed = cfg.parsed_items()
    assert parsed[0].address == Address(Area.HOLDING_REGISTER, 5)
    assert parsed[-1].address == Address(Area.HOLDING_REGISTER, 99)
    assert {p.registers for p in parsed} == {1}
    # Organisation disables the device and overrides timings.
    assert cfg.enabled is False
    eff = cfg.effective_parameters()
    assert (eff.read_cycle, eff.connect_timeout, eff.reconnect_interval) == (1000, 5000, 10000)
    assert comm.reconnect_interval == 5000  # the original is untouched


def test_seed_modbus_rtu_json_pascal_case_loads() -> None:
    comm = load_communication(SEED_RTU)
    assert comm.com_port == "COM1" and comm.baud_rate == 19200
    assert comm.parity is Parity.NONE and comm.read_timeout == 3000 and comm.read_cycle == 5000
    assert comm.tcp_host == "192.168.0.10" and comm.max_merge_address_gap == 5
    assert comm.transport == "rtu" and comm.is_enable is True


def test_sources_path_str_json_and_dict(tmp_path: Path) -> None:
    text = SEED_DEVICE.read_text(encoding="utf-8")
    from_path = load_device_config(SEED_DEVICE)
    assert load_device_config(str(SEED_DEVICE)) == from_path
    assert load_device_config(text) == from_path
    assert load_device_config(json.loads(text)) == from_path
    bom = tmp_path / "bom.json"
    bom.write_text("\ufeff" + text, encoding="utf-8")
    assert load_device_config(bom) == from_path


def test_to_dict_is_camel_case_json_and_round_trips() -> None:
    cfg = load_device_config(SEED_DEVICE)
    data = cfg.to_dict()
    json.dumps(data)
    assert data["communication"]["maxMergeAddressGap"] == 10
    assert data["communication"]["parity"] == "N"
    assert data["addressList"][1]["convertedDataType"] == ""
    assert data["addressList"][0]["deviceDataType"] == "Int16"
    assert load_device_config(data) == cfg


def test_defaults() -> None:
    comm = DriverModbusRtuParameter()
    assert (comm.com_port, comm.baud_rate, comm.data_bits, comm.stop_bits) == ("COM1", 9600, 8, 1)
    assert comm.parity is Parity.NONE and comm.slave_id == 1
    assert (comm.read_timeout, comm.read_cycle, comm.connect_timeout) == (1000, 1000, 3000)
    assert comm.reconnect_interval == 5000 and comm.byte_timeout == 200
    assert comm.max_block_read_register_count == 120 and comm.max_merge_address_gap == 10
    assert comm.max_block_read_bit_count == 2000 and comm.retries == 1
    assert comm.transport == "rtu" and comm.use_tcp is False
    assert comm.address_prefix == "function-code" and comm.address_base == 0
    assert comm.report_mode == "change" and comm.encoding == "utf-8"
    assert comm.write_single_register_function == 6 and comm.request_interval == 0
    assert comm.settle_timeout is None  # the line settles for one response timeout
    assert comm.offline_after_failed_cycles == 3 and comm.max_backoff == 60000
    assert comm.rs485 == "none" and comm.echo is False and comm.snapshot_interval == 0
    assert LineTiming(response_timeout=1.0).settle == 1.0
    assert LineTiming(response_timeout=1.0, settle_timeout=0.0).settle == 0.0


# ----------------------------------------------------------------------------- key spellings


@pytest.mark.parametrize(
    "key", ["maxMergeAddressGap", "MaxMergeAddressGap", "max_merge_address_gap"]
)
def test_key_spellings(key: str) -> None:
    assert DriverModbusRtuParameter.model_validate({key: 3}).max_merge_address_gap == 3


def test_key_given_twice_is_an_error() -> None:
    assert errors_of({"communication": {"comPort": "a", "ComPort": "b"}}) == [
        "communication.comPort 'b': given twice (also as 'comPort')"
    ]


def test_unknown_keys_are_warned_with_paths(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="edgemodbus.config")
    cfg = load_device_config(
        {
            "bogus": 1,
            "organization": {"deviceCode": "x", "colour": "red"},
            "communication": {"Speed": 1},
            "addressList": [item("a", "hr:1"), item("b", "hr:2", Gain=2)],
        }
    )
    assert len(cfg.address_list) == 2
    messages = [r.getMessage() for r in caplog.records if r.name == "edgemodbus.config"]
    assert "<root>: unknown key 'bogus' ignored" in messages
    assert "organization: unknown key 'colour' ignored" in messages
    assert "communication: unknown key 'Speed' ignored" in messages
    assert "addressList[1]: unknown key 'Gain' ignored" in messages
    assert len(messages) == 4


# ----------------------------------------------------------------------------- values


@pytest.mark.parametrize(
    ("raw", "parity"),
    [
        ("None", Parity.NONE),
        ("odd", Parity.ODD),
        ("EVEN", Parity.EVEN),
        (0, Parity.NONE),
        (1, Parity.ODD),
        (2, Parity.EVEN),
        ("N", Parity.NONE),
        ("O", Parity.ODD),
        ("e", Parity.EVEN),
    ],
)
def test_parity_spellings(raw: Any, parity: Parity) -> None:
    assert DriverModbusRtuParameter.model_validate({"parity": raw}).parity is parity


@pytest.mark.parametrize("raw", ["Mark", 3, True, None])
def test_bad_parity(raw: Any) -> None:
    assert errors_of({"communication": {"parity": raw}}) == [
        f"communication.parity {raw!r}: use None|Odd|Even, 0|1|2 or N|O|E"
    ]


def ranged_fields() -> list[tuple[str, str, Range]]:
    out = []
    for name, field in DriverModbusRtuParameter.model_fields.items():
        for meta in field.metadata:
            if isinstance(meta, Range):
                out.append((name, field.alias or name, meta))
    return out


@pytest.mark.parametrize(("name", "key", "rng"), ranged_fields())
def test_every_range_is_enforced_with_path_value_and_bounds(
    name: str, key: str, rng: Range
) -> None:
    base = {"transport": "tcp"}  # slaveId 0..255 is valid on Modbus TCP
    lo = int(rng.lo)
    assert getattr(DriverModbusRtuParameter.model_validate({**base, key: lo}), name) == lo
    assert errors_of({"communication": {**base, key: lo - 1}}) == [
        f"communication.{key} {lo - 1}: must be {rng.describe()}"
    ]
    if rng.hi is not None:
        hi = int(rng.hi)
        assert getattr(DriverModbusRtuParameter.model_validate({**base, key: hi}), name) == hi
        assert errors_of({"communication": {**base, key: hi + 1}}) == [
            f"communication.{key} {hi + 1}: must be {lo}..{hi}"
        ]


def test_example_error_message() -> None:
    assert errors_of({"communication": {"baudRate": 300}}) == [
        "communication.baudRate 300: must be 1200..921600"
    ]


def test_choices() -> None:
    assert errors_of({"communication": {"stopBits": 3, "writeSingleRegisterFunction": 5}}) == [
        "communication.stopBits 3: must be 1 or 2",
        "communication.writeSingleRegisterFunction 5: must be 6 or 16",
    ]
    assert DriverModbusRtuParameter(stop_bits=2, write_single_register_function=16).stop_bits == 2
    problems = errors_of({"communication": {"transport": "udp", "rs485": "RTS-UP"}})
    assert len(problems) == 1 and problems[0].startswith("communication.transport 'udp': ")
    assert "'rtu', 'rtu-over-tcp', 'tcp' or 'mqtt-dtu'" in problems[0]
    assert DriverModbusRtuParameter.model_validate({"rs485": "RTS-UP"}).rs485 == "rts-up"


def test_encoding_must_be_known() -> None:
    assert DriverModbusRtuParameter(encoding="gbk").encoding == "gbk"
    (problem,) = errors_of({"communication": {"encoding": "klingon"}})
    assert problem.startswith("communication.encoding 'klingon': unknown text encoding")


def test_transport_from_use_tcp_and_conflicts() -> None:
    assert DriverModbusRtuParameter(use_tcp=True).transport == "rtu-over-tcp"
    assert DriverModbusRtuParameter(use_tcp=False).transport == "rtu"
    tcp = DriverModbusRtuParameter.model_validate({"transport": "TCP"})
    assert tcp.transport == "tcp" and tcp.use_tcp is True
    assert DriverModbusRtuParameter(transport="rtu-over-tcp", use_tcp=True).use_tcp is True
    assert errors_of({"communication": {"transport": "rtu", "useTcp": True}}) == [
        "communication.useTcp True: contradicts transport 'rtu'"
    ]


def test_slave_id_depends_on_transport() -> None:
    assert DriverModbusRtuParameter(transport="tcp", slave_id=0).slave_id == 0
    assert DriverModbusRtuParameter(transport="tcp", slave_id=255).slave_id == 255
    assert DriverModbusRtuParameter(slave_id=247).slave_id == 247
    for transport in ("rtu", "rtu-over-tcp"):
        for sid in (0, 248):
            assert errors_of({"communication": {"transport": transport, "slaveId": sid}}) == [
                f"communication.slaveId {sid}: must be 1..247 on an RTU line "
                f"(transport {transport!r}); 0..255 only as a Modbus TCP unit id"
            ]


def test_ng_aliases() -> None:
    comm = DriverModbusRtuParameter.model_validate(
        {"maxGap": 4, "maxBatch": 60, "byteOrder": "LittleEndian", "wordOrder": "BigEndian"}
    )
    assert comm.max_merge_address_gap == 4 and comm.max_block_read_register_count == 60
    assert comm.data_format is DataFormat.BADC
    assert DriverModbusRtuParameter.model_validate({"wordOrder": "LittleEndian"}).data_format is (
        DataFormat.CDAB
    )
    assert errors_of(
        {"communication": {"maxGap": 4, "maxMergeAddressGap": 5, "byteOrder": "x"}}
    ) == [
        "communication.maxGap 4: disagrees with maxMergeAddressGap 5",
        "communication.byteOrder/wordOrder: byteOrder 'x': use BigEndian or LittleEndian",
    ]
    assert errors_of({"communication": {"byteOrder": "LittleEndian", "dataFormat": "ABCD"}}) == [
        "communication.dataFormat 'ABCD': disagrees with byteOrder/wordOrder (BADC)"
    ]


def test_several_problems_reported_at_once() -> None:
    problems = errors_of(
        {"communication": {"baudRate": 300, "dataBits": 9, "tcpPort": 0}, "addressList": "x"}
    )
    assert problems[:3] == [
        "communication.baudRate 300: must be 1200..921600",
        "communication.dataBits 9: must be 5..8",
        "communication.tcpPort 0: must be 1..65535",
    ]
    assert problems[3].startswith("addressList 'x': ")


def test_bad_json_and_non_object(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"communication": ', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.json: invalid JSON: .* line 1 column 19"):
        load_device_config(bad)
    with pytest.raises(ConfigError, match="must hold a JSON object"):
        load_device_config("[1, 2]")
    with pytest.raises(FileNotFoundError):
        load_device_config(tmp_path / "missing.json")


# ----------------------------------------------------------------------------- organisation


def test_effective_parameters_and_enable() -> None:
    comm = DriverModbusRtuParameter(read_cycle=500, connect_timeout=100)
    org = DeviceOrganizationParameter(read_cycle=2000)
    eff = effective_parameters(org, comm)
    assert (eff.read_cycle, eff.connect_timeout) == (2000, 100)
    assert effective_parameters(None, comm) == comm
    assert device_enabled(None, comm) is True
    assert device_enabled(DeviceOrganizationParameter(), comm) is True
    assert device_enabled(DeviceOrganizationParameter(is_enable=False), comm) is False
    off = DriverModbusRtuParameter(is_enable=False)
    assert device_enabled(DeviceOrganizationParameter(is_enable=True), off) is False
    assert errors_of({"organization": {"readCycle": -1}}) == [
        "organization.readCycle -1: must be 0..86400000"
    ]


# ----------------------------------------------------------------------------- items


def test_item_errors_name_paths() -> None:
    problems = errors_of(
        {
            "addressList": [
                item("ok", "hr:1"),
                item("", "hr:1"),
                item("x", "hr:1", "Int17"),
                item("y", "5:100"),
                item("z", "hr:1", dataFormat="ABDC", dataMultiplier=0),
            ]
        }
    )
    assert problems == [
        "addressList[1].name '': an item needs a non-empty name",
        "addressList[2].deviceDataType 'Int17': unknown data type 'Int17' (use one of "
        + ", ".join(t.value for t in DataType)
        + ")",
        "addressList[3].address '5:100': unknown type '5' "
        "(use coil|c|1, di|discreteinput|2, hr|holding|3, ir|input|4)",
        "addressList[4].dataMultiplier 0: must be a finite number other than 0",
        "addressList[4].dataFormat 'ABDC': unknown data format 'ABDC' "
        "(use ABCD, BADC, CDAB or DCBA)",
    ]


def test_cross_checks_against_communication() -> None:
    problems = errors_of(
        {
            "addressList": [
                item("tag1", "hr:1"),
                item("tag1", "hr:2"),
                item("s", "hr:10", "String"),
                item("f", "hr:1.3", "Float"),
                item("c", "coil:1", "Int16"),
                item("d", "di:1", "String", quantity=4),
                item("q", "hr:1", "Boolean", quantity=2),
                item("w", "hr:65535", "Float"),
                item("b", "coil:1", "Boolean", quantity=2),
            ]
        }
    )
    assert problems == [
        "addressList[1].name 'tag1': duplicate item name (also addressList[0])",
        "addressList[2].quantity: String needs quantity (its length in registers)",
        "addressList[3].deviceDataType 'Float': a bit address (.N) reads one bit: use Boolean",
        "addressList[4].deviceDataType 'Int16': a coil holds one bit: use Boolean",
        "addressList[5].deviceDataType 'String': a discrete input holds one bit: use Boolean",
        "addressList[5].quantity 4: a discrete input holds one bit: use 1 or leave it out",
        "addressList[6].quantity 2: Boolean allows quantity 1 (or leave it out)",
        "addressList[7].address 'hr:65535': 2 registers from here run past the last address 65535",
        "addressList[8].quantity 2: a coil holds one bit: use 1 or leave it out",
    ]


def test_prefix_and_base_options_apply_to_items() -> None:
    items = [item("a", "3:00001"), item("b", "4:00001"), item("c", "hr:65536")]
    cfg = load_device_config(
        {"communication": {"addressPrefix": "modicon", "addressBase": 1}, "addressList": items}
    )
    assert [p.address for p in cfg.parsed_items()] == [
        Address(Area.INPUT_REGISTER, 0),
        Address(Area.HOLDING_REGISTER, 0),
        Address(Area.HOLDING_REGISTER, 65535),
    ]
    assert errors_of({"addressList": [item("c", "hr:65536")]}) == [
        "addressList[0].address 'hr:65536': offset 65536 out of range 0..65535"
    ]
    assert errors_of({"communication": {"addressBase": 1}, "addressList": [item("z", "hr:0")]}) == [
        "addressList[0].address 'hr:0': offset 0 out of range 1..65536 (addressBase 1)"
    ]


def test_parsed_item_fields() -> None:
    comm = DriverModbusRtuParameter(data_format="CDAB", encoding="gbk")
    items = [
        DeviceAddressItem.model_validate(item("f", "ir:10", "Float32", dataMultiplier=0.5)),
        DeviceAddressItem.model_validate(
            item("s", "hr:20", "String", quantity=8, encoding="utf-8", dataFormat="BADC")
        ),
        DeviceAddressItem.model_validate(item("d", "hr:30", "Double", quantity=2, deadband=0.1)),
        DeviceAddressItem.model_validate(item("t", "hr:40", "Timestamp", quantity=4)),
        DeviceAddressItem.model_validate(item("bit", "hr:50.7", "Boolean")),
        DeviceAddressItem.model_validate(item("di", "discreteinput:3", "bool")),
        DeviceAddressItem.model_validate(item("l", "hr:60", "Int64", convertedDataType="Double")),
    ]
    parsed = validate_items(items, comm)
    assert [p.registers for p in parsed] == [2, 8, 2, 4, 1, 1, 4]
    f, s, d, t, bit, di, long = parsed
    assert f.item is items[0] and f.name == "f"
    assert f.data_type is DataType.FLOAT and f.multiplier == 0.5 and f.quantity is None
    assert f.data_format is DataFormat.CDAB and f.encoding == "gbk"
    assert s.data_format is DataFormat.BADC and s.encoding == "utf-8" and s.quantity == 8
    assert d.deadband == 0.1 and d.quantity == 2
    assert t.data_type is DataType.TIMESTAMP
    assert bit.address == Address(Area.HOLDING_REGISTER, 50, 7)
    assert di.address.area is Area.DISCRETE_INPUT and di.data_type is DataType.BOOLEAN
    assert long.converted_type is DataType.DOUBLE


def test_validate_items_raises_one_error_listing_all() -> None:
    comm = DriverModbusRtuParameter()
    items = [
        DeviceAddressItem(name="a", address="hr:1", device_data_type=DataType.INT16),
        DeviceAddressItem(name="a", address="coil:1", device_data_type=DataType.FLOAT),
    ]
    with pytest.raises(ConfigError) as info:
        validate_items(items, comm)
    assert len(info.value.problems) == 2
    assert "addressList[1].name 'a': duplicate item name" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_item_field_ranges() -> None:
    assert errors_of({"addressList": [item("a", "hr:1", "String", quantity=0, deadband=-1)]}) == [
        "addressList[0].quantity 0: must be 1..125",
        "addressList[0].deadband -1: must be 0 or more",
    ]


def test_runtime_fields_are_plain_cheap_assignments() -> None:
    it = DeviceAddressItem(name="a", address="hr:1", device_data_type=DataType.INT16)
    assert it.status is ItemStatus.UNKNOWN and it.value is None and it.error_reason is None
    it.value = b"\x00\x01"
    it.status = ItemStatus.INVALID
    it.error_reason = "timeout"
    it.update_ts = datetime.now(timezone.utc)
    assert it.to_dict()["value"] == "AAE="  # bytes serialise as base64
    assert it.to_dict()["status"] == "Invalid"
    n = 20000
    t0 = time.perf_counter()
    for i in range(n):
        it.value = i
        it.status = ItemStatus.OK
    per_assignment = (time.perf_counter() - t0) / (2 * n)
    assert per_assignment < 5e-6  # no validation on assignment (about 0.15 us measured)


def test_status_enums() -> None:
    assert [s.value for s in ItemStatus] == ["Unknown", "Ok", "Invalid"]
    assert [s.value for s in DeviceDriverStatus] == [
        "Stopped",
        "Disabled",
        "Connecting",
        "Running",
        "Offline",
        "Reconnecting",
    ]
    assert ItemStatus.OK == "Ok" and DeviceDriverStatus.RUNNING == "Running"
    loaded = DeviceAddressItem.model_validate(item("a", "hr:1", status="invalid"))
    assert loaded.status is ItemStatus.INVALID


def test_device_config_keeps_item_instances() -> None:
    it = DeviceAddressItem(name="a", address="hr:1", device_data_type=DataType.INT16)
    cfg = DeviceConfig(address_list=[it])
    assert cfg.address_list[0] is it
