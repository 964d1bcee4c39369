"""One loop turn in one C call (csrc/emb_loop_turn.c, ``Loop.turn``): the loop waits and
runs every ready or expired link without coming back to Python until a link has
something Python must see.  Against pymodbus (RTU over TCP, an independent slave)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager

import pytest

import edgemodbus as em
from edgemodbus._ffi.loop import (
    EV_CYCLE,
    EV_WAITS,
    EV_WAKE,
    LS_IDLE,
    SLOT_DUE,
    SLOT_READY,
    Loop,
    LoopLink,
)
from edgemodbus._ffi.outcomes import ST_BACK
from edgemodbus.datatypes import ItemStatus
from tests.integration.test_loop_connect import device, exact, running
from tests.integration.test_loop_link import Dtu, dtus
from tests.peers import PymodbusSlave, default_register
from tests.waiting import wait_for


def take(d: Dtu, ev: int) -> int:
    """Python's part after the turn listed link d with event ev: the passes, then the
    link run again until it waits (as line/loop.py LoopWorker._step does) or comes
    back EV_WAKE (its jobs flagged: left to the caller); that last event."""
    while True:
        for _ in d.engine.take_ended():
            d.passes += 1
            d.status |= d.device.take_status()
        if ev in (EV_WAITS, EV_WAKE):
            return ev
        assert ev == EV_CYCLE, ev
        ev = d.link.run()


@contextmanager
def three_links(loop: Loop, port: int) -> Iterator[list[Dtu]]:
    """Three links, each run once (their first request out)."""
    with dtus(loop, port, [(1, 0), (2, 100), (1, 500)]) as links:
        for d in links:
            take(d, d.link.run())
        yield links


def turn_and_take(loop: Loop, links: list[Dtu], until: float) -> list[tuple[int, int]]:
    turn = loop.turn(until)
    for slot, ev in turn.events:
        take(links[slot], ev)
    return turn.events


def test_a_pass_comes_back_once_and_values_are_exact() -> None:
    """Each pass of these blocks has news (their data kept for Python): the turn comes
    back once per pass at most, with the pass, never for the request's deadline or its
    reply alone (a plain wait comes back for both: two crossings per read)."""
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave, Loop(8) as loop, \
            three_links(loop, slave.port) as links:
        first = sum(d.passes for d in links)
        turns = 0
        until = time.monotonic() + 60
        while time.monotonic() < until and not all(d.passes >= 20 for d in links):
            events = turn_and_take(loop, links, min(until, time.monotonic() + 0.5))
            turns += 1
            assert events and all(ev == EV_CYCLE for _, ev in events), events
            assert len({slot for slot, _ in events}) == len(events)
        for d, (unit, start) in zip(links, [(1, 0), (2, 100), (1, 500)], strict=True):
            assert d.device.passes >= 20
            block = d.device.data(0)
            assert block is not None
            assert block.to_list() == [default_register(unit, "hr", a)
                                       for a in range(start, start + 10)]
            assert d.counters.counts().timeouts == 0
            assert d.status & ST_BACK
        assert turns <= sum(d.passes for d in links) - first


def test_jobs_flag_brings_an_idle_link_back_before_its_next_request() -> None:
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave, Loop(8) as loop, \
            three_links(loop, slave.port) as links:
        job = links[1]
        job.link.jobs = True
        seen: list[tuple[int, int]] = []
        until = time.monotonic() + 30
        while time.monotonic() < until and not seen:
            for slot, ev in loop.turn(until).events:
                if take(links[slot], ev) == EV_WAKE:
                    seen.append((slot, EV_WAKE))
        assert seen == [(1, EV_WAKE)]
        assert job.link.state == LS_IDLE
        requests = job.counters.counts().requests
        time.sleep(0.2)  # pacing: not a wait for a condition: the link must stay still (held)
        assert (1, EV_WAKE) not in turn_and_take(loop, links, time.monotonic() + 0.2)
        assert job.counters.counts().requests == requests  # held: not run by the turn
        job.link.jobs = False
        passes = job.passes
        take(job, job.link.run())
        wait_for(lambda: turn_and_take(loop, links, time.monotonic() + 0.1) is None
                 or job.passes >= passes + 5, timeout=30)


def test_slots_without_a_link_and_a_wake_up() -> None:
    a, peer = socket.socketpair()
    with ExitStack() as stack, Loop(4) as loop:
        for s in (a, peer):
            stack.callback(s.close)
        loop.watch(a.fileno(), 2)
        loop.set_timer(3, time.monotonic())
        loop.set_timer(2, time.monotonic())  # both ready and expired: listed once, due
        peer.send(b"x")
        turn = loop.turn(time.monotonic() + 5)
        assert sorted(turn.events) == [(2, SLOT_DUE), (3, SLOT_DUE)]
        turn = loop.turn(time.monotonic() + 5)  # still readable (level-triggered)
        assert turn.events == [(2, SLOT_READY)]
        a.recv(16)
        threading.Timer(0.05, loop.wake).start()
        start = time.monotonic()
        turn = loop.turn(start + 30)
        assert turn.events == [] and turn.woken
        assert time.monotonic() - start < 25
        turn = loop.turn(time.monotonic() + 0.05)  # the caller's deadline: nothing
        assert turn == ([], False)


def reads(drivers: list[em.DriverModbusRtu]) -> int:
    return sum(int(d.stats()["requests"]) for d in drivers)


def test_a_loop_worker_runs_unchanged_passes_without_python(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Two endpoints on one loop thread, values that never change: the worker's Python
    runs a link (LoopLink.run) far less than once per read.  Before the turn was one C
    call it ran each link at least twice per read (the request's deadline, its reply)."""
    calls = [0]
    real = LoopLink.run

    def counted(self: LoopLink) -> int:
        calls[0] += 1
        return real(self)

    monkeypatch.setattr(LoopLink, "run", counted)
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave:
        cfgs = [device(slave.port, 1), device(slave.port, 2)]
        with running(*cfgs) as drivers:
            wait_for(lambda: all(it.status is ItemStatus.OK
                                 for cfg in cfgs for it in cfg.address_list), timeout=60)
            assert exact(cfgs[0], 1) and exact(cfgs[1], 2)
            before, first = calls[0], reads(drivers)
            wait_for(lambda: reads(drivers) >= first + 40, timeout=60)
            runs, made = calls[0] - before, reads(drivers) - first
            assert runs < made / 2, (runs, made)
            assert exact(cfgs[0], 1) and exact(cfgs[1], 2)


def test_a_job_owed_a_read_waits_for_one_due_read_then_has_the_link() -> None:
    """The fairness rule of csrc/emb_engine.c on a loop link: with a job run since the
    last read (``owed``) and a read due, the link sends that one read before it comes
    back for the next job; with nothing due, the job has the link at once."""
    with PymodbusSlave("rtu-over-tcp", units=(1, 2)) as slave, Loop(8) as loop, \
            three_links(loop, slave.port) as links:
        job = links[0]
        wait_for(lambda: turn_and_take(loop, links, time.monotonic() + 0.05) is not None
                 and job.link.state == LS_IDLE and job.passes >= 2, timeout=30)
        requests = job.counters.counts().requests
        job.device.all_due(time.monotonic())  # a read due now
        job.link.jobs = job.link.owed = True
        ev = job.link.run()
        # not EV_WAKE: the read went out first; the link waits for its reply, or took it
        # in the same run (a loaded machine descheduled the thread between the request
        # and the look for its reply) and the pass ended
        assert ev in (EV_WAITS, EV_CYCLE), ev
        assert job.counters.counts().requests == requests + 1 and not job.link.owed
        woke = ev == EV_CYCLE and take(job, ev) == EV_WAKE  # the read's pass, the job's turn
        until = time.monotonic() + 30
        while not woke and time.monotonic() < until:
            for slot, ev in loop.turn(until).events:
                if slot != 0:
                    take(links[slot], ev)
                    continue
                woke = take(job, ev) == EV_WAKE  # the read's pass, then the job's turn
        assert woke and job.link.state == LS_IDLE
        assert job.counters.counts().requests == requests + 1  # one read, no more
        job.device.all_due(time.monotonic() + 60)  # nothing due
        job.link.owed = True
        assert job.link.run() == EV_WAKE and not job.link.owed
        assert job.counters.counts().requests == requests + 1
        job.link.jobs = False
        job.device.all_due(time.monotonic())
        take(job, job.link.run())


def test_writes_queued_while_the_link_awaits_a_reply_run_once_it_is_idle() -> None:
    """Every reply comes 0.2 s late and a pass (two reads) is due again before it ends,
    so the link is awaiting a reply when the writes are queued: the worker flags the
    jobs (``LoopLink.jobs``), the turn brings the link back once idle, and each write
    reaches the slave.  Without the flag the writes would wait for a pass with news."""
    writes = {"h2": 11, "h3": 12, "h4": 13}
    pool = ThreadPoolExecutor(3)  # the writes queued together, from three threads
    try:
        with PymodbusSlave("rtu-over-tcp", units=(1,)) as slave:
            cfg = device(slave.port, 1, readTimeout=2000)
            with running(cfg) as (drv,):
                wait_for(lambda: all(it.status is ItemStatus.OK
                                     for it in cfg.address_list), timeout=60)
                slave.set_response_delay(0.2)
                cycles = drv.stats()["cycles"]
                wait_for(lambda: drv.stats()["cycles"] >= cycles + 2, timeout=60)  # late now
                futures = [pool.submit(drv.write_address, k, v) for k, v in writes.items()]
                assert [f.result(30) for f in futures] == [(True, None)] * 3
                assert slave.registers(1, "hr", 2, 3) == [11, 12, 13]
                slave.set_response_delay(0.0)
                item = {it.name: it for it in cfg.address_list}
                wait_for(lambda: all(item[k].value == v for k, v in writes.items()),
                         timeout=60)
    finally:
        pool.shutdown(wait=True)  # after stop_device: a write still queued has failed
