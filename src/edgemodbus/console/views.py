"""What the console's pages show, as JSON-able dicts, without the server: the overview
row of a device, a device's tags, and the commissioning steps (check a device document,
its read plan, save it into the config folder).  Pure functions of the drivers and the
config models, unit-tested without a socket (tests/unit/console/)."""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

from ..codec import jsonable
from ..config import ConfigError, DeviceConfig, load_device_config
from ..driver import DriverModbusRtu
from ..line.endpoint import endpoint_for
from ..poll.poller import build_plan
from .host import HostDevice

FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,100}\.json")
"""A device file the console may write: a plain name in the config folder."""

COUNTERS = ("cycles", "failedCycles", "requests", "responses", "timeouts", "crcErrors",
            "protocolErrors", "retries", "writes", "writeErrors", "overruns")


def line_name(cfg: DeviceConfig) -> str:
    """The line a device is on, in words (the endpoint's own description)."""
    return str(endpoint_for(cfg.effective_parameters()).describe())


def last_error(driver: DriverModbusRtu) -> str | None:
    """Why the device is not all good: the reason of its first Invalid item, if any."""
    for item in driver.address_items:
        if item.error_reason and str(getattr(item.status, "value", item.status)) == "Invalid":
            return str(item.error_reason)
    return None


def device_row(dev: HostDevice) -> dict[str, Any]:
    """One line of the overview: status, last error, cycle time, request counters."""
    stats = dev.driver.stats()
    row: dict[str, Any] = {
        "code": dev.code,
        "file": dev.path.name,
        "line": line_name(dev.cfg),
        "slaveId": dev.cfg.effective_parameters().slave_id,
        "status": dev.driver.device_driver_status.value,
        "items": dev.driver.data_item_count,
        "lastError": last_error(dev.driver),
        "lastCycleTime": stats.get("lastCycleTime", 0.0),
        "avgCycleTime": stats.get("avgCycleTime", 0.0),
        "exceptions": sum(cast(Mapping[str, int], stats.get("exceptions", {})).values()),
        "reconnects": stats.get("reconnects", 0),
    }
    for key in COUNTERS:
        row[key] = stats.get(key, 0)
    return row


def writable_names(cfg: DeviceConfig) -> frozenset[str]:
    """The items a write may name: coils and holding registers (Modbus Application
    Protocol 1.1b3 section 4.3: discrete inputs and input registers are read-only)."""
    return frozenset(p.item.name for p in cfg.parsed_items() if p.address.area.writable)


def tag_rows(driver: DriverModbusRtu, writable: frozenset[str]) -> list[dict[str, Any]]:
    """Every item of the device as the tag page shows it."""
    rows = []
    for item in driver.address_items:
        rows.append({
            "name": item.name,
            "address": item.address,
            "type": str(getattr(item.device_data_type, "value", item.device_data_type)),
            "unit": item.unit,
            "writable": item.name in writable,
            **change_row(item),
        })
    return rows


def change_row(item: Any) -> dict[str, Any]:
    """What changes of an item (the live stream sends these): value, status, reason,
    time of the last read."""
    return {
        "name": item.name,
        "value": jsonable(item.value),
        "status": str(getattr(item.status, "value", item.status)),
        "reason": item.error_reason,
        "updateTs": item.update_ts.isoformat() if item.update_ts else None,
    }


def problem_list(exc: ConfigError) -> list[dict[str, Any]]:
    """A ConfigError's problems for the form: the field's path, the value, the message
    (the same text the CLI prints)."""
    out = []
    for problem in exc.problems:
        value = problem.value
        try:
            json.dumps(value)
        except (TypeError, ValueError):
            value = repr(value)
        out.append({"path": problem.path, "value": value, "message": problem.message,
                    "text": str(problem)})
    return out


def check_device(document: Any) -> tuple[DeviceConfig | None, list[dict[str, Any]]]:
    """Load a device document as a device file would be (config/device.py); the config,
    or None and its problems."""
    if not isinstance(document, dict):
        return None, [{"path": "", "value": type(document).__name__,
                       "message": "a device file is a JSON object",
                       "text": "<root>: a device file is a JSON object"}]
    try:
        return load_device_config(document), []
    except ConfigError as exc:
        return None, problem_list(exc)
    except (ValueError, RecursionError) as exc:
        return None, [{"path": "", "value": None, "message": str(exc), "text": str(exc)}]


def plan_preview(cfg: DeviceConfig) -> dict[str, Any]:
    """The read plan of a device (as ``edgemodbus plan`` prints it): one entry per
    request of a cycle."""
    params = cfg.effective_parameters()
    parsed = cfg.parsed_items()
    blocks = build_plan(parsed, params)
    requests = []
    for block in blocks:
        names = [parsed[cast(int, piece.key)].name for piece in block.pieces]
        requests.append({
            "function": block.area.read_function,
            "area": block.area.short_name,
            "start": block.start,
            "count": block.count,
            "every": block.rate,
            "items": names,
        })
    return {"items": len(parsed), "requests": requests, "slaveId": params.slave_id,
            "line": str(endpoint_for(params).describe()), "readCycle": params.read_cycle}


def check_file_name(name: Any, gateway_file: Path) -> str:
    """A device file name the console may write; ValueError says what is allowed."""
    if not isinstance(name, str) or not FILE_NAME.fullmatch(name):
        raise ValueError(f"fileName {name!r}: a plain file name of letters, digits, '_', "
                         "'-' and '.' ending in .json (at most 106 characters), in the "
                         "config folder")
    if name == gateway_file.name:
        raise ValueError(f"fileName {name!r} is the gateway file; choose another name")
    return name


def save_device(folder: Path, name: str, document: Mapping[str, Any], *,
                overwrite: bool) -> Path:
    """Write the device file atomically (a reload never sees half a file);
    FileExistsError when it exists and ``overwrite`` is false."""
    path = folder / name
    if path.exists() and not overwrite:
        raise FileExistsError(f"{name} exists in the config folder: tick 'replace' to "
                              "overwrite it")
    text = json.dumps(document, indent=2, ensure_ascii=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".console-", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as file:
            file.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


__all__ = ["change_row", "check_device", "check_file_name", "device_row", "plan_preview",
           "problem_list", "save_device", "tag_rows", "writable_names"]
