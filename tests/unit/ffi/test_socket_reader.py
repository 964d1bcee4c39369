"""The plain RTU and Modbus TCP reader on a socket (csrc/emb_rtu.c emb_fd_recv): a
greedy read after one poll(), so a reply that came whole costs four system calls
(stale input dropped, request sent, one wait, one read; libmodbus makes seven: a
select() and a read() per phase, docs/performance.md), counted by the link
(``Context.syscalls``).  Reading past a frame must keep every guarantee of the reader
that read exact lengths: stale input before a request is dropped, the last answer wins,
a frame may come split anywhere, the byte timeout holds.  The property test compares our
reader with libmodbus's own (``Context.read_libmodbus``) on the same bytes.

The far end is a thread on a socketpair that answers one request with chunks of bytes,
each one send(), pausing between them (the shape of the wire, not a wait for anything).
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgemodbus import _ffi
from edgemodbus.errors import IncompleteReplyError, ModbusConnectionError
from edgemodbus.protocol import rtu

Answer = Callable[[bytes], list[bytes]]  # the request -> the chunks to send


def rtu_reply(values: list[int], slave: int = 1) -> bytes:
    return rtu.frame(slave, struct.pack(f">BB{len(values)}H", 3, 2 * len(values), *values))


def mbap_reply(tid: int, values: list[int], unit: int = 1) -> bytes:
    pdu = struct.pack(f">BB{len(values)}H", 3, 2 * len(values), *values)
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


class Peer:
    """Answers one request on ``sock``: reads ``request_len`` bytes, then sends what
    ``answer`` makes of them, a send() per chunk, ``pause`` seconds apart."""

    def __init__(self, sock: socket.socket, answer: Answer, request_len: int,
                 pause: float = 0.0) -> None:
        self.sock, self.answer, self.request_len, self.pause = sock, answer, request_len, pause
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="socket-reader-peer")
        self.thread.start()

    def _run(self) -> None:
        try:
            request = b""
            while len(request) < self.request_len:
                got = self.sock.recv(self.request_len - len(request))
                if not got:
                    return
                request += got
            for i, chunk in enumerate(self.answer(request)):
                if i and self.pause:
                    time.sleep(self.pause)  # pacing: the chunks apart
                self.sock.sendall(chunk)
        except BaseException as exc:  # handed to the test by join()
            self.error = exc

    def join(self) -> None:
        self.thread.join(10)
        assert not self.thread.is_alive(), "the peer did not finish"
        if self.error is not None:
            raise self.error


@contextmanager
def link(mbap: bool = False, byte_timeout: float = 0.5) -> Iterator[tuple[_ffi.Context,
                                                                          socket.socket]]:
    """A context on one end of a socketpair, and the other end."""
    ours, theirs = socket.socketpair()
    ctx = _ffi.Context.on_socket(ours.fileno(), "socket-reader", mbap=mbap)
    try:
        ctx.set_timeouts(2.0, byte_timeout)
        yield ctx, theirs
    finally:
        ctx.close()
        ours.close()
        theirs.close()


def read_answered(ctx: _ffi.Context, peer_sock: socket.socket, answer: Answer,
                  count: int, pause: float = 0.0, mbap: bool = False) -> list[int]:
    """One FC03 read of ``count`` registers at 0 answered by ``answer``."""
    peer = Peer(peer_sock, answer, 12 if mbap else 8, pause)
    try:
        return ctx.read(1, 3, 0, count).to_list()
    finally:
        peer.join()


def tid_of(request: bytes) -> int:
    return int.from_bytes(request[:2], "big")


@pytest.mark.parametrize("mbap", [False, True], ids=["rtu", "mbap"])
def test_a_whole_reply_costs_four_system_calls(mbap: bool) -> None:
    values = list(range(100, 220))
    with link(mbap) as (ctx, peer):
        for _ in range(10):
            before = ctx.syscalls
            answer: Answer = ((lambda req: [mbap_reply(tid_of(req), values)]) if mbap
                              else (lambda req: [rtu_reply(values)]))
            assert read_answered(ctx, peer, answer, 120, mbap=mbap) == values
            # recv (nothing stale), write, poll, read: the reply and the proof that
            # nothing is behind it in one read
            assert ctx.syscalls - before == 4
        assert ctx.take_discarded() == 0


def test_stale_input_before_the_request_is_dropped_whatever_its_size() -> None:
    values = [7] * 10
    with link() as (ctx, peer):
        stale = rtu_reply([9] * 10) * 60  # 1500 bytes: three reads of the drain
        peer.sendall(stale)
        before = ctx.syscalls
        assert read_answered(ctx, peer, lambda req: [rtu_reply(values)], 10) == values
        assert ctx.take_discarded() == len(stale)
        assert ctx.syscalls - before == 3 + 3  # 512 + 512 + 476 (short: all), then as above


def test_the_last_answer_wins_when_both_come_together() -> None:
    late, real = rtu_reply([1] * 120), rtu_reply([2] * 120)
    with link() as (ctx, peer):
        before = ctx.syscalls
        assert read_answered(ctx, peer, lambda req: [late + real], 120) == [2] * 120
        assert ctx.take_discarded() == len(late)
        # 490 bytes: the first read fills the reader's buffer (one ADU, 260 bytes), the
        # rest is read at once, without a wait first
        assert ctx.syscalls - before == 5


def test_the_last_answer_wins_when_the_second_is_still_arriving() -> None:
    late, real = rtu_reply([1] * 120), rtu_reply([2] * 120)
    with link() as (ctx, peer):
        chunks = [late + real[:20], real[20:]]
        assert read_answered(ctx, peer, lambda req: chunks, 120, pause=0.05) == [2] * 120
        assert ctx.take_discarded() == len(late)


def test_a_frame_that_does_not_answer_behind_the_reply_is_dropped() -> None:
    real, other = rtu_reply([2] * 10), rtu_reply([5] * 11)  # another byte count
    with link() as (ctx, peer):
        assert read_answered(ctx, peer, lambda req: [real + other], 10) == [2] * 10
        assert ctx.take_discarded() == len(other)


def test_bytes_behind_the_reply_too_few_for_a_frame_are_dropped_with_it() -> None:
    with link() as (ctx, peer):
        answer: Answer = lambda req: [rtu_reply([3] * 10) + b"\x01\x02\x03"]  # noqa: E731
        assert read_answered(ctx, peer, answer, 10) == [3] * 10
        assert ctx.take_discarded() == 3
        assert read_answered(ctx, peer, lambda req: [rtu_reply([4] * 10)], 10) == [4] * 10
        assert ctx.take_discarded() == 0


def test_a_reply_to_an_earlier_transaction_is_skipped_in_the_same_read() -> None:
    """Modbus TCP: the old transaction's reply and ours in one read; the bytes behind the
    skipped one are carried into the next receive, not lost."""
    with link(mbap=True) as (ctx, peer):
        def answer(req: bytes) -> list[bytes]:
            tid = tid_of(req)
            return [mbap_reply((tid - 1) & 0xFFFF, [1] * 60) + mbap_reply(tid, [2] * 60)]

        before = ctx.syscalls
        assert read_answered(ctx, peer, answer, 60, mbap=True) == [2] * 60
        assert ctx.take_discarded() == 7 + 2 + 120
        assert ctx.syscalls - before == 4  # both in one read, nothing asked after it


def test_a_reply_that_stops_short_fails_one_byte_timeout_after_its_last_byte() -> None:
    with link(byte_timeout=0.2) as (ctx, peer):
        reply = rtu_reply(list(range(120)))
        t0 = time.monotonic()
        with pytest.raises(IncompleteReplyError):
            read_answered(ctx, peer, lambda req: [reply[:100]], 120)
        assert 0.2 <= time.monotonic() - t0 < 1.8  # the byte timeout, not the response's


def test_the_peer_closing_is_a_connection_error_in_the_drain() -> None:
    with link() as (ctx, peer):
        peer.close()
        with pytest.raises(ModbusConnectionError, match="link error"):
            ctx.read(1, 3, 0, 1)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(values=st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=125),
       cuts=st.lists(st.integers(1, 254), max_size=3, unique=True),
       pause=st.sampled_from([0.0, 0.003]))
def test_ours_and_libmodbus_read_the_same_reply_however_it_is_split(
        values: list[int], cuts: list[int], pause: float) -> None:
    reply = rtu_reply(values)
    points = sorted(c for c in cuts if c < len(reply))
    chunks = [reply[a:b] for a, b in zip([0, *points], [*points, len(reply)], strict=True)]
    with link() as (ctx, peer):
        before = ctx.syscalls
        assert read_answered(ctx, peer, lambda req: chunks, len(values), pause) == values
        # a wait and a read per chunk at most, besides the drain and the send
        assert ctx.syscalls - before <= 2 + 2 * len(chunks)
        assert ctx.take_discarded() == 0
        peer_thread = Peer(peer, lambda req: chunks, 8, pause)
        try:
            assert ctx.read_libmodbus(1, 0, len(values)).to_list() == values
        finally:
            peer_thread.join()
