"""The PROXY v2 header (line/proxy_v2.py) under attack on a DTU listen port behind a
balancer (docs/fault-checklist.md "PROXY v2"): a header with 64 KB of TLVs, one sent
byte by byte, one never finished, a balancer's connection that sends nothing, a flood of
malformed headers.  Each is closed and counted with one log line per kind and interval
and no thread per peer; a slow but complete header still registers its DTU."""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time

import pytest

from edgemodbus.line.proxy_v2 import SIGNATURE, build
from edgemodbus.sim import Simulator
from tests.integration.test_dtu import dtu_device, free_port, ok, running
from tests.integration.test_listener_attacks import closed_by_peer, counter, raw_connections
from tests.integration.test_listener_proxy import DTU_ADDR, balancers, peers
from tests.waiting import wait_for


def oversize_header(tlv_bytes: int) -> bytes:
    """A TCP4 PROXY header carrying ``tlv_bytes`` of NOOP TLVs (type 0x04), laid out as
    HAProxy's doc/proxy-protocol.txt section 2.2 gives them."""
    tlvs = b""
    while len(tlvs) < tlv_bytes:
        chunk = min(60_000, tlv_bytes - len(tlvs) - 3)
        tlvs += bytes([0x04]) + struct.pack("!H", chunk) + bytes(chunk)
    body = bytes([203, 0, 113, 7, 127, 0, 0, 1]) + struct.pack("!HH", 4000, 9502) + tlvs
    return SIGNATURE + bytes([0x21, 0x11]) + struct.pack("!H", len(body)) + body


def test_an_oversize_header_is_refused_before_its_bytes_arrive() -> None:
    port = free_port()
    with balancers("127.0.0.1/32"), running(dtu_device(port, "GOOD")), \
            raw_connections(port, 1) as (sock,):
        assert sock is not None
        raw = oversize_header(65_000)
        sock.sendall(raw[:16])  # the fixed part says 65,012 bytes follow
        wait_for(lambda: counter(port, "proxyMalformed") == 1, what="proxyMalformed")
        wait_for(lambda: closed_by_peer(sock), what="closed")


@pytest.mark.usefixtures("engine")
def test_a_header_sent_byte_by_byte_within_the_timeout_registers_its_dtu() -> None:
    port = free_port()
    cfg = dtu_device(port, "GOOD", registrationTimeout=5000)
    header = build(DTU_ADDR, 7)

    with balancers("127.0.0.1/32"), Simulator(slaves=[1]) as sim, running(cfg):
        sock = socket.create_connection(("127.0.0.1", port))
        try:
            for byte in header:
                sock.send(bytes([byte]))
                time.sleep(0.01)  # pacing: the sender (the attack), waits for nothing
            sock.sendall(b"GOOD\r\n")
            wait_for(lambda: counter(port, "registered") == 1, what="registered")
            assert counter(port, "proxyMalformed") == counter(port, "proxyMissing") == 0
        finally:
            sock.close()
        sim.dial("127.0.0.1", port, registration=build(DTU_ADDR, 8) + b"GOOD\r\n")
        wait_for(ok(cfg), what="the DTU Ok through the balancer")
        assert f"{DTU_ADDR}:8" in peers(port)


def test_unfinished_and_missing_headers_are_closed_at_the_deadline_and_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    caplog.set_level(logging.WARNING, logger="edgemodbus")
    with balancers("127.0.0.1/32"), running(dtu_device(port, "GOOD")), \
            raw_connections(port, 2) as (unfinished, silent):
        assert unfinished is not None and silent is not None
        unfinished.sendall(build(DTU_ADDR, 1)[:20])  # 20 of 28 bytes, then nothing
        wait_for(lambda: closed_by_peer(unfinished) and closed_by_peer(silent),
                 what="both closed at registrationTimeout")
        wait_for(lambda: counter(port, "proxyMalformed") == 1, what="the unfinished one")
        assert counter(port, "silent") == 1 and counter(port, "registered") == 0
        text = caplog.text
        assert "PROXY v2 header not complete" in text and "20 bytes" in text, text


def test_a_flood_of_malformed_headers_costs_bounded_lines_and_no_threads(
        caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    caplog.set_level(logging.WARNING, logger="edgemodbus")
    bad = [SIGNATURE + bytes([0x21, 0x31, 0, 216]) + bytes(216),  # UNIX family
           SIGNATURE[:11] + b"X" + bytes(8),                       # bad signature
           SIGNATURE + bytes([0x11, 0x11, 0, 12]) + bytes(12),     # version 1
           SIGNATURE + bytes([0x21, 0x11, 0, 4]) + bytes(4)]       # length too short
    with balancers("127.0.0.1/32"), running(dtu_device(port, "GOOD")):
        threads = threading.active_count()
        for i in range(200):
            with socket.create_connection(("127.0.0.1", port)) as sock:
                sock.sendall(bad[i % len(bad)])
            assert threading.active_count() <= threads + 1
        wait_for(lambda: counter(port, "proxyMalformed") + counter(port, "proxyMissing")
                 == 200, what="200 refusals counted")
        lines = [r for r in caplog.records if "PROXY" in r.getMessage()]
        assert len(lines) <= 10, [r.getMessage() for r in lines]
