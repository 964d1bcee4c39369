"""Device templates: the search path, merging defaults and items, overrides by name,
disabling, address conversion to the device's numbering, and the errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError
from edgemodbus.config.templates import (
    SHIPPED_DIR,
    TEMPLATE_PATH_ENV,
    find_templates,
    search_path,
    template_bytes,
)
from edgemodbus.descriptor import driver_descriptor


def _template(folder: Path, name: str, **doc: Any) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    body = {"description": f"{name} for tests",
            "source": {"vendor": "Acme", "document": "AC-1 register map", "version": "1.0"},
            **doc}
    path = folder / f"{name}.json"
    path.write_text(json.dumps(body))
    return path


PUMP = {
    "communication": {"dataFormat": "CDAB", "maxBlockReadRegisterCount": 20,
                      "addressPrefix": "entity"},
    "itemDefaults": {"deviceDataType": "Float"},
    "addressList": [
        {"name": "Flow", "address": "30001", "unit": "m3/h"},
        {"name": "Head", "address": "30003"},
        {"name": "Mode", "address": "40010", "deviceDataType": "UInt16"},
        {"name": "Fault", "address": "10001", "deviceDataType": "Boolean"},
    ],
}


@pytest.fixture
def pump_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "site-templates"
    _template(folder, "acme-pump", **PUMP)
    monkeypatch.setenv(TEMPLATE_PATH_ENV, str(folder))
    return folder


def _errors(data: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as info:
        em.load_device_config(data)
    return [str(p) for p in info.value.problems]


def test_items_and_defaults_come_from_the_template(pump_dir: Path) -> None:
    cfg = em.load_device_config({"template": "acme-pump", "communication": {"slaveId": 4}})
    assert [i.name for i in cfg.address_list] == ["Flow", "Head", "Mode", "Fault"]
    # written in entity numbers, rewritten to the device's (function-code) numbering
    assert [i.address for i in cfg.address_list] == ["ir:0", "ir:2", "hr:9", "di:0"]
    assert [i.device_data_type.value for i in cfg.address_list] == [
        "Float", "Float", "UInt16", "Boolean"]
    comm = cfg.communication
    assert (comm.data_format.value, comm.max_block_read_register_count) == ("CDAB", 20)
    assert comm.address_prefix == "function-code" and comm.slave_id == 4
    assert cfg.address_list[0].unit == "m3/h"


def test_device_overrides_items_by_name_disables_and_adds(pump_dir: Path) -> None:
    cfg = em.load_device_config({
        "template": "acme-pump",
        "communication": {"maxBlockReadRegisterCount": 50},
        "addressList": [
            {"name": "Head", "dataMultiplier": 0.1, "unit": "m"},
            {"name": "Fault", "isEnable": False},
            {"name": "Speed", "address": "hr:20", "deviceDataType": "UInt16"},
        ],
    })
    items = {i.name: i for i in cfg.address_list}
    assert list(items) == ["Flow", "Head", "Mode", "Fault", "Speed"]
    assert (items["Head"].data_multiplier, items["Head"].unit) == (0.1, "m")
    assert items["Head"].address == "ir:2"
    assert items["Fault"].is_enable is False
    assert cfg.communication.max_block_read_register_count == 50
    planned = {p.name for p in cfg.parsed_items() if p.item.is_enable}
    assert "Fault" not in planned and "Speed" in planned


def test_device_numbering_is_used_for_template_addresses(pump_dir: Path) -> None:
    for comm, flow in (({"addressPrefix": "entity"}, "300001"),
                       ({"addressBase": 1}, "ir:1")):
        cfg = em.load_device_config({"template": "acme-pump", "communication": comm})
        assert cfg.address_list[0].address == flow
        assert str(cfg.parsed_items()[0].address) == "ir:0"


def test_to_dict_loads_back_to_the_same_device(pump_dir: Path) -> None:
    cfg = em.load_device_config({"template": "acme-pump",
                                 "addressList": [{"name": "Fault", "isEnable": False}]})
    again = em.load_device_config(cfg.to_dict(secrets=True))
    assert again.to_dict(secrets=True) == cfg.to_dict(secrets=True)


def test_unknown_template_names_field_value_and_search_path(pump_dir: Path) -> None:
    (line,) = _errors({"template": "acme-pmup"})
    assert line.startswith("template 'acme-pmup': no such template on the search path ")
    assert str(pump_dir) in line and str(SHIPPED_DIR) in line
    assert "did you mean 'acme-pump'?" in line


def test_an_override_with_a_bad_key_is_named(pump_dir: Path) -> None:
    lines = _errors({"template": "acme-pump",
                     "addressList": [{"name": "Head", "dataMultiplyer": 0.1}]})
    assert lines == [
        "addressList[0].dataMultiplyer 0.1: not a key here (did you mean 'dataMultiplier'? "
        "use name, address, deviceDataType, convertedDataType, dataMultiplier, description, "
        "unit, updateTs, status, isEnable, addressChanged, dataFormat ...): an override of "
        "template item 'Head'"]


def test_template_may_not_set_where_the_device_is(tmp_path: Path) -> None:
    _template(tmp_path, "bad", communication={"tcpHost": "10.0.0.1"}, addressList=[])
    (line,) = _errors({"template": "bad", "templateDirs": [str(tmp_path)]})
    assert line.startswith(f"template bad ({tmp_path / 'bad.json'}): communication.tcpHost "
                           "'10.0.0.1': not a key here (use dataFormat, ")


def test_template_file_errors_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "broken.json").write_text("{nope")
    (line,) = _errors({"template": "broken", "templateDirs": [str(tmp_path)]})
    assert line.startswith(f"template broken ({tmp_path / 'broken.json'}): invalid JSON")
    _template(tmp_path, "badaddr", addressList=[
        {"name": "x", "address": "hr:70000", "deviceDataType": "UInt16"}])
    (line,) = _errors({"template": "badaddr", "templateDirs": [str(tmp_path)]})
    assert "addressList[0].address 'hr:70000'" in line and "out of range 0..65535" in line


def test_template_dirs_are_relative_to_the_device_file(tmp_path: Path) -> None:
    _template(tmp_path / "tpl", "local", addressList=[
        {"name": "r", "address": "hr:1", "deviceDataType": "UInt16"}])
    device = tmp_path / "dev" / "device.json"
    device.parent.mkdir()
    device.write_text(json.dumps({"template": "local", "templateDirs": ["../tpl"]}))
    cfg = em.load_device_config(device)
    assert [i.address for i in cfg.address_list] == ["hr:1"]


def test_first_on_the_search_path_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _template(tmp_path / "a", "eastron-sdm120", description="site copy", addressList=[])
    monkeypatch.setenv(TEMPLATE_PATH_ENV, str(tmp_path / "a"))
    assert search_path()[-1] == SHIPPED_DIR
    found = {t.name: t for t in find_templates()}
    assert found["eastron-sdm120"].description == "site copy"
    assert em.load_device_config({"template": "eastron-sdm120"}).address_list == []


def test_descriptor_lists_the_templates_as_presets() -> None:
    desc = driver_descriptor()
    assert desc["supportsPresets"] is True
    names = [p["name"] for p in desc["presets"]]
    assert {"eastron-sdm120", "eastron-sdm630", "xy-md02", "waveshare-relay-d-8ch"} <= set(names)
    for preset in desc["presets"]:
        assert set(preset) == {"name", "description", "source"}


def test_the_readme_example_loads() -> None:
    """docs/device-files.md "Device templates": its device file loads as described."""
    doc = (Path(__file__).resolve().parents[3] / "docs" / "device-files.md").read_text("utf-8")
    section = doc.split("## Device templates", 1)[1]
    example = json.loads(section.split("```json", 1)[1].split("```", 1)[0])
    cfg = em.load_device_config(example)
    items = {i.name: i for i in cfg.address_list}
    assert len(items) == 15 and list(items)[-1] == "Relay"
    assert items["PhaseAngle"].is_enable is False
    assert items["ImportActiveEnergy"].deadband == 0.01
    assert items["Voltage"].address == "ir:0"
    assert (cfg.communication.baud_rate, cfg.communication.slave_id) == (2400, 7)


def test_errors_point_at_the_device_files_items(pump_dir: Path) -> None:
    """The merged list counts the template's items first; messages name the item as the
    device file (or the template) has it."""
    lines = _errors({"template": "acme-pump", "addressList": [
        {"name": "Fault", "deviceDataType": "Float"},
        {"name": "X", "address": "coil:1", "deviceDataType": "UInt16"}]})
    assert lines == [
        "addressList[0].deviceDataType (over template item 'Fault') 'Float': a discrete "
        "input holds one bit: use Boolean",
        "addressList[1].deviceDataType 'UInt16': a coil holds one bit: use Boolean"]
    (line,) = _errors({"template": "acme-pump", "addressList": [
        {"name": "X", "address": "hr:1", "deviceDataType": "Flot"}]})
    assert line.startswith("addressList[0].deviceDataType 'Flot': unknown data type")
    lines = _errors({"template": "acme-pump", "addressList": [
        {"name": "X", "address": "hr:1", "deviceDataType": "UInt16"},
        {"name": "X", "address": "hr:2", "deviceDataType": "UInt16"}]})
    assert lines == ["addressList[1].name 'X': duplicate item name (also addressList[0])"]


def test_template_bytes_follow_the_named_template(tmp_path: Path) -> None:
    """What the gateway adds to a device file's digest: a changed template reloads."""
    tpl = _template(tmp_path / "tpl", "local", addressList=[])
    device = tmp_path / "device.json"
    device.write_text(json.dumps({"Template": "local", "templateDirs": "tpl"}))
    assert template_bytes(device) == tpl.read_bytes()
    device.write_text(json.dumps({"template": "eastron-sdm120"}))
    assert template_bytes(device) == (SHIPPED_DIR / "eastron-sdm120.json").read_bytes()
    for text in ('{"template": "nowhere"}', "{}", "not json"):
        device.write_text(text)
        assert template_bytes(device) == b""
