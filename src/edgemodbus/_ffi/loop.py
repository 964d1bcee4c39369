"""The core of the loop engine (csrc/emb_loop.c): one epoll set, one wake-up
eventfd and one min-heap of deadlines that a loop thread serves many links with.

A link is a *slot* number ``0 <= slot < capacity``; its socket is watched under that
slot and it has at most one deadline (the earliest its state machine waits for).  Only
the owning thread calls :meth:`Loop.wait` and the slot methods; any thread may call
:meth:`Loop.wake`.  Times are ``time.monotonic()`` seconds (CLOCK_MONOTONIC, the clock C
reads).  :meth:`Loop.wait` runs without the GIL.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any, NamedTuple

from .native import ffi, lib

if TYPE_CHECKING:
    from .context import Context
    from .engine import Engine

READABLE: int = lib.EMB_LOOP_IN
WRITABLE: int = lib.EMB_LOOP_OUT
HANGUP: int = lib.EMB_LOOP_HUP
ERROR: int = lib.EMB_LOOP_ERR

_NO_TIMER: int = lib.EMB_LOOP_NO_TIMER
_BATCH = 63  # ready sockets per wait (csrc/emb_loop.c EMB_LOOP_BATCH less the eventfd)


def _ns(seconds: float) -> int:
    return _NO_TIMER if seconds == float("inf") else round(seconds * 1e9)


class Turn(NamedTuple):
    """What one :meth:`Loop.wait` found: the ready slots with their events (``READABLE``
    ...), the slots whose deadline passed (earliest first; their deadline is gone), and
    whether another thread woke the loop."""

    ready: list[tuple[int, int]]
    expired: list[int]
    woken: bool


class LinkTurn(NamedTuple):
    """What one :meth:`Loop.turn` hands back: ``(slot, event)`` per link or slot Python
    must see, and whether another thread woke the loop."""

    events: list[tuple[int, int]]
    woken: bool


class Loop:
    """One loop thread's epoll set, eventfd and deadlines for ``capacity`` slots."""

    def __init__(self, capacity: int) -> None:
        if not isinstance(capacity, int) or not 1 <= capacity <= 1 << 24:
            raise ValueError(f"loop capacity {capacity!r}: must be an integer 1..{1 << 24}")
        self.capacity = capacity
        self._heap = ffi.new("emb_timer[]", capacity)
        self._pos = ffi.new("uint32_t[]", capacity)
        self._lp = ffi.new("emb_loop *")
        self._lp.cap = capacity
        self._lp.heap = self._heap
        self._lp.pos = self._pos
        self._ready = ffi.new("uint32_t[]", _BATCH)
        self._events = ffi.new("uint32_t[]", _BATCH)
        self._expired = ffi.new("uint32_t[]", capacity)
        self._links = ffi.new("emb_loop_link *[]", capacity)  # by slot (LoopLink)
        self._kept: dict[int, Any] = {}  # each emb_loop_link in _links, kept alive
        self._out_slot = ffi.new("uint32_t[]", _BATCH + capacity)
        self._out_ev = ffi.new("int[]", _BATCH + capacity)
        self._n_expired = ffi.new("int *")
        self._woken = ffi.new("int *")
        if lib.emb_loop_open(self._lp) == -1:
            err = ffi.errno
            raise OSError(err, f"loop: cannot open its epoll set or eventfd: {os.strerror(err)}")

    def close(self) -> None:
        """Close the epoll set and the eventfd (idempotent); the sockets stay the caller's."""
        lib.emb_loop_close(self._lp)

    def __enter__(self) -> Loop:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _slot(self, slot: int) -> int:
        if not isinstance(slot, int) or not 0 <= slot < self.capacity:
            raise ValueError(f"loop slot {slot!r}: must be an integer 0..{self.capacity - 1}")
        return slot

    def watch(self, fd: int, slot: int, want_write: bool = False) -> None:
        """Watch socket ``fd`` for ``slot`` (readable; writable too with ``want_write``);
        again for a watched fd changes what is watched."""
        if lib.emb_loop_watch(self._lp, fd, self._slot(slot), 1 if want_write else 0) == -1:
            err = ffi.errno
            raise OSError(err, f"loop: cannot watch fd {fd} for slot {slot}: {os.strerror(err)}")

    def unwatch(self, fd: int) -> None:
        """Stop watching ``fd`` (before it is closed)."""
        if lib.emb_loop_unwatch(self._lp, fd) == -1:
            err = ffi.errno
            raise OSError(err, f"loop: cannot unwatch fd {fd}: {os.strerror(err)}")

    def wake(self) -> None:
        """Wake the loop's :meth:`wait` (any thread; wake-ups coalesce)."""
        if lib.emb_loop_wake(self._lp) == -1:
            err = ffi.errno
            raise OSError(err, f"loop: cannot wake: {os.strerror(err)}")

    def set_timer(self, slot: int, due: float) -> None:
        """Set (or move) ``slot``'s deadline to ``due`` (monotonic seconds)."""
        lib.emb_timer_set(self._lp, self._slot(slot), _ns(due))

    def clear_timer(self, slot: int) -> None:
        """Remove ``slot``'s deadline, if any."""
        lib.emb_timer_clear(self._lp, self._slot(slot))

    def timer_of(self, slot: int) -> float | None:
        """``slot``'s deadline in monotonic seconds, None without one."""
        ns = int(lib.emb_timer_of(self._lp, self._slot(slot)))
        return None if ns == _NO_TIMER else ns / 1e9

    def next_due_ns(self) -> int | None:
        """The earliest deadline (CLOCK_MONOTONIC ns), None without any."""
        ns = int(lib.emb_timer_next(self._lp))
        return None if ns == _NO_TIMER else ns

    @property
    def n_timers(self) -> int:
        """Deadlines set."""
        return int(self._lp.n_timers)

    def wait(self, until: float) -> Turn:
        """Sleep (GIL released) until a socket is ready, a deadline passes, another thread
        wakes the loop or ``until`` (monotonic seconds); what it found."""
        n = lib.emb_loop_wait(self._lp, _ns(until), self._ready, self._events, _BATCH,
                              self._expired, self.capacity, self._n_expired, self._woken)
        if n == -1:
            err = ffi.errno
            raise OSError(err, f"loop: wait failed: {os.strerror(err)}")
        ready = [(int(self._ready[i]), int(self._events[i])) for i in range(n)]
        expired = [int(self._expired[i]) for i in range(self._n_expired[0])]
        return Turn(ready, expired, bool(self._woken[0]))

    def turn(self, until: float) -> LinkTurn:
        """One turn in one C call (csrc/emb_loop_turn.c, GIL released): wait, run every
        ready or expired link (:class:`LoopLink`), and again, until a link has an event
        for Python, another thread woke the loop or ``until`` (monotonic seconds).

        The events are ``(slot, event)``: a link's (``EV_CYCLE``, ``EV_SPLIT``,
        ``EV_REPORTS``, ``EV_FAILED``, ``EV_WAKE``: idle with :attr:`LoopLink.jobs`
        set, ``EV_COLLECT``: its trace or stream counters hold something), each link
        held until :meth:`LoopLink.run` runs it again; for a slot without a link,
        ``SLOT_READY`` (its socket, a connect under way) or ``SLOT_DUE`` (its
        deadline)."""
        n = lib.emb_loop_turn(self._lp, self._links, _ns(until), self._ready, self._events,
                              _BATCH, self._expired, self._out_slot, self._out_ev,
                              self._woken)
        if n == -1:
            err = ffi.errno
            raise OSError(err, f"loop: turn failed: {os.strerror(err)}")
        out_slot, out_ev = self._out_slot, self._out_ev
        return LinkTurn([(int(out_slot[i]), int(out_ev[i])) for i in range(n)],
                        bool(self._woken[0]))


# the link's states (csrc/emb_loop_link.h) and what its run hands back (csrc/emb_edev.h)
LS_IDLE: int = lib.EMB_LS_IDLE
LS_AWAIT: int = lib.EMB_LS_AWAIT
LS_SETTLE: int = lib.EMB_LS_SETTLE
LS_FAILED: int = lib.EMB_LS_FAILED
LS_SEND: int = lib.EMB_LS_SEND
LS_NEXT: int = lib.EMB_LS_NEXT
EV_WAITS: int = 0  # the link waits for its socket or its deadline
EV_CYCLE: int = lib.EMB_EV_CYCLE
EV_FAILED: int = lib.EMB_EV_FAILED
EV_SPLIT: int = lib.EMB_EV_SPLIT
EV_REPORTS: int = lib.EMB_EV_REPORTS
EV_WAKE: int = lib.EMB_EV_WAKE  # idle, with jobs flagged (LoopLink.jobs)
EV_COLLECT: int = lib.EMB_LT_COLLECT  # Loop.turn: the trace or stream counters to take
SLOT_READY: int = lib.EMB_LT_READY  # Loop.turn: a slot without a link is ready
SLOT_DUE: int = lib.EMB_LT_DUE  # Loop.turn: a slot without a link reached its deadline


class LoopLink:
    """One link as a state machine on ``loop`` under ``slot`` (csrc/emb_loop_link.c):
    the devices, counters and cleaning of ``engine`` (an
    :class:`~edgemodbus._ffi.engine.Engine` on ``ctx``, a context on a connected
    socket), no thread of its own.  The link kind is the context's, as on the blocking
    engine: a DTU stream (plain RTU with heartbeats or the echo option, or wrapped
    frames with their reports: :meth:`run` comes back ``EV_REPORTS``) or Modbus TCP
    (``Context.on_socket(fd, label, mbap=True)``: MBAP header, transaction ids)."""

    def __init__(self, loop: Loop, slot: int, engine: Engine, ctx: Context,
                 byte_timeout: float) -> None:
        if not 0 <= byte_timeout <= 60:
            raise ValueError(f"{ctx.label}: byte timeout {byte_timeout!r} s: must be 0..60")
        self.loop = loop
        self.slot = loop._slot(slot)
        self.engine = engine
        self.ctx = ctx
        if not ctx.mbap:  # a stream is framed in its buffers; MBAP replies in the engine's
            ctx.ensure_stream_buffers()
        fd = ctx.fd
        os.set_blocking(fd, False)
        k = ffi.new("emb_loop_link *")
        k.e = engine.native
        k.fd = fd
        k.slot = slot
        k.state = LS_IDLE
        k.which = -1
        k.byte_ms = round(byte_timeout * 1000)
        self._k = k
        self._paused = False
        loop.watch(fd, slot)
        loop._links[slot] = k  # Loop.turn runs it from now on
        loop._kept[slot] = k

    @property
    def jobs(self) -> bool:
        """Python has jobs for the link: once idle, it comes back ``EV_WAKE`` before
        its next request (set by the loop thread; cleared before running it again)."""
        return bool(self._k.jobs)

    @jobs.setter
    def jobs(self, value: bool) -> None:
        self._k.jobs = 1 if value else 0

    @property
    def owed(self) -> bool:
        """A read is owed before the next job: with :attr:`jobs` set, it comes back
        ``EV_WAKE`` only after sending its next due read, or when nothing is due.  One
        read per flag: Python counts what a job owes (line/loop_jobs.py
        ``job_or_wait``: a job of k transactions owes k) and sets it again per read."""
        return bool(self._k.owed)

    @owed.setter
    def owed(self, value: bool) -> None:
        self._k.owed = 1 if value else 0

    @property
    def state(self) -> int:
        return int(self._k.state)

    def run(self) -> int:
        """Take the link as far as it goes now (GIL released): ``EV_WAITS``, or
        ``EV_CYCLE`` (the engine's ``take_ended``), ``EV_SPLIT``, ``EV_REPORTS`` (the
        context holds wrapped reports, dropped or lost frames: taken before the link
        runs again, as after the blocking engine's EV_REPORTS; ``engine.event_device``:
        the device whose read took them, -1 while idle) or ``EV_FAILED`` for Python,
        which acts and must run it again: only ``EV_WAITS`` leaves a deadline set or a
        socket to wake it.  ``EV_WAKE``: idle with :attr:`jobs` set.  It lets
        :meth:`Loop.turn` run the link again (an event it came back with is taken)."""
        self._k.held = 0
        return int(lib.emb_loop_link_run(self.loop._lp, self._k))

    @property
    def paused(self) -> bool:
        return self._paused

    def pause(self) -> None:
        """Step out of the loop while another thread uses the socket (a job of the
        line, line/loop_jobs.py): not run by :meth:`Loop.turn`, no deadline, the socket
        not watched; its state (idle, a pass under way) is kept for :meth:`resume`.
        Loop thread only."""
        if self._paused:
            return
        self.loop.unwatch(self.ctx.fd)
        self.loop._links[self.slot] = ffi.NULL
        self.loop.clear_timer(self.slot)
        self._paused = True

    def resume(self) -> None:
        """Back in the loop after :meth:`pause` (the socket watched again); Python
        runs it next (:meth:`run`).  Loop thread only."""
        if not self._paused:
            return
        self.loop.watch(self.ctx.fd, self.slot)
        self.loop._links[self.slot] = self._k
        self._paused = False

    def detach(self) -> None:
        """Leave the loop (its deadline and its socket); the socket stays the caller's
        (a paused link's socket is not watched: it may be closed already)."""
        self.loop._links[self.slot] = ffi.NULL
        self.loop._kept.pop(self.slot, None)
        self.loop.clear_timer(self.slot)
        if not self._paused:
            self.loop.unwatch(self.ctx.fd)
        self._paused = False
