"""Sparkplug settings in the gateway file: docs/gateway.md's example loads, and every mistake
is an error that names the field, the value and what is allowed."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.gateway.config import load_gateway_config
from edgemodbus.northbound.sparkplug.bdseq import MAGIC, BdSeqStore
from edgemodbus.northbound.sparkplug.publisher import SparkplugPublisher
from tests.fake_brokers import self_signed_cert

ROOT = Path(__file__).resolve().parents[3]


def readme_example() -> dict[str, object]:
    text = (ROOT / "docs" / "gateway.md").read_text()
    section = text[text.index("## Sparkplug B"):]
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


def sparkplug_gateway(tmp_path: Path, **sparkplug: object) -> Path:
    path = tmp_path / "gateway.json"
    path.write_text(json.dumps({"gatewayId": "gw", "mqtt": {
        "mode": "sparkplug", "sparkplug": {"groupId": "g", **sparkplug}}}))
    return path


def test_bd_seq_file_that_is_not_ours_is_refused_not_overwritten(tmp_path: Path) -> None:
    """The issue's case: bdSeqFile names the gateway file itself.  It was warned about,
    then overwritten with "1"; now the error names the field, the path and what it
    holds, at load and when a publisher is made, and the file is left alone."""
    path = sparkplug_gateway(tmp_path, bdSeqFile="gateway.json")
    before = path.read_bytes()
    with pytest.raises(ConfigError) as info:
        load_gateway_config(path)
    assert str(info.value).startswith(
        f"mqtt.sparkplug.bdSeqFile '{path}': exists and is not an edgemodbus bdSeq file "
        "(found '{\"gatewayId\": \"gw\", \"mqtt\": {\"mode\": \"sp'... (110 characters)); "
        "give another path, or remove it if it is no longer used")
    with pytest.raises(ConfigError, match="is not an edgemodbus bdSeq file"):
        SparkplugPublisher({"mode": "sparkplug", "sparkplug": {"groupId": "g",
                                                               "bdSeqFile": str(path)}})
    assert path.read_bytes() == before


def test_bd_seq_is_written_atomically_in_our_format(tmp_path: Path) -> None:
    store = BdSeqStore(str(tmp_path / "bdseq"))
    assert store.load() == 0
    store.save(7)
    assert (tmp_path / "bdseq").read_text() == f"{MAGIC}\n7\n"
    assert [p.name for p in tmp_path.iterdir()] == ["bdseq"]  # no temporary file left
    assert store.load() == 7
    (tmp_path / "bdseq").write_text("42\n")  # what earlier versions wrote
    assert store.load() == 42
    (tmp_path / "bdseq").write_text("")
    assert store.load() == 0
    for foreign in ("256", "-1", "x", f"{MAGIC}\n", "1\n2"):
        (tmp_path / "bdseq").write_text(foreign)
        with pytest.raises(ConfigError, match="bdSeqFile"):
            store.load()


def test_the_gateway_keeps_bd_seq_by_default(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Without bdSeqFile the gateway keeps it in $STATE_DIRECTORY (systemd), else beside
    the gateway file, so bdSeq goes on increasing across restarts."""
    path = sparkplug_gateway(tmp_path)
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    sp = load_gateway_config(path).mqtt.sparkplug  # type: ignore[union-attr]
    assert sp is not None and sp.bd_seq_file == str(tmp_path / "sparkplug.bdseq")
    state = tmp_path / "state"
    state.mkdir()
    monkeypatch.setenv("STATE_DIRECTORY", f"{state}:/var/lib/other")
    sp = load_gateway_config(path).mqtt.sparkplug  # type: ignore[union-attr]
    assert sp is not None and sp.bd_seq_file == str(state / "sparkplug.bdseq")
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "missing"))
    sp = load_gateway_config(path).mqtt.sparkplug  # type: ignore[union-attr]
    assert sp is not None and sp.bd_seq_file is None  # warned: kept in memory


def test_rebirth_interval_is_checked() -> None:
    text = error({"mqtt": {"mode": "sparkplug",
                           "sparkplug": {"groupId": "g", "rebirthInterval": -1}}})
    assert text.startswith("mqtt.sparkplug.rebirthInterval -1: ")
