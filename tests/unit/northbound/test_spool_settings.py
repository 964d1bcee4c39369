"""``mqtt.storeAndForward`` in the gateway file: defaults, bounds and the spool's folder,
each refusal naming the field, the value and what is allowed."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.gateway.config import load_gateway_config


def gateway(spool: dict[str, Any]) -> dict[str, Any]:
    return {"gatewayId": "gw1", "mqtt": {"host": "127.0.0.1", "storeAndForward": spool}}


def test_defaults_and_a_relative_path_taken_from_the_gateway_files_folder(
        tmp_path: Path) -> None:
    (tmp_path / "var").mkdir()
    file = tmp_path / "gateway.json"
    file.write_text(json.dumps(gateway({"path": "var/spool.db", "maxBytes": 5_000_000})))
    cfg = load_gateway_config(file)
    assert cfg.mqtt is not None and cfg.mqtt.store_and_forward is not None
    s = cfg.mqtt.store_and_forward
    assert s.path == str(tmp_path / "var" / "spool.db")
    assert (s.max_bytes, s.max_age_s, s.replay_rate_per_s) == (5_000_000, 604_800, 500.0)
    assert s.replay_bytes_per_s is None and s.synchronous == "normal"
    assert load_gateway_config({"mqtt": {}}).mqtt.store_and_forward is None  # type: ignore[union-attr]


def test_a_missing_directory_names_the_field_and_the_value(tmp_path: Path) -> None:
    missing = str(tmp_path / "nope" / "spool.db")
    with pytest.raises(ConfigError) as err:
        load_gateway_config(gateway({"path": missing}))
    [problem] = err.value.problems
    assert problem.path == "mqtt.storeAndForward.path" and problem.value == missing
    assert f"its directory {str(tmp_path / 'nope')!r} does not exist" in str(err.value)
    with pytest.raises(ConfigError, match=r"mqtt\.storeAndForward\.path .*is a directory"):
        load_gateway_config(gateway({"path": str(tmp_path)}))


@pytest.mark.parametrize("field, value, allowed", [
    ("maxBytes", 0, "65536 or more"),
    ("maxBytes", 65535, "65536 or more"),  # the file's floor: SQLite's own pages
    ("memoryQueueSize", -1, "0..10000000"),
    ("maxAgeS", 0, "1 or more"),
    ("replayRatePerS", 0, "0.01 or more"),
    ("replayBytesPerS", -1, "1 or more"),
    ("synchronous", "off", "'normal'"),
])
def test_bounds_refused_with_field_value_and_allowed(
        tmp_path: Path, field: str, value: Any, allowed: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_gateway_config(gateway({"path": str(tmp_path / "s.db"), field: value}))
    text = str(err.value)
    assert f"mqtt.storeAndForward.{field}" in text and repr(value) in text.replace('"', "'")
    assert allowed in text


def test_the_path_is_required(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"mqtt\.storeAndForward\.path"):
        load_gateway_config(gateway({"maxBytes": 10}))
    with pytest.raises(ConfigError, match=r"mqtt\.storeAndForward\.path .*must not be empty"):
        load_gateway_config(gateway({"path": " "}))


def test_a_fifo_or_a_device_as_the_spool_is_a_field_error(tmp_path: Path) -> None:
    """Before: both passed the check at load; at start a FIFO raised sqlite3's
    OperationalError "disk I/O error" (a traceback), /dev/null the same words."""
    fifo = tmp_path / "spool.db"
    os.mkfifo(fifo)
    for path, kind in ((str(fifo), "a FIFO"), ("/dev/null", "a character device")):
        with pytest.raises(ConfigError) as err:
            load_gateway_config(gateway({"path": path}))
        [problem] = err.value.problems
        assert problem.path == "mqtt.storeAndForward.path" and problem.value == path
        assert f"is {kind}, not a regular file" in str(err.value)
