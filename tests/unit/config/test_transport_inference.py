"""The transport a device file means when it says neither ``transport`` nor ``useTcp``
(issue 24): a file with only ``tcpHost``/``tcpPort`` polled the serial port COM1."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, load_device_config

DATA = Path(__file__).resolve().parents[2] / "data"


def comm_of(comm: dict[str, Any]) -> Any:
    return load_device_config({"communication": comm, "addressList": []}).communication


@pytest.mark.parametrize(("comm", "transport"), [
    ({"tcpHost": "10.0.0.5", "tcpPort": 1502}, "rtu-over-tcp"),
    ({"tcpHost": "10.0.0.5"}, "rtu-over-tcp"),
    ({"TcpPort": 4001}, "rtu-over-tcp"),  # PascalCase (the seed's modbusRtu.json)
    ({"comPort": "/dev/ttyUSB0"}, "rtu"),
    ({}, "rtu"),
    ({"tcpHost": "10.0.0.5", "useTcp": False}, "rtu"),  # the seed's modbusRtu.json
    ({"tcpHost": "10.0.0.5", "comPort": "COM1", "useTcp": True}, "rtu-over-tcp"),
    ({"tcpHost": "10.0.0.5", "comPort": "COM1", "transport": "tcp"}, "tcp"),
])
def test_transport_from_the_keys_given(comm: dict[str, Any], transport: str) -> None:
    got = comm_of(comm)
    assert (got.transport, got.use_tcp) == (transport, transport != "rtu")


def test_serial_and_tcp_keys_without_a_choice_are_refused_naming_both() -> None:
    with pytest.raises(ConfigError) as info:
        comm_of({"comPort": "COM3", "tcpHost": "10.0.0.5", "tcpPort": 1502})
    [problem] = info.value.problems
    text = str(problem)
    assert text.startswith("communication.transport: missing: comPort 'COM3' and tcpHost "
                           "'10.0.0.5' and tcpPort 1502 are both given"), text
    assert "'rtu'" in text and "'rtu-over-tcp'" in text and "useTcp" in text


def test_seed_files_load_as_before(tmp_path: Path) -> None:
    seed = json.loads((DATA / "seed-device.json").read_text(encoding="utf-8"))
    assert load_device_config(seed).communication.transport == "rtu-over-tcp"  # useTcp true
    no_use_tcp = {**seed, "communication": {k: v for k, v in seed["communication"].items()
                                            if k != "useTcp"}}
    with pytest.raises(ConfigError, match="comPort 'COM1' and tcpHost"):
        load_device_config(no_use_tcp)  # COM1 and a TCP host: which one was meant?


KEYS = {"comPort": "COM2", "tcpHost": "192.0.2.1", "tcpPort": 1502}


@given(st.sets(st.sampled_from(sorted(KEYS))), st.sampled_from([None, True, False]),
       st.sampled_from([None, "rtu", "rtu-over-tcp", "tcp"]))
def test_never_a_serial_port_nobody_named(keys: set[str], use_tcp: bool | None,
                                          transport: str | None) -> None:
    """Whatever subset of the keys: a device polls a serial port only when comPort, useTcp
    false or transport rtu said so, and a TCP endpoint only when a TCP key, useTcp or
    transport said so; an ambiguous file is refused, never guessed."""
    comm: dict[str, Any] = {k: KEYS[k] for k in keys}
    if use_tcp is not None:
        comm["useTcp"] = use_tcp
    if transport is not None:
        comm["transport"] = transport
    try:
        got = comm_of(comm)
    except ConfigError as exc:
        assert (use_tcp is None and transport is None) or (
            transport is not None and use_tcp is not None), exc  # ambiguous or contradictory
        return
    if transport is not None:
        assert got.transport == transport
    elif use_tcp is not None:
        assert got.transport == ("rtu-over-tcp" if use_tcp else "rtu")
    elif keys & {"tcpHost", "tcpPort"}:
        assert "comPort" not in keys and got.transport == "rtu-over-tcp"
    else:
        assert got.transport == "rtu"
