"""DTU streams framed in C (csrc/emb_stream.c): heartbeats and wrapped report frames.

The wrapped framing must follow the rules of the Python parser the simulator keeps using
(:class:`edgemodbus.protocol.wrapped.ReportParser`): the same byte streams, cut into the
same segments, give the same reports, drops and heartbeats.  Then a wrapped exchange
and a plain one with heartbeats on a socketpair, with a peer thread answering.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from edgemodbus import _ffi
from edgemodbus.errors import IllegalDataAddress, ModbusTimeoutError
from edgemodbus.protocol import rtu
from edgemodbus.protocol.wrapped import ReportParser, wrap

EXAMPLES = int(os.environ.get("EDGEMODBUS_FUZZ_EXAMPLES", "200"))


@contextmanager
def stream_context(heartbeat: bytes = b"", wrapped: bool = True,
                   echo: bool = False) -> Iterator[tuple[_ffi.Context, socket.socket]]:
    """A context on one end of a socketpair (the other end is the peer's)."""
    ours, peer = socket.socketpair()
    ctx = _ffi.Context.on_socket(ours.fileno(), "pair", mbap=False)
    try:
        ctx.set_timeouts(0.5, 0.1)
        ctx.set_stream(heartbeat, wrapped)
        ctx.set_echo(echo)
        yield ctx, peer
    finally:
        ctx.close()
        ours.close()
        peer.close()


# -- the same rules as ReportParser -----------------------------------------------------


def _read_reply(slave: int, fc: int, regs: list[int]) -> bytes:
    if fc in (1, 2):
        return bytes([fc, len(regs)]) + bytes(r & 0xFF for r in regs)
    return struct.pack(f">BB{len(regs)}H", fc, 2 * len(regs), *regs)


@st.composite
def pieces(draw: st.DrawFn, heartbeat: bytes) -> bytes:
    """One piece of a stream: a valid wrapped frame, a damaged one, noise, a heartbeat."""
    kind = draw(st.sampled_from(["frame", "frame", "frame", "crc", "tail", "bogus", "noise",
                                 "heartbeat", "exception", "write"]))
    address = draw(st.integers(0, 0xFFFF))
    slave = draw(st.integers(0, 255))
    if kind == "heartbeat":
        return heartbeat
    if kind == "noise":
        return draw(st.binary(min_size=1, max_size=12))
    if kind == "exception":
        return wrap(address, slave, bytes([draw(st.sampled_from([0x83, 0x84, 0x90])),
                                           draw(st.integers(0, 255))]))
    if kind == "write":
        return wrap(address, slave, struct.pack(">BHH", 6, address, draw(st.integers(0, 65535))))
    if kind == "bogus":  # a header, then something that is no Modbus reply
        return b"\xff\xaa" + draw(st.binary(min_size=2, max_size=8))
    fc = draw(st.sampled_from([1, 2, 3, 4]))
    regs = draw(st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=126))
    frame = bytearray(wrap(address, slave, _read_reply(slave, fc, regs)))
    if kind == "crc":
        frame[-2] ^= 0x01
    elif kind == "tail":
        frame[-1] = 0x0E
    return bytes(frame)


@st.composite
def streams(draw: st.DrawFn) -> tuple[bytes, bytes, list[bytes]]:
    """(heartbeat, stream, segments the stream arrives in)."""
    heartbeat = draw(st.sampled_from([b"", b"\xfe", b"HB", b"\xff\xaa", b"PING\r\n"]))
    data = b"".join(draw(st.lists(pieces(heartbeat), max_size=12)))
    cuts = sorted(draw(st.lists(st.integers(0, len(data)), max_size=8)))
    segments = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
    return heartbeat, data, segments


@settings(max_examples=EXAMPLES, deadline=None)
@given(streams())
# a heartbeat that looks like the header: a header found behind noise is parsed as one,
# and taken as a heartbeat when the parser comes back to it (here with no new bytes)
@example((b"\xff\xaa", b"\x00\xff\xaa\x57", [b"\x00\xff\xaa\x57", b""]))
def test_wrapped_framing_follows_the_report_parser(case: tuple[bytes, bytes, list[bytes]]) -> None:
    heartbeat, _, segments = case
    parser = ReportParser(heartbeat)
    with stream_context(heartbeat) as (ctx, _peer):
        for segment in segments:
            expected = [r.raw for r in parser.feed(segment)]
            ctx.feed(segment)
            assert ctx.take_reports() == expected
        counts = ctx.take_counters()
        dropped = counts.dropped if counts else 0
        heartbeats = counts.heartbeats if counts else 0
        assert (heartbeats, dropped) == (parser.heartbeats, parser.dropped)
        assert ctx.reports_waiting == 0 and ctx.take_discarded() == 0


def test_a_full_report_ring_loses_reports_and_counts_them() -> None:
    report = wrap(1, 1, _read_reply(1, 3, list(range(80))))  # 170 bytes, 172 in the ring
    with stream_context() as (ctx, _peer):
        assert ctx.feed(report * 40) == 23  # 4096 // 172
        assert ctx.take_counters() == _ffi.StreamCounters(lost=17)
        assert ctx.take_reports() == [report] * 23
        assert ctx.feed(report) == 1  # room again


def test_plain_stream_counts_heartbeats_anywhere_and_drops_the_rest() -> None:
    with stream_context(b"HB", wrapped=False) as (ctx, _peer):
        ctx.feed(b"HBxxHBHByH")
        assert ctx.take_counters() == _ffi.StreamCounters(heartbeats=3)
        assert ctx.take_discarded() == 4
        assert ctx.reports_waiting == 0


# -- exchanges ---------------------------------------------------------------------------


class Peer:
    """Answers one request on ``sock``: reads ``request_len`` bytes, sends ``answer``."""

    def __init__(self, sock: socket.socket, request_len: int, answer: bytes) -> None:
        self.request = b""
        self._sock, self._len, self._answer = sock, request_len, answer
        self._thread = threading.Thread(target=self._run, name="stream-peer")
        self._thread.start()

    def _run(self) -> None:
        while len(self.request) < self._len:
            chunk = self._sock.recv(self._len - len(self.request))
            if not chunk:
                return
            self.request += chunk
        if self._answer:
            self._sock.sendall(self._answer)

    def join(self) -> None:
        self._thread.join(5)


def test_wrapped_read_takes_its_reply_and_queues_reports_before_and_behind() -> None:
    older = wrap(1, 1, _read_reply(1, 3, [9001, 9002, 9003]))  # same address, other count
    reply = wrap(1, 1, _read_reply(1, 3, [501, 502]))
    newer = wrap(7, 1, _read_reply(1, 3, [77]))
    with stream_context(b"\xfe") as (ctx, peer):
        ctx.feed(b"\xfe" + older[:5])  # a heartbeat and half a report before the link
        p = Peer(peer, 13, older[5:] + b"\xfe" + reply + newer[:9])
        try:
            assert ctx.read(1, 3, 1, 2).to_list() == [501, 502]
        finally:
            p.join()
        assert p.request == wrap(1, 1, struct.pack(">BHH", 3, 1, 2))
        assert (ctx.reports_waiting, ctx.reports_before) == (1, 1)
        assert ctx.take_reports(1) == [older]
        assert ctx.take_counters() == _ffi.StreamCounters(heartbeats=2)
        peer.sendall(newer[9:])
        assert ctx.pump() == 1 and ctx.take_reports() == [newer]


def test_wrapped_exception_and_timeout() -> None:
    with stream_context() as (ctx, peer):
        p = Peer(peer, 13, wrap(40, 2, bytes([0x83, 0x02])))
        try:
            with pytest.raises(IllegalDataAddress):
                ctx.read(2, 3, 40, 10)
        finally:
            p.join()
        # a reply of another address is a report; a frame that stops short is no reply
        other = wrap(41, 2, _read_reply(2, 3, [1]))
        p = Peer(peer, 13, other + wrap(40, 2, _read_reply(2, 3, [5]))[:8])
        try:
            with pytest.raises(ModbusTimeoutError, match="no response"):
                ctx.read(2, 3, 40, 1)
        finally:
            p.join()
        assert ctx.take_reports() == [other]


@pytest.mark.parametrize("echo", [False, True])
def test_plain_stream_skips_heartbeats_around_the_echo_and_the_reply(echo: bool) -> None:
    request = rtu.frame(3, struct.pack(">BHH", 4, 10, 3))
    reply = rtu.frame(3, _read_reply(3, 4, [7, 8, 9]))
    with stream_context(b"HB", wrapped=False, echo=echo) as (ctx, peer):
        answer = (b"HB" + request if echo else b"") + b"HBHB" + reply + b"HB"
        p = Peer(peer, len(request), answer)
        try:
            assert ctx.read(3, 4, 10, 3).to_list() == [7, 8, 9]
        finally:
            p.join()
        assert p.request == request
        ctx.pump()  # the heartbeat behind the reply
        assert ctx.take_counters() == _ffi.StreamCounters(heartbeats=4 if echo else 3)
