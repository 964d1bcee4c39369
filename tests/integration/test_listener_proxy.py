"""The DTU listener behind a load balancer (issue #28): with ``fleet.loadBalancers`` set
(here 127.0.0.1, standing in for HAProxy), a connection from it starts with a PROXY v2
header and every check sees the DTU's address from the header; a header from elsewhere,
a malformed one, or none from the balancer is refused and counted; LOCAL is closed."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest

import edgemodbus as em
from edgemodbus.datatypes import ItemStatus
from edgemodbus.line.proxy_v2 import build
from edgemodbus.sim import Simulator
from tests.integration.test_dtu import dtu_device, free_port, ok, running, values
from tests.integration.test_listener_attacks import (
    REAL,
    closed_by_peer,
    counter,
    raw_connections,
)
from tests.waiting import wait_for

DTU_ADDR = "203.0.113.7"  # where the header says the DTU is (TEST-NET-3, never local)


@contextlib.contextmanager
def balancers(*cidrs: str) -> Iterator[None]:
    registry = em.DriverModbusRtu.dtu_registry
    registry.set_load_balancers(cidrs)
    try:
        yield
    finally:
        registry.set_load_balancers(())


def peers(port: int) -> list[str]:
    held = em.DriverModbusRtu.dtu_registry.held().get(f"127.0.0.1:{port}", [])
    return [str(d["peer"]) for d in held if d["connected"]]


@pytest.mark.usefixtures("engine")
def test_a_dtu_behind_the_balancer_is_seen_at_its_own_address() -> None:
    """listenAllowFrom and dtuAllowFrom admit the header's address, not 127.0.0.1 (which
    neither lists): without the header reader this DTU is refused."""
    port = free_port()
    cfg = dtu_device(port, "GOOD", listenAllowFrom=["203.0.113.0/24"],
                     dtuAllowFrom=[f"{DTU_ADDR}/32"])
    with balancers("127.0.0.1/32"), Simulator(slaves=[1]) as sim, running(cfg):
        sim.dial("127.0.0.1", port, registration=build(DTU_ADDR, 40001) + b"GOOD\r\n")
        wait_for(ok(cfg), what="GOOD Ok through the balancer")
        assert values(cfg) == REAL
        assert peers(port) == [f"{DTU_ADDR}:40001"]
        assert counter(port, "refusedNotAllowed") == 0


def test_the_header_address_is_refused_by_the_dtus_allow_list() -> None:
    port = free_port()
    cfg = dtu_device(port, "GOOD", dtuAllowFrom=["198.51.100.0/24"])
    with balancers("127.0.0.1/32"), Simulator(slaves=[1]) as sim, running(cfg):
        client = sim.dial("127.0.0.1", port, registration=build(DTU_ADDR, 1) + b"GOOD\r\n")
        wait_for(lambda: counter(port, "refusedDtuNotAllowed") == 1, what="refused")
        wait_for(lambda: client.closed, what="closed after the registration timeout")
        assert not any(it.status is ItemStatus.OK for it in cfg.address_list)


def test_per_source_caps_count_the_dtus_address_not_the_balancers() -> None:
    """Three silent connections from one balancer with maxUnregisteredPerSource 2 are all
    admitted (they come from three DTUs); three headers naming one DTU address are not."""
    port = free_port()
    cfg = dtu_device(port, "GOOD", maxUnregisteredPerSource=2, registrationTimeout=3000)
    with balancers("127.0.0.1/32"), running(cfg), raw_connections(port, 3) as socks:
        for k, sock in enumerate(socks):
            assert sock is not None
            sock.sendall(build(f"198.51.100.{k + 1}", 1000))
        wait_for(lambda: counter(port, "accepted") == 3, what="3 accepted")
        with raw_connections(port, 3) as same:
            for sock in same:
                if sock is not None:
                    with contextlib.suppress(OSError):
                        sock.sendall(build(DTU_ADDR, 1000))
            wait_for(lambda: counter(port, "refusedSourceCap") == 1, what="the third refused")
        assert counter(port, "refusedSourceCap") == 1
        assert counter(port, "proxyMissing") == counter(port, "proxyMalformed") == 0


def test_refusals_and_the_health_check() -> None:
    port = free_port()
    cfg = dtu_device(port, "GOOD", registrationTimeout=3000)
    with balancers("127.0.0.1/32"), running(cfg):
        cases = [(b"GOOD\r\n", "proxyMissing"),
                 (build(DTU_ADDR, 1)[:12] + bytes([0x21, 0x12, 0, 12]) + bytes(12),
                  "proxyMalformed"),
                 (build(None, local=True), "proxyLocal")]
        for raw, name in cases:
            with raw_connections(port, 1) as (sock,):
                assert sock is not None
                sock.sendall(raw)
                wait_for(lambda name=name: counter(port, name) == 1, what=name)
                wait_for(lambda sock=sock: closed_by_peer(sock), what=f"{name} closed")
        assert counter(port, "registered") == 0
    port = free_port()
    cfg = dtu_device(port, "GOOD", registrationTimeout=3000)
    with balancers("192.0.2.0/24"), running(cfg), raw_connections(port, 1) as (sock,):
        assert sock is not None  # 127.0.0.1 is no balancer now: its header is refused
        sock.sendall(build(DTU_ADDR, 1) + b"GOOD\r\n")
        wait_for(lambda: counter(port, "proxyNotAllowed") == 1, what="proxyNotAllowed")
        wait_for(lambda: closed_by_peer(sock), what="closed")
        assert counter(port, "registered") == 0


@pytest.mark.usefixtures("engine")
def test_a_port_without_registration_behind_the_balancer() -> None:
    """registration "none": the one DTU of the port is handed the connection once its
    header is read (before it, nothing was known of the DTU's address)."""
    port = free_port()
    cfg = dtu_device(port, "", registration="none", listenAllowFrom=[DTU_ADDR])
    with balancers("127.0.0.1/32"), Simulator(slaves=[1]) as sim, running(cfg):
        sim.dial("127.0.0.1", port, registration=build(DTU_ADDR, 7))
        wait_for(ok(cfg), what="the DTU Ok through the balancer")
        assert values(cfg) == REAL
        assert peers(port) == [f"{DTU_ADDR}:7"]
