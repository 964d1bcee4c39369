"""Links of the loop engine (csrc/emb_loop_link.c): several DTU streams served by one
thread (this test's) through one epoll set and deadline heap, against pymodbus
(RTU over TCP, an independent slave): exact values on every link, and the fault policy
of the blocking engine on a silent slave (timeouts, settle, offline with backoff)."""

from __future__ import annotations

import errno
import os
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass

from edgemodbus._ffi.context import Context
from edgemodbus._ffi.engine import EV_CYCLE as ENGINE_CYCLE
from edgemodbus._ffi.engine import BlockSpec, Engine, EngineDevice, Waker
from edgemodbus._ffi.loop import EV_CYCLE, EV_FAILED, EV_WAITS, LS_FAILED, Loop, LoopLink
from edgemodbus._ffi.outcomes import ST_BACK, ST_OFFLINE, Clean, LineCounters
from edgemodbus.protocol import rtu
from tests.peers import ExceptionRange, PymodbusSlave, default_register

CLEAN = Clean(settle=0.05, settle_limit=0.2, quiet=0.01, drain_limit=0.1)


@dataclass
class Dtu:
    sock: socket.socket
    ctx: Context
    engine: Engine
    device: EngineDevice
    link: LoopLink
    counters: LineCounters
    passes: int = 0
    status: int = 0


@contextmanager
def dtus(loop: Loop, port: int, specs: list[tuple[int, int]], timeout: float = 0.5,
         offline_after: int = 3, clean: Clean = CLEAN) -> Iterator[list[Dtu]]:
    """One connection per (unit, start): 10 holding registers from start, 50 ms cycle."""
    with ExitStack() as stack:
        out = []
        for slot, (unit, start) in enumerate(specs):
            sock = socket.create_connection(("127.0.0.1", port), timeout=10)
            stack.callback(sock.close)
            ctx = Context.on_socket(sock.fileno(), f"dtu{slot}", mbap=False)
            stack.callback(ctx.close)
            waker = Waker()
            stack.callback(waker.close)
            counters = LineCounters()
            engine = Engine(ctx, waker, counters, 0.0, None, clean)
            device = EngineDevice(unit, timeout, True, 0.05)
            device.set_policy(0, offline_after, 0.4)
            device.set_blocks([BlockSpec(3, start, 10, 0.05, None, True)])
            device.active = True
            engine.set_devices([device])
            link = LoopLink(loop, slot, engine, ctx, byte_timeout=0.1)
            stack.callback(link.detach)
            out.append(Dtu(sock, ctx, engine, device, link, counters))
        yield out


def drive(d: Dtu, limit: int | None = None) -> None:
    """Run link d until it waits (every EV_CYCLE taken: a link that came back with one
    is not running until it is run again), or until it made ``limit`` passes."""
    while limit is None or d.passes < limit:
        ev = d.link.run()
        if ev == EV_WAITS:
            return
        assert ev == EV_CYCLE, (d.link.slot, ev, d.engine.event_errno)
        for _ in d.engine.take_ended():
            d.passes += 1
            d.status |= d.device.take_status()


def serve(loop: Loop, links: list[Dtu], until: float, done: Callable[[], bool],
          limit: int | None = None) -> None:
    """Run the loop on this thread until ``done()`` or ``until``; a link stops after
    ``limit`` passes (its deadline left unset)."""
    for d in links:
        drive(d, limit)
    while time.monotonic() < until and not done():
        turn = loop.wait(min(until, time.monotonic() + 0.5))
        for s in sorted({s for s, _ in turn.ready} | set(turn.expired)):
            drive(links[s], limit)


def test_three_dtus_on_one_thread_read_exact_values() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave, Loop(8) as loop, \
            dtus(loop, slave.port, [(1, 0), (2, 100), (1, 500)]) as links:
        serve(loop, links, time.monotonic() + 30, lambda: all(d.passes >= 10 for d in links))
        for d, (unit, start) in zip(links, [(1, 0), (2, 100), (1, 500)], strict=True):
            assert d.passes >= 10
            block = d.device.data(0)
            assert block is not None
            assert block.to_list() == [default_register(unit, "hr", a)
                                       for a in range(start, start + 10)]
            counts = d.counters.counts()
            assert counts.timeouts == 0 and counts.protocol_errors == 0, counts
            assert d.status & ST_BACK


def test_a_silent_slave_times_out_goes_offline_and_is_probed_with_backoff() -> None:
    """Unit 9 is not served (pymodbus stays silent, as an RS-485 slave that is off):
    every pass times out, after 3 the slave is offline and probed once per backoff; the
    link beside it on the same loop keeps its cycle."""
    with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave, Loop(4) as loop, \
            dtus(loop, slave.port, [(9, 0), (1, 0)], timeout=0.1) as links:
        silent, good = links
        start = time.monotonic()
        serve(loop, links, start + 30, lambda: bool(silent.device.offline)
              and silent.counters.counts().timeouts >= 5)
        assert silent.device.offline and silent.status & ST_OFFLINE
        assert silent.counters.counts().timeouts >= 5
        assert good.passes >= 10  # the silent link never held the good one
        block = good.device.data(0)
        assert block is not None
        assert block.to_list() == [default_register(1, "hr", a) for a in range(10)]


def test_a_late_reply_is_waited_out_and_dropped() -> None:
    """The slave answers after the reply timeout: each late reply comes while the link
    settles and is dropped (counted), never taken for the next request's answer; once
    the slave is quick again, the values read are the slave's new ones."""
    settle = Clean(settle=0.3, settle_limit=0.6, quiet=0.01, drain_limit=0.1)
    with PymodbusSlave("rtu-over-tcp", units=(1,), response_delay=0.15) as slave, \
            Loop(2) as loop, dtus(loop, slave.port, [(1, 0)], timeout=0.1,
                                  offline_after=100, clean=settle) as links:
        (d,) = links
        serve(loop, links, time.monotonic() + 30,
              lambda: d.counters.counts().timeouts >= 3
              and d.counters.counts().discarded_bytes >= 3 * 25)
        counts = d.counters.counts()
        assert counts.timeouts >= 3 and counts.responses == 0
        assert counts.discarded_bytes >= 3 * 25  # 25 bytes a reply of 10 registers
        new = [4000 + a for a in range(10)]
        slave.set_registers(1, "hr", 0, new)
        slave.set_response_delay(0.0)
        passes = d.passes
        serve(loop, links, time.monotonic() + 30,
              lambda: d.counters.counts().responses >= 5 and d.passes >= passes + 5)
        block = d.device.data(0)
        assert block is not None and block.to_list() == new
        assert d.counters.counts().protocol_errors == 0


def _counts_after(engine: str, port: int, passes: int) -> list[tuple[object, ...]]:
    """Per link, the device's fault counters and state after exactly ``passes`` passes
    on the loop engine (each link run from Python: "loop"; one C call per turn: "turn")
    or on the blocking engine (csrc/emb_engine.c: "thread")."""
    specs = [(1, 0), (1, 100), (9, 0)]  # good; exception 02 on every read; silent
    with Loop(4) as loop, dtus(loop, port, specs, timeout=0.1, offline_after=2) as links:
        for d in links:
            d.device.set_policy(1, 2, 0.2)  # a retry per timeout; offline after 2
        if engine == "loop":
            serve(loop, links, time.monotonic() + 60,
                  lambda: all(d.passes >= passes for d in links), limit=passes)
        elif engine == "turn":  # one C call per turn (Loop.turn); a link at its limit
            for d in links:      # stays held, so the turn runs it no more
                drive(d, passes)
            until = time.monotonic() + 60
            while time.monotonic() < until and not all(d.passes >= passes for d in links):
                for slot, ev in loop.turn(min(until, time.monotonic() + 0.5)).events:
                    d = links[slot]
                    assert ev == EV_CYCLE, (slot, ev)
                    for _ in d.engine.take_ended():
                        d.passes += 1
                        d.status |= d.device.take_status()
                    drive(d, passes)
        else:
            for d in links:
                d.link.detach()
                os.set_blocking(d.ctx.fd, True)
                while d.passes < passes:
                    assert d.engine.run(time.monotonic() + 60) == ENGINE_CYCLE
                    for _ in d.engine.take_ended():
                        d.passes += 1
                        d.status |= d.device.take_status()
                d.link.loop.watch(d.ctx.fd, d.link.slot)  # detached again on the way out
        out: list[tuple[object, ...]] = []
        for d in links:
            c = d.device.counts()
            out.append((d.passes, c.requests, c.responses, c.timeouts, c.exceptions,
                        c.retries, c.failed_cycles, c.skipped_blocks, c.cycles,
                        bool(d.device.offline), d.status, d.device.has_failures))
        return out


def test_the_fault_counts_match_the_blocking_engine() -> None:
    """Differential: the same devices, pass for pass, on both engines (a good slave, an
    exception on every read, a silent slave with a retry that goes offline) end with
    the same counters, status and failures; the loop also with one C call per turn."""
    with PymodbusSlave("rtu-over-tcp", units=(1,), exception_ranges=[
            ExceptionRange(100, 110, code=2, unit=1)]) as slave:
        loop = _counts_after("loop", slave.port, 6)
        turn = _counts_after("turn", slave.port, 6)
        blocking = _counts_after("thread", slave.port, 6)
    assert loop == blocking
    assert turn == blocking
    assert loop[1][4] == ((2, 6),) and loop[2][9] is True  # the cases happened


@contextmanager
def scripted() -> Iterator[tuple[Loop, Dtu, socket.socket]]:
    """One link on a socketpair whose other end the test plays (a DTU, byte for byte):
    slave 1, holding registers 0..1, one pass a minute, a 5 s reply timeout."""
    peer, ours = socket.socketpair()
    with ExitStack() as stack:
        stack.callback(peer.close)
        stack.callback(ours.close)
        loop = stack.enter_context(Loop(1))
        ctx = Context.on_socket(ours.fileno(), "dtu", mbap=False)
        stack.callback(ctx.close)
        waker = Waker()
        stack.callback(waker.close)
        counters = LineCounters()
        engine = Engine(ctx, waker, counters, 0.0, None, CLEAN)
        device = EngineDevice(1, 5.0, True, 60.0)
        device.set_blocks([BlockSpec(3, 0, 2, 60.0, None, True)])
        device.active = True
        engine.set_devices([device])
        link = LoopLink(loop, 0, engine, ctx, byte_timeout=0.1)
        stack.callback(link.detach)
        peer.settimeout(10)
        yield loop, Dtu(ours, ctx, engine, device, link, counters), peer


def test_the_last_answer_behind_a_reply_wins() -> None:
    """A DTU that held a late reply sends it together with the answer to the next
    request: the later frame answers, the earlier one is dropped (as csrc/emb_io.c)."""
    with scripted() as (loop, d, peer):
        drive(d)
        assert peer.recv(64) == rtu.frame(1, bytes([3, 0, 0, 0, 2]))
        stale = rtu.frame(1, bytes([3, 4, 0, 1, 0, 2]))
        fresh = rtu.frame(1, bytes([3, 4, 0, 7, 0, 8]))
        peer.sendall(stale + fresh)
        serve(loop, [d], time.monotonic() + 30, lambda: d.passes >= 1)
        block = d.device.data(0)
        assert block is not None and block.to_list() == [7, 8]
        assert d.counters.counts().discarded_bytes == len(stale)


def test_a_closed_link_comes_back_as_failed() -> None:
    """The DTU hangs up while a reply is awaited: the link comes back EV_FAILED with the
    errno, for Python to close it (as the blocking engine's EMB_EV_FAILED)."""
    with scripted() as (loop, d, peer):
        drive(d)
        assert peer.recv(64)
        peer.close()
        deadline = time.monotonic() + 30
        ev = EV_WAITS
        while ev == EV_WAITS and time.monotonic() < deadline:
            loop.wait(deadline)
            ev = d.link.run()
        assert ev == EV_FAILED and d.link.state == LS_FAILED
        assert d.engine.event_errno in (errno.ECONNRESET, errno.EPIPE, errno.ENOTCONN)
        assert d.engine.event_device == 0
        assert d.counters.counts().timeouts == 0
