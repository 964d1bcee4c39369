"""Logs as JSON lines (issue 29): ``--log-format json`` on the command line and
``logFormat`` in the gateway file; every line of stderr is one JSON object with time,
level, logger and message, for Loki/ELK."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest

from edgemodbus.cli import build_parser
from edgemodbus.logs import JsonFormatter


def _record(message: str, *args: object, exc: BaseException | None = None) -> logging.LogRecord:
    exc_info = (type(exc), exc, exc.__traceback__) if exc is not None else None
    return logging.LogRecord("edgemodbus.line", logging.WARNING, __file__, 1, message, args,
                             exc_info)


def test_a_record_is_one_json_line() -> None:
    line = JsonFormatter().format(_record("line %s: ünïcode\nsecond line %d", "COM1", 7))
    assert "\n" not in line
    doc = json.loads(line)
    assert doc["level"] == "WARNING" and doc["logger"] == "edgemodbus.line"
    assert doc["message"] == "line COM1: ünïcode\nsecond line 7"
    assert doc["time"].endswith("Z")
    assert datetime.fromisoformat(doc["time"].replace("Z", "+00:00")).utcoffset() is not None


def test_a_traceback_stays_in_the_object() -> None:
    try:
        raise RuntimeError("boom")
    except RuntimeError as exc:
        line = JsonFormatter().format(_record("failed", exc=exc))
    doc = json.loads(line)
    assert doc["message"] == "failed"
    assert "RuntimeError: boom" in doc["exception"] and "Traceback" in doc["exception"]


def test_the_option_before_or_after_the_command() -> None:
    parser = build_parser()
    assert parser.parse_args(["plan", "x.json"]).log_format == "text"
    assert parser.parse_args(["--log-format", "json", "plan", "x.json"]).log_format == "json"
    assert parser.parse_args(["plan", "x.json", "--log-format", "json"]).log_format == "json"
    with pytest.raises(SystemExit):
        parser.parse_args(["--log-format", "xml", "plan", "x.json"])


def _service_log(tmp_path: Path, *options: str) -> list[str]:
    """stderr of a short gateway run (no device files: it logs its start and stop)."""
    out = subprocess.run(
        [sys.executable, "-m", "edgemodbus.cli", *options, "run", "--config-dir",
         str(tmp_path), "--seconds", "0.2"],
        capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    lines = out.stderr.splitlines()
    assert len(lines) >= 2, out.stderr  # "gateway ... running", "stopping", "stopped"
    return lines


def _assert_json_lines(lines: list[str]) -> None:
    for line in lines:
        doc = json.loads(line)
        assert {"time", "level", "logger", "message"} <= doc.keys(), doc
        assert doc["logger"].startswith("edgemodbus") and doc["level"] == "INFO", doc
    assert any("running" in json.loads(line)["message"] for line in lines), lines


def test_log_format_json_on_the_command_line(tmp_path: Path) -> None:
    _assert_json_lines(_service_log(tmp_path, "--log-format", "json"))


def test_log_format_in_the_gateway_file(tmp_path: Path) -> None:
    text = _service_log(tmp_path)
    assert not text[0].startswith("{")  # text by default
    (tmp_path / "gateway.json").write_text(json.dumps({"gatewayId": "gw",
                                                       "logFormat": "json"}))
    _assert_json_lines(_service_log(tmp_path))
