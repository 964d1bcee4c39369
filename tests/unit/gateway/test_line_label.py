"""The metrics label of a device's line names the line: the serial port, the TCP peer,
or the listen port and id of a DTU that dials in."""

from __future__ import annotations

from typing import Any

import edgemodbus as em
from edgemodbus.gateway.service import line_label


def label(**comm: Any) -> str:
    cfg = em.load_device_config({"communication": comm, "addressList": [
        {"name": "x", "address": "hr:0", "deviceDataType": "UInt16"}]})
    return line_label(cfg.effective_parameters())


def test_each_transport_names_its_own_line() -> None:
    assert label(transport="rtu", comPort="/dev/ttyS3") == "/dev/ttyS3"
    assert label(transport="tcp", tcpHost="10.0.0.5", tcpPort=502) == "tcp://10.0.0.5:502"
    assert (label(transport="rtu-over-tcp", tcpHost="10.0.0.6", tcpPort=4001)
            == "rtu-over-tcp://10.0.0.6:4001")


def test_a_dtu_is_named_by_its_listen_port_and_id_not_by_tcp_host() -> None:
    a = label(transport="rtu-over-tcp-server", listenPort=9502, dtuId="861234567890123",
              registration="regex", registrationPattern="^(?P<id>[0-9]{15})$")
    b = label(transport="rtu-over-tcp-server", listenPort=9502, dtuId="861234567890124",
              registration="regex", registrationPattern="^(?P<id>[0-9]{15})$")
    assert a == "dtu://0.0.0.0:9502/861234567890123"
    assert a != b
