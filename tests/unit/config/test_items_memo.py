"""An address list is validated once per distinct input (config/items.py's memo) and a
file's list once per distinct JSON (config/item_cache.py): the results are those of a
fresh validation, an item changed after it was checked is checked again, and every
file is still told its unknown keys."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgemodbus.config import (
    ConfigError,
    DeviceAddressItem,
    DriverModbusRtuParameter,
    item_cache,
    items,
    load_device_config,
    validate_items,
)
from edgemodbus.config.item_model import DeviceAddressItem as Item
from edgemodbus.datatypes import DataType
from tests.peers import free_port


def _file(tmp_path: Path, name: str, address_list: list[dict[str, Any]],
          dtu: str = "DTU1", port: int = 9502) -> Path:
    path = tmp_path / name
    path.write_text(json.dumps({
        "organization": {"deviceCode": name.removesuffix(".json")},
        "communication": {"transport": "rtu-over-tcp-server", "listenHost": "127.0.0.1",
                          "listenPort": port, "dtuId": dtu, "registration": "text",
                          "slaveId": 1},
        "addressList": address_list}))
    return path


def _template(n: int = 20) -> list[dict[str, Any]]:
    return [{"name": f"t{a}", "address": f"3:{a}", "deviceDataType": "UInt16"}
            for a in range(n)]


class _Recording:
    """A communication record that notes every field read."""

    def __init__(self, comm: DriverModbusRtuParameter) -> None:
        self.comm = comm
        self.read: set[str] = set()

    def __getattr__(self, name: str) -> Any:
        self.read.add(name)
        return getattr(self.comm, name)


_ITEM_KINDS: list[dict[str, Any]] = [
    {"address": "3:0", "deviceDataType": "UInt16"},
    {"address": "4:10", "deviceDataType": "Float", "dataFormat": "CDAB"},
    {"address": "hr:5.3", "deviceDataType": "Boolean"},
    {"address": "coil:7", "deviceDataType": "Boolean"},
    {"address": "3:20", "deviceDataType": "String", "quantity": 4, "encoding": "gbk"},
    {"address": "3:30", "deviceDataType": "UInt16", "readCycle": 500, "reportEvery": 100},
    {"address": "3:40", "deviceDataType": "Int32", "quantity": 1},  # Smart Cast
    {"address": "3:65535", "deviceDataType": "Int32"},  # past the end
    {"address": "40001", "deviceDataType": "UInt16"},  # refused under function-code
    {"address": "3:50", "deviceDataType": "UInt16", "readCycle": 0},  # needs wrapped
    {"address": "coil:1", "deviceDataType": "UInt16"},  # a bit area
]
_COMMS = [
    {}, {"addressPrefix": "entity"}, {"addressBase": 1, "dataFormat": "DCBA"},
    {"transport": "rtu-over-tcp", "tcpHost": "127.0.0.1", "framing": "wrapped-report",
     "reportEvery": 1000, "readCycle": 2000},
    {"byteSwap16": True, "encoding": "gbk", "reportMode": "cycle"},
]


def _outcome(call: Any) -> Any:
    try:
        parsed = call()
    except ConfigError as exc:
        return ("error", str(exc))
    return ("ok", [(p.item.name, p.address, p.data_type, p.data_format, p.byte_swap16,
                    p.registers, p.quantity, p.multiplier, p.encoding) for p in parsed])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.sampled_from(range(len(_ITEM_KINDS))), min_size=1, max_size=6),
       st.sampled_from(range(len(_COMMS))), st.booleans())
def test_the_memo_gives_what_a_fresh_validation_gives(kinds: list[int], comm_at: int,
                                                      same_names: bool) -> None:
    """Differential: validate_items (twice: computed, then from the memo, on new equal
    items) against the validation it caches, which reads only COMM_KEYS of comm."""
    comm = DriverModbusRtuParameter.model_validate(_COMMS[comm_at])

    def make() -> list[DeviceAddressItem]:
        return [Item(name="x" if same_names else f"i{k}", **_ITEM_KINDS[kind])
                for k, kind in enumerate(kinds)]

    recording = _Recording(comm)
    fresh = _outcome(lambda: items._validate(make(), recording))  # type: ignore[arg-type]
    assert recording.read <= set(items.COMM_KEYS), recording.read - set(items.COMM_KEYS)
    first, second = make(), make()
    assert _outcome(lambda: validate_items(first, comm)) == fresh
    got = _outcome(lambda: validate_items(second, comm))
    assert got == fresh
    if got[0] == "ok":  # the parsed items are the ones given, not the first list's
        assert [p.item for p in validate_items(second, comm)] == second
        assert all(p.item is it for p, it in zip(validate_items(second, comm), second,
                                                  strict=True))


def test_an_item_changed_after_its_check_is_checked_again() -> None:
    comm = DriverModbusRtuParameter()
    listed = [Item(name=f"t{a}", address=f"3:{a}", deviceDataType="UInt16")
              for a in range(3)]
    validate_items(listed, comm)
    listed[1].quantity = 0  # assigned, unvalidated (item_model.py)
    with pytest.raises(ConfigError, match=r"addressList\[1\]\.quantity"):
        validate_items(listed, comm)
    listed[1].quantity = 1
    assert validate_items(listed, comm)[1].quantity == 1
    listed[1].quantity = True  # equal to 1, not the same input: its own result
    assert validate_items(listed, comm)[1].quantity is True
    assert _outcome(lambda: validate_items(listed, comm)) == \
        _outcome(lambda: items._validate(listed, comm))
    listed[1].quantity = None
    listed[2].address = "3:65535"
    listed[2].device_data_type = DataType.INT32
    with pytest.raises(ConfigError, match=r"addressList\[2\]\.address"):
        validate_items(listed, comm)


def test_a_changed_option_is_a_new_input() -> None:
    listed = [Item(name="a", address="3:0", deviceDataType="UInt16")]
    assert validate_items(listed, DriverModbusRtuParameter())
    with pytest.raises(ConfigError, match=r"addressList\[0\]\.address"):
        validate_items(listed, DriverModbusRtuParameter(address_base=1))


def test_files_of_one_template_are_validated_once_from_load_to_start(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Provenance: the items a file loaded were checked then; starting the device (its
    effective options the same) checks nothing again, and the second file of the same
    list builds its items without pydantic.  Before, each load and each start parsed
    every address again."""
    import edgemodbus as em

    parsed_addresses: list[str] = []
    built: list[Any] = []
    real_parse, real_of = items.parse_address, Item.of.__func__  # type: ignore[attr-defined]

    def parse(address: str, *rest: Any) -> Any:
        parsed_addresses.append(address)
        return real_parse(address, *rest)

    def of(cls: type[Item], fields: Any) -> Item:
        built.append(fields)
        return real_of(cls, fields)  # type: ignore[no-any-return]

    monkeypatch.setattr(items, "parse_address", parse)
    monkeypatch.setattr(Item, "of", classmethod(of))
    template = _template(20)
    template[0]["description"] = f"memo test {tmp_path}"  # a list no other test loaded
    port = free_port()
    configs = [load_device_config(_file(tmp_path, f"d{k}.json", template, f"DTU{k}", port))
               for k in range(3)]
    assert len(built) == 20  # the first file's items; the others are copies
    a, b = configs[0].address_list, configs[1].address_list
    assert a == b and all(x is not y for x, y in zip(a, b, strict=True))  # (before a
    drivers = [em.DriverModbusRtu() for _ in configs]  # start tells each why it is down)
    try:
        for drv, cfg in zip(drivers, configs, strict=True):
            assert drv.start_device(cfg.organization, cfg.communication, cfg.address_list)
    finally:
        for drv in drivers:
            drv.stop_device()
    assert len(parsed_addresses) == 20, len(parsed_addresses)


def test_each_file_is_told_its_unknown_item_keys(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    listed = _template(2)
    listed[1]["colour"] = "red"
    with caplog.at_level(logging.WARNING, logger="edgemodbus"):
        for k in range(2):
            load_device_config(_file(tmp_path, f"u{k}.json", listed))
    told = [r.getMessage() for r in caplog.records if "colour" in r.getMessage()]
    assert len(told) == 2, told


def test_only_json_text_is_looked_up_and_nan_is_not_null(tmp_path: Path) -> None:
    listed = _template(1)
    listed[0]["deadband"] = None
    listed[0]["description"] = f"nan test {tmp_path}"
    load_device_config(_file(tmp_path, "n.json", listed))
    text = json.dumps({"addressList": [{**listed[0], "deadband": math.nan}]})
    with pytest.raises(ConfigError, match="deadband"):
        load_device_config(text)  # NaN, not the null of the file before
    assert item_cache.list_key([1]) is None  # outside a load of JSON text
    with pytest.raises(ConfigError, match="deadband"):
        load_device_config({"addressList": [{**listed[0], "deadband": -1.0}]})


def test_a_list_with_values_is_not_kept(tmp_path: Path) -> None:
    listed = _template(1)
    listed[0]["value"] = 5
    listed[0]["description"] = f"value test {tmp_path}"
    first = load_device_config(_file(tmp_path, "v0.json", listed))
    first.address_list[0].value = 7
    second = load_device_config(_file(tmp_path, "v1.json", listed))
    assert second.address_list[0].value == 5
