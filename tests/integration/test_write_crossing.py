"""A write crosses into C once (issue 26): FC05, FC06, FC15, FC16 and FC22 are encoded,
sent, received and checked (csrc/emb_check.c: the echo, FC16's quantity) in one call of
csrc/emb_io.c's ``emb_write``; a forwarded request with its own response timeout in one
call of ``emb_request`` (before: two more calls to set the timeout and two to restore
it).  Against pymodbus in its own process (tests/peers.py), RTU over TCP and Modbus TCP;
the peer's registers and coils say each write arrived whole."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from typing import Any

import pytest

from edgemodbus._ffi import context as ffi_context
from edgemodbus.errors import IllegalDataAddress
from edgemodbus.line.connect import open_link
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.link import ContextLink
from edgemodbus.stats import LineStats
from tests.peers import ExceptionRange, PymodbusSlave


class CountingLib:
    """Stands in for the cffi ``lib`` of _ffi/context.py: counts each function called."""

    def __init__(self, lib: Any) -> None:
        self._lib = lib
        self.calls: list[str] = []

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._lib, name)
        if not callable(value):
            return value

        def call(*args: Any) -> Any:
            self.calls.append(name)
            return value(*args)
        return call


@pytest.fixture(params=["rtu-over-tcp", "tcp"])
def peer(request: pytest.FixtureRequest) -> Iterator[PymodbusSlave]:
    with PymodbusSlave(request.param, units=(1,), fill="zero", size=500,
                       exception_ranges=[ExceptionRange(400, 499, 2)]) as slave:
        yield slave


@pytest.fixture()
def link(peer: PymodbusSlave) -> Iterator[ContextLink]:
    host, port = peer.address
    lk = open_link(TcpEndpoint(host, port, transport=peer.transport), LineTiming(),
                   LineStats())
    lk.set_response_timeout(3.0)
    try:
        yield lk
    finally:
        lk.close()


@pytest.fixture()
def counted(monkeypatch: pytest.MonkeyPatch) -> CountingLib:
    lib = CountingLib(ffi_context.lib)
    monkeypatch.setattr(ffi_context, "lib", lib)
    return lib


def test_each_write_is_one_call_into_c(link: ContextLink, peer: PymodbusSlave,
                                       counted: CountingLib) -> None:
    link.write_register(1, 10, 0xBEEF)
    assert counted.calls == ["emb_write"]
    link.write_registers(1, 20, [1, 2, 0xFFFF])
    link.write_coil(1, 5, True)
    link.write_coils(1, 30, [True, False, True, True, False, False, False, False, True])
    link.mask_write_register(1, 10, 0x00FF, 0x1200)  # (0xBEEF & 0xFF) | 0x1200
    assert counted.calls == ["emb_write"] * 5
    assert peer.registers(1, "hr", 10) == [0x12EF]
    assert peer.registers(1, "hr", 20, 3) == [1, 2, 0xFFFF]
    assert peer.bits(1, "co", 5) == [True]
    assert peer.bits(1, "co", 30, 9) == [True, False, True, True, False, False, False,
                                         False, True]
    assert link.stats.requests == link.stats.responses == 5


def test_a_refused_write_is_one_call_and_keeps_its_error(link: ContextLink,
                                                         counted: CountingLib) -> None:
    with pytest.raises(IllegalDataAddress, match=r"slave 1 FC16"):
        link.write_registers(1, 410, [7, 8])
    assert counted.calls == ["emb_write"]
    assert link.stats.exceptions == {2: 1}


def test_a_request_with_its_own_timeout_is_one_call(link: ContextLink, peer: PymodbusSlave,
                                                    counted: CountingLib) -> None:
    pdu = struct.pack(">BHHHHB2H", 0x17, 0, 2, 40, 2, 4, 5, 6)  # FC23 (AP 6.17)
    adu = link.transact(1, pdu, timeout=2.5)
    assert counted.calls == ["emb_request"]
    assert link.reply_pdu(adu) == bytes([0x17, 4, 0, 0, 0, 0])
    assert peer.registers(1, "hr", 40, 2) == [5, 6]
    assert link.stats.requests == link.stats.responses == 1


def test_bad_write_arguments_name_what_is_allowed(link: ContextLink) -> None:
    with pytest.raises(ValueError, match=r"write of 124 registers: must be 1\.\.123"):
        link.write_registers(1, 0, [0] * 124)
    with pytest.raises(ValueError, match=r"write of 0 coils: must be 1\.\.1968"):
        link.write_coils(1, 0, [])
    assert link.stats.requests == 0
