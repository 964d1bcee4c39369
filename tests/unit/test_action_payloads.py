"""The action command's pure parts: NG function code spellings, the MQTT payload, the CLI's
name=value parameters."""

from __future__ import annotations

import json

import pytest

from edgemodbus.cli.action import parse_params
from edgemodbus.cli.output import CliError
from edgemodbus.config.compat import function_code
from edgemodbus.northbound.mqtt.commands import parse_action


def test_function_code_spellings() -> None:
    assert [function_code(v) for v in (16, "16", "0x10", "WriteMultipleRegisters",
                                       "write_single_coil", "readInputRegisters")] == [
        16, 16, 16, 16, 5, 4]
    assert function_code("nope") is None
    assert function_code(True) is None
    assert function_code(1.5) is None


def test_parse_action_payloads() -> None:
    body = {"action": "start", "parameters": {"speed": 1.5}, "id": 7}
    assert parse_action(json.dumps(body).encode()) == (7, "start", {"speed": 1.5})
    assert parse_action(b'{"action": "stop"}') == (None, "stop", {})
    assert parse_action(b'{"action": "stop", "parameters": null}') == (None, "stop", {})
    for payload, why in ((b"{oops", "not JSON"), (b'{"parameters": {}}', '"action"'),
                         (b'{"action": 5}', '"action"'),
                         (b'{"action": "a", "parameters": [1]}', "must be an object"),
                         (b"\xff", "not JSON"), (b" " * 70000, "too large")):
        with pytest.raises(ValueError, match=why):
            parse_action(payload)


def test_cli_parameters() -> None:
    assert parse_params(["speed=12.5", "name=a=b", " mode = 3"]) == {
        "speed": "12.5", "name": "a=b", "mode": " 3"}
    with pytest.raises(CliError, match="name=value"):
        parse_params(["speed"])
    with pytest.raises(CliError, match="given twice"):
        parse_params(["a=1", "a=2"])
