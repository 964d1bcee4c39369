"""The frame trace ring (csrc/emb_io.c, emb_trace in csrc/emb_link.h): every frame a
transaction sends or receives, with its direction and time, in order; a full ring loses
the newest frames and counts them.  Checked on a socketpair against a model of the ring
written here from its contract (a byte budget of EMB_TRACE_SIZE, 11 bytes a record
besides the frame)."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager

from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus import _ffi
from edgemodbus._ffi.native import lib
from edgemodbus.errors import CrcError
from edgemodbus.protocol import rtu

RING = int(lib.EMB_TRACE_SIZE)
HEAD = 11  # direction, length, time


@contextmanager
def traced_context(trace: bool = True) -> Iterator[tuple[_ffi.Context, socket.socket]]:
    """A plain RTU context on one end of a socketpair, traced; the other end is the
    peer's."""
    ours, peer = socket.socketpair()
    ctx = _ffi.Context.on_socket(ours.fileno(), "pair", mbap=False)
    try:
        ctx.set_timeouts(0.5, 0.1)
        ctx.set_trace(trace)
        yield ctx, peer
    finally:
        ctx.close()
        ours.close()
        peer.close()


def _answer(peer: socket.socket, reply: bytes) -> threading.Thread:
    """A peer thread: wait for one request, answer ``reply``."""

    def run() -> None:
        peer.settimeout(5)
        peer.recv(512)
        peer.sendall(reply)

    thread = threading.Thread(target=run)
    thread.start()
    return thread


def _broadcast(address: int, n: int) -> bytes:
    """An FC16 request PDU writing n registers at address (broadcast: no reply)."""
    return struct.pack(f">BHHB{n}H", 16, address, n, 2 * n, *range(n))


def test_a_transaction_traces_its_request_and_reply_in_order() -> None:
    request = struct.pack(">BHH", 3, 0, 2)
    reply = rtu.frame(1, bytes([3, 4, 0, 7, 0, 9]))
    with traced_context() as (ctx, peer):
        before = time.monotonic()
        peer_thread = _answer(peer, reply)
        ctx.transact(1, request)
        peer_thread.join()
        after = time.monotonic()
        frames, lost = ctx.take_trace()
        assert ctx.take_trace() == ([], 0)  # taken once
    assert lost == 0
    assert [(f.tx, f.frame) for f in frames] == [(True, rtu.frame(1, request)), (False, reply)]
    assert before <= frames[0].at <= frames[1].at <= after


def test_a_refused_reply_is_traced_as_it_came() -> None:
    bad = bytearray(rtu.frame(1, bytes([3, 2, 0, 7])))
    bad[-1] ^= 0xFF  # the CRC does not match
    with traced_context() as (ctx, peer):
        peer_thread = _answer(peer, bytes(bad))
        try:
            ctx.transact(1, struct.pack(">BHH", 3, 0, 1))
        except CrcError:
            pass
        else:
            raise AssertionError("a bad CRC was taken")
        finally:
            peer_thread.join()
        frames, _ = ctx.take_trace()
    assert [f.tx for f in frames] == [True, False]
    assert frames[1].frame == bytes(bad)


def test_no_trace_records_nothing() -> None:
    with traced_context(trace=False) as (ctx, _peer):
        ctx.send(0, _broadcast(0, 1))
        assert ctx.traced == 0
        assert ctx.take_trace() == ([], 0)
        ctx.set_trace(True)
        ctx.send(0, _broadcast(1, 1))
        ctx.set_trace(False)
        ctx.send(0, _broadcast(2, 1))
        ctx.set_trace(True)
        frames, _ = ctx.take_trace()
    assert [f.frame for f in frames] == [rtu.frame(0, _broadcast(1, 1))]


def test_a_full_ring_keeps_the_oldest_and_counts_the_rest() -> None:
    size = HEAD + len(rtu.frame(0, _broadcast(0, 1)))
    fits = RING // size
    with traced_context() as (ctx, peer):
        peer.setblocking(False)
        for k in range(fits + 30):
            ctx.send(0, _broadcast(k, 1))
            if k % 50 == 0:
                try:
                    while peer.recv(65536):
                        pass
                except BlockingIOError:
                    pass
        frames, lost = ctx.take_trace()
    assert lost == 30
    assert [f.frame for f in frames] == [rtu.frame(0, _broadcast(k, 1)) for k in range(fits)]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.one_of(st.tuples(st.just("send"), st.integers(1, 123)),
                          st.tuples(st.just("take"), st.integers(0, 40))),
                max_size=120))
def test_the_ring_against_a_model(ops: list[tuple[str, int]]) -> None:
    """Frames of every length sent and taken in any order, around the ring's end: what
    is taken is what the model kept, in order, and the lost count is the model's."""
    model: deque[bytes] = deque()
    used = lost = 0
    with traced_context() as (ctx, peer):
        peer.setblocking(False)
        for k, (op, n) in enumerate(ops):
            if op == "send":
                ctx.send(0, _broadcast(k, n))
                frame = rtu.frame(0, _broadcast(k, n))
                if RING - used >= len(frame) + HEAD:
                    model.append(frame)
                    used += len(frame) + HEAD
                else:
                    lost += 1
                try:
                    while peer.recv(65536):
                        pass
                except BlockingIOError:
                    pass
                continue
            # take everything (the binding has no partial take): n only spreads the takes
            if n % 4:
                continue
            frames, got_lost = ctx.take_trace()
            assert [f.frame for f in frames] == list(model)
            assert all(f.tx for f in frames)
            assert got_lost == lost
            model.clear()
            used = lost = 0
        assert ctx.traced == len(model)
        frames, got_lost = ctx.take_trace()
    assert [f.frame for f in frames] == list(model)
    assert got_lost == lost
