"""The non-blocking connect of a connect-mode loop line (line/loop_connect.py ``Dialer``)
on a real :class:`~edgemodbus._ffi.loop.Loop`: what it watches and when it wakes, the
failures in the line worker's words, and nothing left open."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest

from edgemodbus._ffi.loop import WRITABLE, Loop
from edgemodbus.errors import ModbusConnectionError
from edgemodbus.line.endpoint import LineTiming, TcpEndpoint
from edgemodbus.line.loop_connect import Dialer
from edgemodbus.line.worker import LineWorker
from tests.integration.test_loop_connect import hanging_port
from tests.peers import free_port

SLOT = 3


@pytest.fixture
def loop() -> Iterator[Loop]:
    with Loop(8) as lp:
        yield lp


def run(dialer: Dialer, loop: Loop, timeout: float, limit: float = 10.0) -> int:
    """Step the dialer on every wake-up of its slot until it ends; the wake-ups taken."""
    wakes = 0
    dialer.step(loop, SLOT, timeout, lambda: None)
    deadline = time.monotonic() + limit
    while dialer.busy:
        assert time.monotonic() < deadline, "the connect never ended"
        turn = loop.wait(time.monotonic() + 1.0)
        if any(slot == SLOT for slot, _ in turn.ready) or SLOT in turn.expired:
            wakes += 1
            dialer.step(loop, SLOT, timeout, lambda: None)
    return wakes


def test_a_listener_is_connected_and_the_link_opened(loop: Loop) -> None:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(4)
        ep = TcpEndpoint("127.0.0.1", listener.getsockname()[1])
        dialer = Dialer(ep)
        run(dialer, loop, 2.0)
        line = LineWorker(ep, LineTiming())
        link = dialer.open(line)
        try:
            assert link.is_open
            peer, _ = listener.accept()
            peer.close()
        finally:
            link.close()
        with pytest.raises(ModbusConnectionError, match="not connected yet"):
            dialer.open(line)  # the socket was handed over once


def test_a_refused_connect_fails_in_the_line_worker_s_words(loop: Loop) -> None:
    ep = TcpEndpoint("127.0.0.1", free_port())
    dialer = Dialer(ep)
    run(dialer, loop, 2.0)
    with pytest.raises(ModbusConnectionError,
                       match=rf"^{ep.describe()}: connect failed: Connection refused$"):
        dialer.open(LineWorker(ep, LineTiming()))


def test_a_hanging_connect_waits_on_the_loop_until_its_deadline(loop: Loop) -> None:
    with hanging_port() as port:
        ep = TcpEndpoint("127.0.0.1", port)
        dialer = Dialer(ep)
        start = time.monotonic()
        assert dialer.step(loop, SLOT, 0.3, lambda: None) is False
        due = loop.timer_of(SLOT)
        assert due is not None and 0.25 < due - start < 0.35  # the deadline, not a wait
        assert time.monotonic() - start < 0.1  # step returned at once
        turn = loop.wait(start + 0.1)
        assert not [e for s, e in turn.ready if s == SLOT and e & WRITABLE]
        run(dialer, loop, 0.3)
        assert time.monotonic() - start >= 0.3
        with pytest.raises(ModbusConnectionError, match=r"connect timed out after 0.3 s$"):
            dialer.open(LineWorker(ep, LineTiming()))


def test_abort_drops_a_connect_under_way(loop: Loop) -> None:
    with hanging_port() as port:
        dialer = Dialer(TcpEndpoint("127.0.0.1", port))
        assert dialer.step(loop, SLOT, 5.0, lambda: None) is False and dialer.busy
        dialer.abort()  # the socket unwatched and closed (the leak check counts fds)
        assert not dialer.busy


def test_rtu_over_tcp_and_modbus_tcp_are_dialled() -> None:
    for transport in ("rtu-over-tcp", "tcp"):  # (TcpEndpoint refuses any other)
        dialer = Dialer(TcpEndpoint("127.0.0.1", 502, transport))
        assert dialer.endpoint.transport == transport and not dialer.busy
