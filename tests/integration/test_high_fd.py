"""Sockets whose fd is 1024 or more: csrc/emb_io.c receives with poll(), so a line on such
an fd reads and writes like any other (libmodbus 3.1.6's select() would overflow its
FD_SET there and abort the process: listen mode used to stop at about 1015 DTUs)."""

from __future__ import annotations

import os
import resource
import socket
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from edgemodbus import _ffi
from edgemodbus.errors import IllegalDataAddress, ModbusConnectionError
from tests.peers import ExceptionRange, PymodbusSlave, default_register

HIGH_FD = 1500


@contextmanager
def high_fd_socket(address: tuple[str, int]) -> Iterator[int]:
    """A socket connected to ``address`` and moved to fd HIGH_FD (the soft fd limit raised
    for the test and put back after)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard <= HIGH_FD:
        pytest.skip(f"the hard fd limit {hard} does not allow fd {HIGH_FD}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, HIGH_FD + 1), hard))
    try:
        with socket.create_connection(address, timeout=5) as sock:
            sock.settimeout(None)
            os.dup2(sock.fileno(), HIGH_FD)
        try:
            yield HIGH_FD
        finally:
            os.close(HIGH_FD)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


@pytest.mark.parametrize("transport", ["rtu-over-tcp", "tcp"])
def test_reads_writes_and_errors_on_an_fd_above_1024(slave_factory, transport: str) -> None:
    slave: PymodbusSlave = slave_factory(
        transport, exception_ranges=[ExceptionRange(900, 1000, code=2)]
    )
    with high_fd_socket(slave.address) as fd:
        ctx = _ffi.Context.on_socket(fd, f"high fd {fd}", mbap=transport == "tcp")
        try:
            assert ctx.fd == fd
            ctx.set_timeouts(1.0, 0.2)
            for unit in (1, 2, 3):  # the longest reply too: 125 registers, 255 data bytes
                block = ctx.read(unit, 3, 0, 125)
                assert block.to_list() == [default_register(unit, "hr", a) for a in range(125)]
            pdu = bytes.fromhex("0600070abc")  # FC06: the reply echoes the request
            header = 7 if transport == "tcp" else 1
            assert ctx.transact(2, pdu)[header:header + len(pdu)] == pdu
            assert slave.registers(2, "hr", 7) == [0x0ABC]
            with pytest.raises(IllegalDataAddress):
                ctx.read(1, 3, 950, 2)
            assert ctx.read(1, 4, 10, 3).to_list() == [default_register(1, "ir", a)
                                                       for a in range(10, 13)]
            slave.drop_connections()
            with pytest.raises(ModbusConnectionError):
                ctx.read(1, 3, 0, 1)
        finally:
            ctx.close()
