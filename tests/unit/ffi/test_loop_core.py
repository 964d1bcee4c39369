"""The core of the loop engine (csrc/emb_loop.c via _ffi/loop.py): the links' deadlines
in one min-heap, checked against a model written here from the contract (a dict of
slot -> due, expired in (due, slot) order); sockets watched by slot; the wake-up eventfd
from another thread; bad arguments named."""

from __future__ import annotations

import socket
import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgemodbus._ffi.loop import HANGUP, READABLE, WRITABLE, Loop

CAP = 16

# an op: ("set", slot, due in ns, all in the past) or ("clear", slot, 0)
_ops = st.lists(
    st.tuples(st.sampled_from(["set", "clear"]), st.integers(0, CAP - 1),
              st.integers(1, 50)),
    max_size=120,
)


@settings(max_examples=300, deadline=None)
@given(_ops)
def test_deadlines_match_a_model(ops: list[tuple[str, int, int]]) -> None:
    model: dict[int, int] = {}
    with Loop(CAP) as lp:
        for op, slot, due in ops:
            if op == "set":
                lp.set_timer(slot, due / 1e9)
                model[slot] = due
            else:
                lp.clear_timer(slot)
                model.pop(slot, None)
            assert lp.n_timers == len(model)
            assert lp.next_due_ns() == (min(model.values()) if model else None)
            for s in range(CAP):
                got = lp.timer_of(s)
                assert (None if got is None else round(got * 1e9)) == model.get(s)
        # every due time is long past: one wait pops them all, earliest first
        turn = lp.wait(0.0)
        assert turn.expired == [s for s, _ in sorted(model.items(), key=lambda kv: (kv[1], kv[0]))]
        assert lp.n_timers == 0 and lp.next_due_ns() is None


def test_a_future_deadline_ends_the_wait_not_before() -> None:
    with Loop(4) as lp:
        start = time.monotonic()
        lp.set_timer(1, start + 0.05)
        lp.set_timer(2, start + 3600)
        expired: list[int] = []
        while not expired:  # an EINTR may end a wait early, with nothing
            turn = lp.wait(start + 30)
            expired = turn.expired
        assert expired == [1]
        assert time.monotonic() >= start + 0.05
        assert lp.timer_of(2) is not None and lp.n_timers == 1


def test_the_callers_deadline_ends_an_idle_wait() -> None:
    with Loop(2) as lp:
        start = time.monotonic()
        turn = lp.wait(start + 0.03)
        assert turn == ([], [], False)
        assert time.monotonic() >= start + 0.03


def test_another_thread_wakes_the_loop() -> None:
    with Loop(2) as lp:
        waker = threading.Thread(target=lp.wake)
        start = time.monotonic()
        waker.start()
        woken = False
        while not woken and time.monotonic() < start + 30:  # EINTR: a wait with nothing
            woken = lp.wait(start + 30).woken
        waker.join()
        assert woken
        # the wake-up was taken: the next wait sleeps to its deadline
        assert lp.wait(time.monotonic() + 0.02).woken is False
        for _ in range(5):  # wake-ups coalesce
            lp.wake()
        assert lp.wait(time.monotonic() + 30).woken is True
        assert lp.wait(time.monotonic()).woken is False


def test_sockets_are_reported_by_slot() -> None:
    a, b = socket.socketpair()
    c, d = socket.socketpair()
    try:
        with Loop(8) as lp:
            lp.watch(a.fileno(), 3)
            lp.watch(c.fileno(), 5)
            assert lp.wait(time.monotonic()).ready == []
            b.send(b"\x01\x03")
            turn = lp.wait(time.monotonic() + 30)
            assert [(s, ev & READABLE) for s, ev in turn.ready] == [(3, READABLE)]
            # level-triggered: still ready until read
            assert [s for s, _ in lp.wait(time.monotonic() + 30).ready] == [3]
            a.recv(16)
            lp.watch(c.fileno(), 5, want_write=True)  # a request only partly sent
            turn = lp.wait(time.monotonic() + 30)
            assert [(s, ev & WRITABLE) for s, ev in turn.ready] == [(5, WRITABLE)]
            lp.watch(c.fileno(), 5)
            d.close()
            turn = lp.wait(time.monotonic() + 30)
            assert [s for s, ev in turn.ready if ev & HANGUP] == [5]
            lp.unwatch(c.fileno())
            lp.unwatch(a.fileno())
            assert lp.wait(time.monotonic()).ready == []
    finally:
        for s in (a, b, c, d):
            s.close()


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match=r"loop capacity 0: must be an integer 1\.\."):
        Loop(0)
    with Loop(4) as lp:
        with pytest.raises(ValueError, match=r"loop slot 4: must be an integer 0\.\.3"):
            lp.set_timer(4, 1.0)
        with pytest.raises(ValueError, match=r"loop slot -1"):
            lp.clear_timer(-1)
        with pytest.raises(OSError, match="cannot unwatch fd"):
            lp.unwatch(9999)
