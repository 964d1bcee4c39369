"""The Modbus TCP server's allow-lists (serve ``allowFrom``, per server and per unit;
docs/links.md): a connection from outside the server's list is reset at once and
counted, a request from outside a unit's list gets exception 0A and is counted.
pymodbus' client is the master (from 127.0.0.1 and, bound to it, from 127.0.0.2: the
loopback range only), a pymodbus slave (own process) the device behind the gateway."""

from __future__ import annotations

import ipaddress
import json
import socket
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymodbus.client import ModbusTcpClient

from edgemodbus.gateway import Gateway as GatewayService
from edgemodbus.gateway import load_gateway_config
from edgemodbus.serve import ModbusTcpServer
from tests.conftest import SlaveFactory
from tests.integration.test_serve import REFUSING, Gateway, hr
from tests.integration.test_serve_gateway import device_file
from tests.waiting import wait_for

OTHER = "127.0.0.2"


@pytest.fixture
def guarded(slave_factory: SlaveFactory) -> Iterator[Gateway]:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=2000,
                         exception_ranges=[REFUSING])
    gw = Gateway(peer, max_connections=4, idle_timeout=5.0, allow_from=["127.0.0.1/32"])
    try:
        yield gw
    finally:
        gw.close()


def read_from(source: str, port: int, unit: int = 1) -> bytes:
    """One FC03 request from ``source``; what came back (b"" when closed)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(5)
        sock.bind((source, 0))
        try:  # a reset may already end the connect
            sock.connect(("127.0.0.1", port))
            sock.sendall(struct.pack(">HHHBBHH", 7, 0, 6, unit, 3, 0, 2))
            return sock.recv(260)
        except ConnectionResetError:
            return b""


def test_the_server_resets_sources_outside_its_allow_list(guarded: Gateway) -> None:
    assert read_from(OTHER, guarded.port) == b""
    wait_for(lambda: guarded.server.stats()["refusedSource"] == 1, what="the refusal counted")
    client = guarded.client()  # from 127.0.0.1: served
    try:
        rr = client.read_holding_registers(0, count=3, device_id=1)
        assert not rr.isError() and rr.registers == hr(1, 0, 3)
    finally:
        client.close()
    stats = guarded.server.stats()
    assert stats["refusedSource"] == 1 and stats["accepted"] == 1


def test_a_unit_answers_only_its_allow_list(slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=2000,
                         exception_ranges=[REFUSING])
    gw = Gateway(peer, max_connections=4, idle_timeout=5.0)  # the server: any source
    try:
        gw.server.serve_device(1, gw.dev1, gw.cfg1, allow_from=[OTHER])
        gw.server.forward_device(9, gw.dev2, timeout=0.5, allow_from=["127.0.0.0/30"])
        local = gw.client()
        other = ModbusTcpClient("127.0.0.1", port=gw.port, timeout=2, retries=0,
                                source_address=(OTHER, 0))
        assert other.connect()
        try:
            refused = local.read_holding_registers(0, count=2, device_id=1)
            assert refused.isError() and refused.exception_code == 0x0A
            wait_for(lambda: other.read_holding_registers(0, count=2, device_id=1)
                     .registers == hr(1, 0, 2), what="unit 1 from 127.0.0.2")
            rr = local.read_holding_registers(0, count=2, device_id=9)  # 127.0.0.0/30
            assert not rr.isError() and rr.registers == hr(2, 0, 2)
            assert gw.server.stats()["refusedUnit"] == 1
            gw.server.remove_unit(1)  # a unit served again starts with no list
            gw.server.serve_device(1, gw.dev1, gw.cfg1)
            wait_for(lambda: not local.read_holding_registers(0, count=2, device_id=1)
                     .isError(), what="unit 1 from 127.0.0.1 once its list is gone")
        finally:
            other.close()
            local.close()
    finally:
        gw.close()


def test_the_gateway_file_s_allow_lists_reach_the_server(
        tmp_path: Path, slave_factory: SlaveFactory) -> None:
    peer = slave_factory("rtu-over-tcp", units=(1, 2), size=200)
    (tmp_path / "meter1.json").write_text(json.dumps(device_file(peer, 1, "meter1", 2)))
    (tmp_path / "gateway.json").write_text(json.dumps({"serve": {
        "listen": "127.0.0.1:0", "allowFrom": "127.0.0.0/30",
        "units": [{"unitId": 1, "device": "meter1", "allowFrom": [OTHER]},
                  {"unitId": 2, "device": "meter1"}]}}))
    gateway = GatewayService(tmp_path, load_gateway_config(tmp_path / "gateway.json"),
                      tmp_path / "gateway.json")
    gateway.start()
    try:
        server = gateway.serving.server
        assert server is not None
        wait_for(lambda: len(read_from(OTHER, server.port, unit=2)) == 13,
                 what="unit 2 from 127.0.0.2 (inside 127.0.0.0/30)")
        assert read_from("127.0.0.1", server.port, unit=1)[7:] == bytes([0x83, 0x0A])
        assert len(read_from(OTHER, server.port, unit=1)) == 13
        assert read_from("127.0.0.5", server.port) == b""  # outside 127.0.0.0/30
        wait_for(lambda: server.stats()["refusedSource"] == 1, what="the reset counted")
        assert server.stats()["refusedUnit"] == 1
    finally:
        gateway.stop()


def test_a_bad_allow_list_names_the_entry() -> None:
    with pytest.raises(ValueError, match=r"allowFrom\[1\] '::1': the server listens on "
                                         r"IPv4 only"):
        ModbusTcpServer("127.0.0.1", 0, allow_from=["10.0.0.0/8", "::1"])


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(nets=st.lists(st.tuples(st.integers(0, 2**24 - 1), st.integers(8, 32)), max_size=3),
       source=st.integers(1, 2**24 - 2))
def test_the_c_allow_list_matches_ipaddress(nets: list[tuple[int, int]], source: int) -> None:
    """Differential: the server's C match (csrc/emb_serve.c) against Python's ipaddress
    for networks and sources in 127.0.0.0/8 (every one of them is bindable locally)."""
    allow = [str(ipaddress.IPv4Network(((127 << 24) | host, prefix), strict=False))
             for host, prefix in nets]
    src = str(ipaddress.IPv4Address((127 << 24) | source))
    want = not allow or any(ipaddress.IPv4Address(src) in ipaddress.IPv4Network(n)
                            for n in allow)
    server = ModbusTcpServer("127.0.0.1", 0, allow_from=allow).start()
    try:
        reply = read_from(src, server.port, unit=5)  # no unit 5: 0A when let in
        assert (reply[7:] == bytes([0x83, 0x0A])) == want, (allow, src, reply)
        if want:
            assert server.stats()["refusedSource"] == 0
    finally:
        server.stop()
