"""The link keys (config/links.py, docs/links.md): alternates, failoverAfter,
failbackInterval, connections, channel, flowControl; each bad value is an error that
names the field, the value and what is allowed; the endpoint carries what was given."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from edgemodbus.config import ConfigError, DriverModbusRtuParameter, load_device_config
from edgemodbus.line.endpoint import SerialPort, TcpEndpoint, endpoint_for


def comm(**keys: Any) -> DriverModbusRtuParameter:
    return DriverModbusRtuParameter.model_validate(keys)


def errors_of(**keys: Any) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_device_config({"communication": keys, "addressList": []})
    return [str(p) for p in info.value.problems]


def test_tcp_alternates_become_the_endpoint_s_targets() -> None:
    params = comm(transport="tcp", tcpHost="10.0.0.1", tcpPort=502,
                  alternates=["10.0.1.1:1502", "[fd00::7]:502"], failoverAfter=2,
                  failbackInterval=1500)
    ep = endpoint_for(params)
    assert isinstance(ep, TcpEndpoint)
    assert ep.alternates == (("10.0.1.1", 1502), ("fd00::7", 502))
    assert (ep.failover_after, ep.failback_interval) == (2, 1.5)
    assert [t.describe() for t in ep.targets()] == [
        "tcp://10.0.0.1:502", "tcp://10.0.1.1:1502", "tcp://[fd00::7]:502"]
    assert ep.key == ("tcp", "10.0.0.1", "502")  # the primary is the line's identity


def test_serial_alternates_are_ports_with_the_same_settings() -> None:
    ep = endpoint_for(comm(transport="rtu", comPort="/dev/ttyUSB0", baudRate=19200,
                           alternates="/dev/ttyUSB1, /dev/serial/by-path/pci-0:1.0-port0"))
    assert isinstance(ep, SerialPort)
    ports = [(t.port, t.baudrate, t.alternates) for t in ep.targets()]
    assert ports == [("/dev/ttyUSB0", 19200, ()), ("/dev/ttyUSB1", 19200, ()),
                     ("/dev/serial/by-path/pci-0:1.0-port0", 19200, ())]


@pytest.mark.parametrize(("keys", "error"), [
    ({"transport": "tcp", "alternates": ["10.0.0.2"]},
     "communication.alternates[0] '10.0.0.2': must be host:port (or [IPv6]:port) on a TCP "
     "line, e.g. 10.0.1.20:502"),
    ({"transport": "rtu-over-tcp", "alternates": ["h:70000"]},
     "communication.alternates[0] 'h:70000': port 70000: must be 1..65535"),
    ({"transport": "rtu", "comPort": "/dev/ttyS0", "alternates": ["10.0.0.2:502"]},
     "communication.alternates[0] '10.0.0.2:502': a serial line's alternates are serial "
     "ports (e.g. /dev/ttyUSB1); host:port is for rtu-over-tcp and tcp lines"),
    ({"transport": "tcp", "tcpHost": "10.0.0.1", "tcpPort": 502,
      "alternates": ["10.0.0.1:502"]},
     "communication.alternates[0] '10.0.0.1:502': repeats the primary endpoint or another "
     "alternate"),
    ({"transport": "rtu-over-tcp-server", "alternates": ["a:1"]},
     "communication.alternates ['a:1']: a DTU that dials in (rtu-over-tcp-server) picks its "
     "own path; alternates are for lines we open (rtu, rtu-over-tcp, tcp)"),
    ({"transport": "rtu-over-tcp", "connections": 4},
     "communication.connections 4: more than one connection is for Modbus TCP (transport "
     "tcp), whose transaction ids pair replies with requests; transport is 'rtu-over-tcp'"),
    ({"transport": "tcp", "connections": 4, "channel": 4},
     "communication.channel 4: must be 0..3 (connections is 4)"),
    ({"transport": "tcp", "connections": 17}, "communication.connections 17: must be 1..16"),
    ({"transport": "rtu", "flowControl": "rtscts", "rs485": "rts-up"},
     "communication.flowControl 'rtscts': RTS/CTS flow control and RS-485 direction "
     "control (rs485 'rts-up') both drive RTS: use one, rs485 'none' with rtscts"),
    ({"transport": "tcp", "alternates": 5},
     "communication.alternates 5: must be a list of alternate endpoints of the line's own "
     "kind: host:port (or [IPv6]:port) for a TCP line, a serial port (e.g. /dev/ttyUSB1, "
     "COM4) for a serial line"),
])
def test_bad_link_keys_name_field_value_and_what_is_allowed(keys: dict[str, Any],
                                                            error: str) -> None:
    assert errors_of(**keys) == [error]


def test_flow_control_is_carried_to_the_serial_endpoint() -> None:
    ep = endpoint_for(comm(transport="rtu", comPort="/dev/ttyS1", flowControl="RTSCTS"))
    assert isinstance(ep, SerialPort) and ep.flow_control == "rtscts"
    assert "rtscts" in ep.describe()
    assert errors_of(transport="rtu", flowControl="xonxoff")[0].startswith(
        "communication.flowControl 'xonxoff': ")


@given(connections=st.integers(1, 16), slave=st.integers(0, 255),
       channel=st.none() | st.integers(0, 15))
def test_connections_spread_devices_by_unit_id_or_channel(
        connections: int, slave: int, channel: int | None) -> None:
    """Property: every device lands on one of the endpoint's connections, the one its
    channel names, else its unit id modulo connections; each connection is its own
    line (key), and one connection keeps the plain key."""
    if channel is not None and 1 < connections <= channel:
        assert errors_of(transport="tcp", connections=connections, channel=channel,
                         slaveId=slave)
        return
    ep = endpoint_for(comm(transport="tcp", tcpHost="gw", connections=connections,
                           channel=channel, slaveId=slave))
    assert isinstance(ep, TcpEndpoint)
    want = 0 if connections == 1 else (slave if channel is None else channel) % connections
    assert ep.channel == want
    if connections == 1:
        assert ep.key == ("tcp", "gw", "502")
    else:
        assert ep.key == ("tcp", "gw", "502", f"#{want}")
