"""Every link kind on the loop engine (csrc/emb_loop_link.c): wrapped DTU streams with
their reports and echoing lines against our simulator (edgemodbus.sim, which plays the
edge MCU and the echoing adapter), Modbus TCP against pymodbus, each with exact values
and a differential pass-for-pass check against the blocking engine (csrc/emb_engine.c
over csrc/emb_io.c's backends) on the same peer; and scripted peers for what a real one
does only by chance (reports around a reply, a reply to an old transaction id)."""

from __future__ import annotations

import errno
import os
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field

import pytest

from edgemodbus._ffi.context import Context
from edgemodbus._ffi.engine import EV_CYCLE as ENGINE_CYCLE
from edgemodbus._ffi.engine import EV_REPORTS as ENGINE_REPORTS
from edgemodbus._ffi.engine import BlockSpec, Engine, EngineDevice, Waker
from edgemodbus._ffi.loop import (
    EV_CYCLE,
    EV_FAILED,
    EV_REPORTS,
    EV_WAITS,
    LS_AWAIT,
    LS_NEXT,
    LS_SEND,
    Loop,
    LoopLink,
)
from edgemodbus._ffi.native import lib
from edgemodbus._ffi.outcomes import Clean, LineCounters
from edgemodbus.protocol import rtu
from edgemodbus.protocol.wrapped import wrap
from edgemodbus.sim import Simulator, default_register
from tests.peers import ExceptionRange, PymodbusSlave
from tests.peers import default_register as pymodbus_register

CLEAN = Clean(settle=0.05, settle_limit=0.2, quiet=0.01, drain_limit=0.1)
KINDS = ("rtu", "wrapped", "echo", "mbap")


@dataclass
class Link:
    ctx: Context
    engine: Engine
    device: EngineDevice
    ll: LoopLink
    counters: LineCounters
    passes: int = 0
    status: int = 0
    reports: list[bytes] = field(default_factory=list)
    handovers: list[tuple[int, int]] = field(default_factory=list)  # (device, before)


def _context(fd: int, label: str, kind: str) -> Context:
    ctx = Context.on_socket(fd, label, mbap=kind == "mbap")
    if kind == "wrapped":
        ctx.set_stream(b"", True)
    elif kind == "echo":
        ctx.set_echo(True)
    return ctx


@contextmanager
def links(loop: Loop, socks: list[socket.socket], specs: list[tuple[int, int]], kind: str,
          timeout: float = 2.0, offline_after: int = 3, cycle: float = 0.05,
          count: int = 10, byte_timeout: float = 0.1) -> Iterator[list[Link]]:
    """A link per (unit, start) on each socket: ``count`` holding registers from start."""
    with ExitStack() as stack:
        out = []
        for slot, (sock, (unit, start)) in enumerate(zip(socks, specs, strict=True)):
            ctx = _context(sock.fileno(), f"{kind}{slot}", kind)
            stack.callback(ctx.close)
            waker = Waker()
            stack.callback(waker.close)
            counters = LineCounters()
            engine = Engine(ctx, waker, counters, 0.0, None, CLEAN)
            device = EngineDevice(unit, timeout, True, cycle)
            device.set_policy(0, offline_after, 0.4)
            device.set_blocks([BlockSpec(3, start, count, cycle, None, True)])
            device.active = True
            engine.set_devices([device])
            ll = LoopLink(loop, slot, engine, ctx, byte_timeout=byte_timeout)
            stack.callback(ll.detach)
            out.append(Link(ctx, engine, device, ll, counters))
        yield out


def connect(port: int, n: int, stack: ExitStack) -> list[socket.socket]:
    socks = []
    for _ in range(n):
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        stack.callback(sock.close)
        socks.append(sock)
    return socks


def take_reports(d: Link, which: int) -> None:
    """What the line worker does after EV_REPORTS, at the C level: the reports before
    the reply, then the rest (their order on the wire)."""
    d.handovers.append((which, d.ctx.reports_before))
    d.reports.extend(d.ctx.take_reports())


def drive(d: Link, limit: int | None = None) -> None:
    """Run link d until it waits, or until it made ``limit`` passes."""
    while limit is None or d.passes < limit:
        ev = d.ll.run()
        if ev == EV_WAITS:
            return
        if ev == EV_REPORTS:
            take_reports(d, d.engine.event_device)
            continue
        assert ev == EV_CYCLE, (d.ll.slot, ev, d.engine.event_errno)
        for _ in d.engine.take_ended():
            d.passes += 1
            d.status |= d.device.take_status()


def serve(loop: Loop, ds: list[Link], seconds: float, done: Callable[[], bool],
          limit: int | None = None) -> None:
    """Run the loop on this thread for up to ``seconds`` or until ``done()``."""
    until = time.monotonic() + seconds
    for d in ds:
        drive(d, limit)
    while time.monotonic() < until and not done():
        turn = loop.wait(min(until, time.monotonic() + 0.5))
        for s in sorted({s for s, _ in turn.ready} | set(turn.expired)):
            drive(ds[s], limit)


def passes_made(ds: list[Link], n: int) -> Callable[[], bool]:
    return lambda: all(d.passes >= n for d in ds)


def run_blocking(d: Link, passes: int) -> None:
    """The same link on the blocking engine (csrc/emb_engine.c), pass for pass."""
    d.ll.detach()
    os.set_blocking(d.ctx.fd, True)
    try:
        while d.passes < passes:
            ev = d.engine.run(time.monotonic() + 60)
            if ev == ENGINE_REPORTS:
                take_reports(d, d.engine.event_device)
                continue
            assert ev == ENGINE_CYCLE, ev
            for _ in d.engine.take_ended():
                d.passes += 1
                d.status |= d.device.take_status()
    finally:
        d.ll.loop.watch(d.ctx.fd, d.ll.slot)  # detached again on the way out


def outcome(d: Link) -> tuple[object, ...]:
    """A link's device after its passes: counters, state and failures (errno, reply)."""
    c = d.device.counts()
    failures = [(f.kind, f.errno, f.reply, f.length, f.header)
                for f in d.device.take_failures()]
    return (d.passes, c.requests, c.responses, c.timeouts, c.exceptions, c.retries,
            c.failed_cycles, c.cycles, bool(d.device.offline), d.status, failures)


def values_of(d: Link) -> list[int]:
    block = d.device.data(0)
    assert block is not None
    return list(block.to_list())


# -- wrapped streams and echoing lines, against the simulator ----------------------------

@contextmanager
def simulator(kind: str, echo_fault: bool = False) -> Iterator[tuple[Simulator, int]]:
    """Slaves 1 (good) and 2 (no FC03: exception 01) on a raw RTU-over-TCP port
    (wrapped frames for "wrapped"), each echoing its requests with ``echo_fault`` or
    for "echo"; slave 9 is not there (silent)."""
    with Simulator(slaves=[1, 2]) as sim:
        sim.slave(2).set_faults(refused_functions=frozenset({3}))
        for unit in (1, 2):
            sim.slave(unit).set_faults(echo_request=echo_fault or kind == "echo")
        yield sim, sim.serve_tcp("127.0.0.1", 0, wrapped=kind == "wrapped")


@pytest.mark.parametrize("kind", ["wrapped", "echo"])
def test_wrapped_and_echoing_links_on_one_thread_read_exact_values(kind: str) -> None:
    specs = [(1, 0), (2, 0), (1, 500)]
    with simulator(kind) as (sim, port), Loop(4) as loop, ExitStack() as stack:
        sim.slave(2).set_faults(refused_functions=frozenset())
        ds = stack.enter_context(links(loop, connect(port, 3, stack), specs, kind))
        serve(loop, ds, 30, lambda: all(d.passes >= 10 for d in ds))
        for d, (unit, start) in zip(ds, specs, strict=True):
            assert d.passes >= 10
            assert values_of(d) == [default_register(unit, a) for a in range(start, start + 10)]
            counts = d.counters.counts()
            assert counts.timeouts == 0 and counts.protocol_errors == 0, counts
            if kind == "echo":  # each request's 8 bytes came back first and were skipped
                assert counts.discarded_bytes >= 8 * counts.responses
        assert all(not d.reports for d in ds)


@pytest.mark.parametrize("kind", ["wrapped", "echo", "echo-unset"])
def test_the_fault_counts_match_the_blocking_engine(kind: str) -> None:
    """Differential: the same devices, pass for pass, on both engines (a good slave, an
    exception on every read, a silent slave with a retry that goes offline; an echoing
    line without the echo option: every read fails as "the line echoes") end with the
    same counters, status and failures (errno and rejected reply)."""
    results = []
    for engine in ("loop", "thread"):
        with simulator("rtu" if kind == "echo-unset" else kind,
                       echo_fault=kind == "echo-unset") as (_, port), \
                Loop(4) as loop, ExitStack() as stack:
            ds = stack.enter_context(links(
                loop, connect(port, 3, stack), [(1, 0), (2, 0), (9, 0)],
                "rtu" if kind == "echo-unset" else kind, timeout=0.5, offline_after=2))
            for d in ds:
                d.device.set_policy(1, 2, 0.2)
            if engine == "loop":
                serve(loop, ds, 60, passes_made(ds, 5), limit=5)
            else:
                for d in ds:
                    run_blocking(d, 5)
            results.append([outcome(d) for d in ds])
    loop_run, blocking = results
    assert loop_run == blocking
    good, refused, silent = loop_run
    assert silent[8] is True  # offline
    if kind == "echo-unset":
        failures = good[10]
        assert isinstance(failures, list) and failures
        assert all(f[1] == lib.EMB_EECHOSEEN for f in failures)
    else:
        assert good[2] == 5 and refused[4] == ((1, 5),)


@contextmanager
def scripted(kind: str, timeout: float = 5.0,
             byte_timeout: float = 0.1) -> Iterator[tuple[Loop, Link, socket.socket]]:
    """One link on a socketpair whose other end the test plays byte for byte: slave 1,
    holding registers 0..1, one pass a minute, a 5 s reply timeout."""
    peer, ours = socket.socketpair()
    with ExitStack() as stack:
        stack.callback(peer.close)
        stack.callback(ours.close)
        loop = stack.enter_context(Loop(1))
        (d,) = stack.enter_context(links(loop, [ours], [(1, 0)], kind, timeout=timeout,
                                         cycle=60.0, count=2, byte_timeout=byte_timeout))
        peer.settimeout(10)
        yield loop, d, peer


def test_reports_around_a_wrapped_reply_are_handed_over_in_their_order() -> None:
    """An edge MCU sends a report, the reply and another report in one segment: the
    reply answers (its slave, function, address and byte count), the reports are
    handed over with the read (EV_REPORTS, the device named), the one before the reply
    marked as before it, as the blocking engine hands them to the line worker."""
    with scripted("wrapped") as (loop, d, peer):
        drive(d)
        assert peer.recv(64) == wrap(0, 1, bytes([3, 0, 0, 0, 2]))
        before = wrap(5, 1, bytes([3, 4, 0, 1, 0, 2]))  # the MCU's own report of 5..6
        reply = wrap(0, 1, bytes([3, 4, 0, 7, 0, 8]))
        after = wrap(0, 1, bytes([3, 2, 0, 9]))  # of 0 only: not the answer (count 2)
        peer.sendall(before + reply + after)
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert values_of(d) == [7, 8]
        assert d.reports == [before, after]
        assert d.handovers == [(0, 1)]


def test_a_wrapped_report_while_idle_is_handed_over_alone() -> None:
    with scripted("wrapped") as (loop, d, peer):
        drive(d)
        peer.recv(64)
        peer.sendall(wrap(0, 1, bytes([3, 4, 0, 7, 0, 8])))
        serve(loop, [d], 30, lambda: d.passes >= 1)
        report = wrap(40, 1, bytes([3, 2, 0x12, 0x34]))
        peer.sendall(report)
        serve(loop, [d], 30, lambda: bool(d.reports))
        assert d.reports == [report] and d.handovers == [(-1, 0)]
        assert values_of(d) == [7, 8]


def test_an_echo_that_differs_from_the_request_fails_the_read() -> None:
    """With the echo option the request's own bytes must come back first: other bytes
    fail the read as a wrong echo (EMB_EECHO), as on the blocking engine."""
    with scripted("echo") as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        assert sent == rtu.frame(1, bytes([3, 0, 0, 0, 2]))
        peer.sendall(bytes([sent[0] ^ 0x40]) + sent[1:] + rtu.frame(1, bytes([3, 4, 0, 7, 0, 8])))
        serve(loop, [d], 30, lambda: d.device.has_failures)
        (failure,) = d.device.take_failures()
        assert failure.errno == lib.EMB_EECHO


def test_an_echo_then_its_reply_in_pieces() -> None:
    """The echo and the reply arrive byte by byte: the echo is skipped, the reply read
    whole."""
    with scripted("echo", byte_timeout=5.0) as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        data = sent + rtu.frame(1, bytes([3, 4, 0, 7, 0, 8]))
        for k in range(len(data)):
            peer.sendall(data[k:k + 1])
            serve(loop, [d], 0.01, lambda: False)
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert values_of(d) == [7, 8]
        assert d.counters.counts().discarded_bytes == len(sent)


# -- Modbus TCP against pymodbus -----------------------------------------------------------

def test_modbus_tcp_links_on_one_thread_read_exact_values() -> None:
    specs = [(1, 0), (2, 100), (1, 500)]
    with PymodbusSlave("tcp", units=(1, 2)) as slave, Loop(4) as loop, \
            ExitStack() as stack:
        ds = stack.enter_context(links(loop, connect(slave.port, 3, stack), specs, "mbap"))
        serve(loop, ds, 30, lambda: all(d.passes >= 10 for d in ds))
        for d, (unit, start) in zip(ds, specs, strict=True):
            assert values_of(d) == [pymodbus_register(unit, "hr", a)
                                    for a in range(start, start + 10)]
            counts = d.counters.counts()
            assert counts.timeouts == 0 and counts.protocol_errors == 0, counts
            assert counts.responses >= 10


def test_modbus_tcp_fault_counts_match_the_blocking_engine() -> None:
    """Differential over MBAP: a good unit, exception 02 on every read, a unit pymodbus
    does not serve (silent), pass for pass on both engines."""
    results = []
    for engine in ("loop", "thread"):
        with PymodbusSlave("tcp", units=(1,), exception_ranges=[
                ExceptionRange(100, 110, code=2, unit=1)]) as slave, \
                Loop(4) as loop, ExitStack() as stack:
            ds = stack.enter_context(links(loop, connect(slave.port, 3, stack),
                                           [(1, 0), (1, 100), (9, 0)], "mbap",
                                           timeout=0.5, offline_after=2))
            for d in ds:
                d.device.set_policy(1, 2, 0.2)
            if engine == "loop":
                serve(loop, ds, 60, passes_made(ds, 5), limit=5)
            else:
                for d in ds:
                    run_blocking(d, 5)
            results.append([outcome(d) for d in ds])
    assert results[0] == results[1]
    good, refused, silent = results[0]
    assert good[2] == 5 and refused[4] == ((2, 5),) and silent[8] is True


def _mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return tid.to_bytes(2, "big") + b"\0\0" + (len(pdu) + 1).to_bytes(2, "big") + \
        bytes([unit]) + pdu


def test_a_reply_to_an_older_transaction_is_skipped_for_ours() -> None:
    """A Modbus TCP peer answers a request we gave up on after we sent the next: that
    reply (its transaction id) is skipped and ours taken; a repeated reply to ours
    behind it wins (the last answer), and the MBAP length is checked."""
    with scripted("mbap") as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        tid = int.from_bytes(sent[:2], "big")
        assert sent == _mbap(tid, 1, bytes([3, 0, 0, 0, 2]))
        old = _mbap(tid - 1, 1, bytes([3, 4, 0, 1, 0, 2]))
        peer.sendall(old)
        serve(loop, [d], 0.05, lambda: False)
        assert d.passes == 0
        peer.sendall(_mbap(tid, 1, bytes([3, 4, 0, 7, 0, 8])))
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert values_of(d) == [7, 8]
        assert d.counters.counts().discarded_bytes == len(old)


def test_only_old_transactions_answer_then_the_read_fails_naming_them() -> None:
    """Only a reply to another transaction came within the reply timeout: the read fails
    with EMB_ETID (not a plain timeout), as on the blocking engine."""
    with scripted("mbap", timeout=1.0) as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        tid = int.from_bytes(sent[:2], "big")
        peer.sendall(_mbap(tid + 7, 1, bytes([3, 4, 0, 1, 0, 2])))
        serve(loop, [d], 30, lambda: d.device.has_failures)
        assert [f.errno for f in d.device.take_failures()] == [lib.EMB_ETID]


def test_a_bad_mbap_length_is_a_protocol_error() -> None:
    with scripted("mbap") as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        bad = bytearray(_mbap(int.from_bytes(sent[:2], "big"), 1, bytes([3, 4, 0, 7, 0, 8])))
        bad[2] = 1  # protocol id 0x0100
        peer.sendall(bytes(bad))
        serve(loop, [d], 30, lambda: d.device.has_failures)
        (failure,) = d.device.take_failures()
        assert failure.errno == lib.EMB_EPROTOID and failure.header == 7



# -- the frame trace -------------------------------------------------------------------------

def _traced(kind: str, engine: str, port: int) -> list[tuple[bool, bytes]]:
    """The frames one link traced over 3 passes on ``engine``: (sent, bytes)."""
    with Loop(2) as loop, ExitStack() as stack:
        (d,) = stack.enter_context(links(loop, connect(port, 1, stack), [(1, 0)], kind))
        d.ctx.set_trace(True)
        if engine == "loop":
            serve(loop, [d], 30, passes_made([d], 3), limit=3)
        else:
            run_blocking(d, 3)
        frames, lost = d.ctx.take_trace()
        assert lost == 0
        return [(f.tx, f.frame) for f in frames]


@pytest.mark.parametrize("kind", KINDS)
def test_the_loop_traces_the_frames_the_blocking_engine_traces(kind: str) -> None:
    """Differential: every frame sent and received, in order, the same bytes on both
    engines (a wrapped link traces the RTU frame inside, Modbus TCP the whole ADU)."""
    with ExitStack() as stack:
        if kind == "mbap":
            port = stack.enter_context(PymodbusSlave("tcp", units=(1,))).port
        else:
            _, port = stack.enter_context(simulator(kind))
        loop_run = _traced(kind, "loop", port)
        blocking = _traced(kind, "thread", port)
    assert loop_run == blocking
    assert [tx for tx, _ in loop_run] == [True, False] * 3
    request = loop_run[0][1]
    body = bytes([1, 3, 0, 0, 0, 10])
    assert request[6:] == body if kind == "mbap" else request == rtu.frame(1, body[1:])


# -- a request that does not go out whole ---------------------------------------------------

def _fill_send_buffer(sock: socket.socket) -> int:
    """Send until the socket takes no more: the bytes sent."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    sock.setblocking(False)
    sent = 0
    while True:
        try:
            sent += sock.send(b"\0" * 1024)
        except BlockingIOError:
            return sent


@contextmanager
def full_buffer(timeout: float) -> Iterator[tuple[Loop, Link, socket.socket, int]]:
    peer, ours = socket.socketpair()
    with ExitStack() as stack:
        stack.callback(peer.close)
        stack.callback(ours.close)
        peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        junk = _fill_send_buffer(ours)
        loop = stack.enter_context(Loop(1))
        (d,) = stack.enter_context(links(loop, [ours], [(1, 0)], "rtu", timeout=timeout,
                                         cycle=60.0, count=2))
        peer.settimeout(10)
        yield loop, d, peer, junk


def test_a_request_on_a_full_send_buffer_goes_out_once_the_socket_drains() -> None:
    """The socket's send buffer is full when the read begins: the link waits (sending,
    the socket watched for writing), not failed; once the peer drains it the request
    goes out whole and its reply is read."""
    with full_buffer(timeout=5.0) as (loop, d, peer, junk):
        drive(d)
        assert d.ll.state == LS_SEND
        assert d.counters.counts().requests == 1
        serve(loop, [d], 0.05, lambda: False)
        assert d.ll.state == LS_SEND  # a full buffer is no reason to give up
        request = rtu.frame(1, bytes([3, 0, 0, 0, 2]))
        got = b""
        while len(got) < junk + len(request):
            got += peer.recv(65536)
            serve(loop, [d], 0.001, lambda: False)
        assert got[junk:] == request and got[:junk] == b"\0" * junk
        assert d.ll.state == LS_AWAIT
        peer.sendall(rtu.frame(1, bytes([3, 4, 0, 7, 0, 8])))
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert values_of(d) == [7, 8]
        assert d.counters.counts().timeouts == 0


def test_a_peer_that_takes_nothing_within_the_reply_timeout_fails_the_link() -> None:
    with full_buffer(timeout=0.2) as (loop, d, _peer, _junk):
        start = time.monotonic()
        ev = d.ll.run()
        while ev == EV_WAITS and time.monotonic() < start + 30:
            loop.wait(start + 30)
            ev = d.ll.run()
        assert ev == EV_FAILED and d.engine.event_errno == errno.ETIMEDOUT
        assert 0.15 <= time.monotonic() - start < 10


# -- the last answer wins, also while it is still arriving ----------------------------------

@pytest.mark.parametrize("kind", ["rtu", "mbap"])
def test_a_second_answer_still_arriving_is_waited_for_and_wins(kind: str) -> None:
    """A late reply and the real one come back to back, the second cut in two pieces: the
    link waits for its rest (up to the byte timeout from its last bytes) and takes it,
    as the blocking receive does; the first is dropped, counted."""
    with scripted(kind, byte_timeout=5.0) as (loop, d, peer):
        drive(d)
        sent = peer.recv(64)
        if kind == "mbap":
            tid = int.from_bytes(sent[:2], "big")
            stale = _mbap(tid, 1, bytes([3, 4, 0, 1, 0, 2]))  # a repeat with other values
            fresh = _mbap(tid, 1, bytes([3, 4, 0, 7, 0, 8]))
        else:
            stale = rtu.frame(1, bytes([3, 4, 0, 1, 0, 2]))
            fresh = rtu.frame(1, bytes([3, 4, 0, 7, 0, 8]))
        cut = len(fresh) - 3
        peer.sendall(stale + fresh[:cut])
        serve(loop, [d], 30, lambda: d.ll.state == LS_NEXT)
        assert d.passes == 0
        peer.sendall(fresh[cut:])
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert values_of(d) == [7, 8]
        assert d.counters.counts().discarded_bytes == len(stale)


def test_a_second_frame_that_stops_short_leaves_the_first_answer() -> None:
    """The frame behind the reply never completes: after the byte timeout the reply
    stands (its values taken), the rest is stale and dropped before the next request."""
    with scripted("rtu", byte_timeout=0.1) as (loop, d, peer):
        drive(d)
        peer.recv(64)
        reply = rtu.frame(1, bytes([3, 4, 0, 7, 0, 8]))
        peer.sendall(reply + rtu.frame(1, bytes([3, 4, 0, 1, 0, 2]))[:6])
        start = time.monotonic()
        serve(loop, [d], 30, lambda: d.passes >= 1)
        assert time.monotonic() - start >= 0.09  # the byte timeout was waited out
        assert values_of(d) == [7, 8]
        assert d.counters.counts().protocol_errors == 0
