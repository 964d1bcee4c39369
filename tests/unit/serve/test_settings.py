"""The serve section of the gateway file (serve/settings.py): what it accepts, and the
errors that name the field, the value and what is allowed."""

from __future__ import annotations

import pytest

from edgemodbus.config import ConfigError
from edgemodbus.serve import ServeSettings, split_listen, unknown_devices


def test_a_worked_section() -> None:
    s = ServeSettings.load({"listen": "0.0.0.0:1502", "maxConnections": 8, "idleTimeoutS": 30,
                            "units": [{"unitId": 1, "device": "m1", "offset": 100,
                                       "maxAgeMs": 5000},
                                      {"unitId": 9, "forward": "m2", "timeoutMs": 800}]})
    assert (s.host, s.port, s.max_connections, s.idle_timeout_s) == ("0.0.0.0", 1502, 8, 30)
    assert [u.target for u in s.units] == ["m1", "m2"]
    assert split_listen("127.0.0.1") == ("127.0.0.1", 502)


@pytest.mark.parametrize(("section", "message"), [
    ({"listen": "gateway.local:502"}, "serve.listen 'gateway.local:502': .*IPv4 address"),
    ({"listen": "127.0.0.1:70000"}, "the port must be 0..65535"),
    ({"maxConnections": 0}, r"serve.maxConnections 0: must be 1..1024"),
    ({"units": [{"unitId": 256, "device": "a"}]}, r"serve.units\[0\].unitId 256: must be 0..255"),
    ({"units": [{"unitId": 1}]}, "give exactly one of 'device'"),
    ({"units": [{"unitId": 1, "device": "a", "forward": "b"}]}, "give exactly one of"),
    ({"units": [{"unitId": 1, "forward": "b", "maxAgeMs": 10}]}, "are for a 'device' unit"),
    ({"units": [{"unitId": 1, "device": "a", "timeoutMs": 10}]}, "is for a 'forward' unit"),
    ({"units": [{"unitId": 1, "device": "a"}, {"unitId": 1, "device": "b"}]},
     "unitId 1 is given twice"),
])
def test_bad_sections_are_refused_clearly(section: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ServeSettings.load(section)


def test_units_naming_no_device() -> None:
    s = ServeSettings.load({"units": [{"unitId": 1, "device": "m1"},
                                      {"unitId": 2, "forward": "gone"}]})
    problems = unknown_devices(s, ["m1"])
    assert [str(p) for p in problems] == [
        "serve.units[1].forward 'gone': no device has this deviceCode; known: m1"]


def test_the_readme_gateway_file_loads() -> None:
    """The worked gateway file of docs/gateway.md's Modbus TCP server section is a valid
    one."""
    import json
    from pathlib import Path

    from edgemodbus.gateway import load_gateway_config

    text = (Path(__file__).resolve().parents[3] / "docs" / "gateway.md").read_text()
    section = text[text.index("## A Modbus TCP server for SCADA"):]
    block = section[section.index("```json\n") + 8:]
    cfg = load_gateway_config(json.loads(block[:block.index("```")]))
    assert cfg.serve is not None
    assert [(u.unit_id, u.target, u.offset) for u in cfg.serve.units] == [
        (1, "meter1", 0), (2, "meter1", 1000), (9, "meter2", 0)]
