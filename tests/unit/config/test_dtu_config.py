"""Listen-mode, heartbeat and framing options of the communication model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.config import ConfigError, DriverModbusRtuParameter
from edgemodbus.line import endpoint_for

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def server(**extra: Any) -> dict[str, Any]:
    return {"transport": "rtu-over-tcp-server", "listenPort": 9502, "dtuId": "A1",
            "registration": "text", **extra}


def error_text(data: dict[str, Any]) -> str:
    with pytest.raises((ConfigError, ValueError)) as info:
        DriverModbusRtuParameter.model_validate(data)
    return str(info.value)


def test_listen_port_falls_back_to_tcp_port_and_heartbeat_is_bytes() -> None:
    p = DriverModbusRtuParameter.model_validate(
        {"transport": "rtu-over-tcp-server", "tcpPort": 7000, "heartbeatHex": "fe"})
    assert p.effective_listen_port == 7000 and p.use_tcp
    assert p.heartbeat_bytes == b"\xfe" and p.registration == "none"
    assert DriverModbusRtuParameter.model_validate(server(heartbeat="HB")).heartbeat_bytes == b"HB"
    ep = endpoint_for(DriverModbusRtuParameter.model_validate(server(listenHost="127.0.0.1")))
    assert ep.key == ("dtu", "127.0.0.1", "9502", "A1")


@pytest.mark.parametrize(("extra", "expected"), [
    ({"dtuId": ""}, "dtuId '': required with registration 'text'"),
    ({"registration": "hex", "dtuId": "xyz"}, "dtuId 'xyz': registration hex needs hex bytes"),
    ({"registration": "regex", "registrationPattern": "("}, "registrationPattern '(': not a "
     "regular expression"),
    ({"heartbeat": "HB", "heartbeatHex": "FE"}, "heartbeatHex 'FE': give heartbeat (text) or "
     "heartbeatHex, not both"),
    ({"heartbeatHex": "F"}, "heartbeatHex 'F': must be hex bytes"),
    ({"heartbeat": "H" * 65}, "heartbeat '" + "H" * 65 + "': at most 64 bytes"),
    ({"heartbeatHex": "FE" * 65}, "heartbeatHex '" + "FE" * 65 + "': at most 64 bytes"),
    ({"framing": "wrapped-report", "echo": True}, "echo True: no echo option with framing"),
    ({"heartbeat": "HB", "dtuId": "HBHB"}, "dtuId 'HBHB': is nothing but the heartbeat 'HB'"),
    ({"registration": "hex", "heartbeatHex": "00", "dtuId": "0000"},
     "dtuId '0000': is nothing but the heartbeat '00'"),
])
def test_bad_listen_options_name_field_and_value(extra: dict[str, Any], expected: str) -> None:
    assert expected in error_text(server(**extra))


def test_heartbeat_and_wrapped_framing_need_rtu_over_tcp() -> None:
    assert "heartbeats apply to DTU streams" in error_text({"transport": "tcp", "heartbeat": "x"})
    assert "framing 'wrapped-report': needs transport rtu-over-tcp, rtu-over-tcp-server or " \
        "mqtt-dtu, not 'tcp'" in error_text({"transport": "tcp", "framing": "wrapped-report"})
    params = DriverModbusRtuParameter.model_validate({"transport": "tcp"})
    params.framing = "wrapped-report"  # changed after loading: the driver still refuses
    with pytest.raises(ValueError, match="framing 'wrapped-report': needs transport"):
        endpoint_for(params)


def test_an_id_that_contains_the_heartbeat_is_accepted() -> None:
    for extra in ({"heartbeat": "HB", "dtuId": "DTU-HB-7"},
                  {"registration": "hex", "heartbeatHex": "00", "dtuId": "0100A3"}):
        assert DriverModbusRtuParameter.model_validate(server(**extra)).dtu_id == extra["dtuId"]


def test_report_only_read_cycle_zero_is_accepted() -> None:
    p = DriverModbusRtuParameter.model_validate(server(framing="wrapped-report", readCycle=0))
    assert p.read_cycle == 0 and p.framing == "wrapped-report"


def test_the_dtu_example_loads() -> None:
    cfg = em.load_device_config(EXAMPLES / "dtu-device.json")
    comm = cfg.communication
    assert comm.transport == "rtu-over-tcp-server" and comm.registration == "regex"
    assert comm.dtu_id == "861234567890123" and comm.heartbeat_bytes == b"HB"
