"""The C loop of the gateway's Modbus TCP server (csrc/emb_serve.c) through its thin
binding, with raw sockets as masters: replies from the image, the exception codes it
answers itself, requests handed to Python and the answers posted back."""

from __future__ import annotations

import queue
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest

from edgemodbus._ffi.serve import (
    EV_REQUEST,
    EV_STOP,
    MODE_CACHED,
    MODE_FORWARD,
    POST_EXCEPTION,
    POST_PDU,
    POST_WRITTEN,
    STATE_INVALID,
    STATE_VALID,
    STATE_WRITABLE,
    ImageRun,
    Request,
    ServerCore,
)
from tests.waiting import wait_for

NEVER = (1 << 63) - 1


class Loop:
    """A ServerCore run by a thread; requests for Python land in ``requests``."""

    def __init__(self, **kw: float) -> None:
        self.core = ServerCore("127.0.0.1", 0, max_connections=int(kw.get("cap", 4)),
                               idle_timeout=kw.get("idle", 0.0))
        self.requests: queue.Queue[Request] = queue.Queue()
        self.thread = threading.Thread(target=self._run)
        self.thread.start()

    def _run(self) -> None:
        while True:
            event = self.core.run(time.monotonic_ns() + 50_000_000)
            if event == EV_STOP:
                return
            if event == EV_REQUEST:
                self.requests.put(self.core.request())

    def connect(self) -> socket.socket:
        sock = socket.create_connection(("127.0.0.1", self.core.port), timeout=3)
        return sock

    def close(self) -> None:
        self.core.stop()
        self.thread.join()
        self.core.close()


@pytest.fixture
def loop() -> Iterator[Loop]:
    lp = Loop()
    core = lp.core
    # unit 1: holding 10..19 (10..14 valid, 15 invalid, 16..19 unmapped), coils 0..7
    core.set_unit(1, MODE_CACHED, [(0, 8), (0, 0), (10, 10), (0, 0)])
    core.update([ImageRun(1, 2, 10, STATE_VALID | STATE_WRITABLE, [100, 101, 102, 103, 104]),
                 ImageRun(1, 2, 15, STATE_INVALID, [0]),
                 ImageRun(1, 0, 0, STATE_VALID | STATE_WRITABLE, [1, 0, 1, 1, 0, 0, 0, 1])])
    core.set_fresh(1, NEVER)
    core.set_unit(9, MODE_FORWARD)
    try:
        yield lp
    finally:
        lp.close()


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            break
        data += chunk
    return data


def recv_adu(sock: socket.socket) -> bytes:
    head = recv_exact(sock, 6)
    return head + recv_exact(sock, struct.unpack(">H", head[4:6])[0]) if len(head) == 6 else head


def ask(sock: socket.socket, tid: int, unit: int, pdu: bytes) -> bytes:
    sock.sendall(mbap(tid, unit, pdu))
    adu = recv_adu(sock)
    assert adu[:2] == struct.pack(">H", tid) and adu[6] == unit
    return adu[7:]


def test_reads_come_from_the_image(loop: Loop) -> None:
    with loop.connect() as sock:
        assert ask(sock, 1, 1, b"\x03\x00\x0a\x00\x05") == b"\x03\x0a" + struct.pack(
            ">5H", 100, 101, 102, 103, 104)
        assert ask(sock, 2, 1, b"\x01\x00\x00\x00\x08") == b"\x01\x01\x8d"
        assert ask(sock, 3, 1, b"\x03\x00\x0f\x00\x01") == b"\x83\x0b"  # invalid
        assert ask(sock, 4, 1, b"\x03\x00\x0e\x00\x03") == b"\x83\x02"  # reaches 16
        assert ask(sock, 5, 1, b"\x03\x00\x09\x00\x01") == b"\x83\x02"  # below the span
        assert ask(sock, 6, 1, b"\x04\x00\x00\x00\x01") == b"\x84\x02"  # no input regs
        assert ask(sock, 7, 2, b"\x03\x00\x0a\x00\x01") == b"\x83\x0a"  # no such unit
        assert ask(sock, 8, 1, b"\x2b\x0e\x01\x00") == b"\xab\x01"  # not a function here
        assert ask(sock, 9, 1, b"\x03\x00\x0a\x00\x00") == b"\x83\x03"  # quantity 0
        loop.core.set_fresh(1, time.monotonic_ns() - 1)
        assert ask(sock, 10, 1, b"\x03\x00\x0a\x00\x01") == b"\x83\x0b"  # too old
    assert loop.requests.empty()
    counters = loop.core.counters()
    assert counters.cached_replies == 2 and counters.exceptions == {1: 1, 2: 3, 3: 1,
                                                                    10: 1, 11: 2}


def test_pipelined_requests_are_answered_in_order(loop: Loop) -> None:
    with loop.connect() as sock:
        sock.sendall(mbap(1, 1, b"\x03\x00\x0a\x00\x01") + mbap(2, 1, b"\x03\x00\x0b\x00\x01")
                     + mbap(3, 1, b"\x03\x00\x10\x00\x01"))
        assert recv_adu(sock) == mbap(1, 1, b"\x03\x02\x00\x64")
        assert recv_adu(sock) == mbap(2, 1, b"\x03\x02\x00\x65")
        assert recv_adu(sock) == mbap(3, 1, b"\x83\x02")


def test_forwarded_requests_and_their_answers(loop: Loop) -> None:
    with loop.connect() as sock, loop.connect() as other:
        sock.sendall(mbap(0x1234, 9, b"\x03\x00\x00\x00\x02"))
        request = loop.requests.get(timeout=3)
        assert request.adu == mbap(0x1234, 9, b"\x03\x00\x00\x00\x02")
        # the other master is served meanwhile
        assert ask(other, 5, 1, b"\x03\x00\x0a\x00\x01") == b"\x03\x02\x00\x64"
        assert loop.core.post(request.conn, request.gen, POST_PDU, b"\x03\x04\x00\x01\x00\x02")
        assert recv_adu(sock) == mbap(0x1234, 9, b"\x03\x04\x00\x01\x00\x02")
        assert not loop.core.post(request.conn, request.gen, POST_PDU, b"\x03\x00")  # answered
        sock.sendall(mbap(7, 9, b"\x06\x00\x01\x00\x02"))
        request = loop.requests.get(timeout=3)
        assert loop.core.post(request.conn, request.gen, POST_EXCEPTION, b"\x0b")
        assert recv_adu(sock) == mbap(7, 9, b"\x86\x0b")
        sock.sendall(mbap(8, 9, b"\x03\x00\x00\x00\x01"))
        request = loop.requests.get(timeout=3)
    # the master left before its answer: the answer is dropped (once the loop saw it go)
    wait_for(lambda: loop.core.open_connections() == 0, timeout=10, what="the close seen")
    assert not loop.core.post(request.conn, request.gen, POST_PDU, b"\x03\x02\x00\x00")


def test_writes_go_to_python_and_land_in_the_image(loop: Loop) -> None:
    with loop.connect() as sock:
        assert ask(sock, 1, 1, b"\x06\x00\x0f\x00\x01") == b"\x86\x02"  # not writable
        assert ask(sock, 2, 1, b"\x10\x00\x0a\x00\x02\x03\x00\x01\x00") == b"\x90\x03"
        sock.sendall(mbap(3, 1, b"\x10\x00\x0a\x00\x02\x04\x00\x07\x00\x08"))
        request = loop.requests.get(timeout=3)
        assert loop.core.post(request.conn, request.gen, POST_WRITTEN, b"")
        assert recv_adu(sock) == mbap(3, 1, b"\x10\x00\x0a\x00\x02")
        assert ask(sock, 4, 1, b"\x03\x00\x0a\x00\x02") == b"\x03\x04\x00\x07\x00\x08"
        sock.sendall(mbap(5, 1, b"\x05\x00\x01\xff\x00"))
        request = loop.requests.get(timeout=3)
        assert loop.core.post(request.conn, request.gen, POST_WRITTEN, b"")
        assert recv_adu(sock) == mbap(5, 1, b"\x05\x00\x01\xff\x00")
        assert ask(sock, 6, 1, b"\x01\x00\x00\x00\x02") == b"\x01\x01\x03"


def test_cap_idle_and_bad_headers() -> None:
    lp = Loop(cap=2, idle=0.3)
    try:
        lp.core.set_unit(1, MODE_CACHED, [(0, 0), (0, 0), (0, 1), (0, 0)])
        a, b, c = lp.connect(), lp.connect(), lp.connect()
        with a, b, c:
            assert c.recv(10) == b""  # over the cap
            a.sendall(struct.pack(">HHHB", 1, 5, 6, 1) + b"\x03\x00\x00\x00\x01")
            assert a.recv(10) == b""  # protocol id 5: closed
            t0 = time.monotonic()
            assert b.recv(10) == b""  # idle
            assert time.monotonic() - t0 < 2
        counters = lp.core.counters()
        assert (counters.refused, counters.closed_bad, counters.closed_idle) == (1, 1, 1)
        assert lp.core.open_connections() == 0
    finally:
        lp.close()
