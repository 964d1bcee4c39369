"""Sparkplug settings in the gateway file: the README's example loads, and every mistake
is an error that names the field, the value and what is allowed."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.gateway.config import load_gateway_config
from tests.fake_brokers import self_signed_cert

ROOT = Path(__file__).resolve().parents[3]


def readme_example() -> dict[str, object]:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("### Sparkplug B"):]
    block = re.search(r"```json\n(.*?)```", section, re.S)
    assert block is not None
    data: dict[str, object] = json.loads(block.group(1))
    return data


def test_the_readme_example_loads_with_paths_from_the_files_folder(tmp_path: Path) -> None:
    cert, _key = self_signed_cert(tmp_path)
    cert.rename(tmp_path / "ca.pem")
    path = tmp_path / "gateway.json"
    path.write_text(json.dumps(readme_example()))
    cfg = load_gateway_config(path)
    assert cfg.mqtt is not None and cfg.mqtt.mode == "sparkplug"
    sp = cfg.mqtt.sparkplug
    assert sp is not None
    assert (sp.group_id, sp.edge_node_id, sp.primary_host_id) == ("plant1", "line3", "scada")
    assert sp.bd_seq_file == str(tmp_path / "bdseq")


def error(data: dict[str, object]) -> str:
    with pytest.raises(ConfigError) as info:
        load_gateway_config(data)
    return str(info.value)


def test_mode_and_section_errors_name_the_field() -> None:
    assert error({"mqtt": {"mode": "sparkplugb"}}) == (
        "mqtt.mode 'sparkplugb': must be 'per-item', 'batch' or 'sparkplug'")
    assert 'mqtt: mode "sparkplug" needs the section mqtt.sparkplug' in error(
        {"mqtt": {"mode": "sparkplug"}})
    assert error({"mqtt": {"mode": "sparkplug", "sparkplug": {}}}) == (
        "mqtt.sparkplug.groupId: required")
    text = error({"mqtt": {"mode": "sparkplug", "sparkplug": {"groupId": "a/b"}}})
    assert text.startswith("mqtt.sparkplug.groupId 'a/b': ") and "'/'" in text
    text = error({"mqtt": {"mode": "sparkplug",
                           "sparkplug": {"groupId": "g", "primaryHostId": "h#"}}})
    assert text.startswith("mqtt.sparkplug.primaryHostId 'h#': ") and "'#'" in text


def test_bd_seq_file_whose_folder_is_missing_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "bdseq"
    text = error({"mqtt": {"mode": "sparkplug",
                           "sparkplug": {"groupId": "g", "bdSeqFile": str(missing)}}})
    assert text == (f"mqtt.sparkplug.bdSeqFile '{missing}': its directory "
                    f"{missing.parent} does not exist")
    text = error({"mqtt": {"mode": "sparkplug",
                           "sparkplug": {"groupId": "g", "bdSeqFile": str(tmp_path)}}})
    assert text.startswith(f"mqtt.sparkplug.bdSeqFile '{tmp_path}': is a directory")


def test_per_item_mode_ignores_the_sparkplug_section(tmp_path: Path) -> None:
    cfg = load_gateway_config({"mqtt": {"sparkplug": {"groupId": "g",
                                                      "bdSeqFile": "/nowhere/x"}}})
    assert cfg.mqtt is not None and cfg.mqtt.mode == "per-item"
