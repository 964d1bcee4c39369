"""The line engine of csrc/emb_engine.c: a device's C state, the engine of one link, and
the waker by which other threads interrupt it.

Times cross as ``time.monotonic()`` seconds (CLOCK_MONOTONIC, the clock C reads);
counters are kept in C, where other threads read them live (:class:`NativeCounts`).
"""

from __future__ import annotations

import contextlib
import os
import weakref
from collections.abc import Sequence
from typing import NamedTuple

from ..stats import CYCLE_BUCKETS, NativeCounts
from .block import Block
from .codec import CODEC_MODE_ALL, CODEC_MODE_TRACK, CodecPlan
from .context import Context
from .native import ffi, lib

EV_DEADLINE: int = lib.EMB_EV_DEADLINE
EV_CYCLE: int = lib.EMB_EV_CYCLE
EV_FAILED: int = lib.EMB_EV_FAILED
EV_WAKE: int = lib.EMB_EV_WAKE
EV_INPUT: int = lib.EMB_EV_INPUT
EV_ERROR: int = lib.EMB_EV_ERROR
EV_REPORTS: int = lib.EMB_EV_REPORTS  # a read took wrapped reports besides its reply
EV_TRACE: int = lib.EMB_EV_TRACE  # the frame trace has frames to log (Link.run_engine did)

_NEVER = (1 << 63) - 1
_BOUNDS = ffi.new("int64_t[]", [round(b * 1e9) for b in CYCLE_BUCKETS])
_N_HIST = len(CYCLE_BUCKETS) + 1
assert _N_HIST <= lib.EMB_HIST_MAX


def _ns(seconds: float) -> int:
    return _NEVER if seconds == float("inf") else round(seconds * 1e9)


def _seconds(ns: int) -> float:
    return float("inf") if ns == _NEVER else ns / 1e9


class BlockSpec(NamedTuple):
    """One planned read as the engine sees it."""

    function: int  # 1..4
    start: int
    size: int  # registers or bits
    period: float  # seconds
    plan: CodecPlan | None  # its whole items, or None
    keep: bool  # Python reads the block's data after every good read (pieces)


class EngineDevice:
    """One polled slave's C state (``emb_device``): its blocks, pass and schedule.

    Owned by a poller; touched by its line's worker only (and never while the engine
    runs, which is on that same thread)."""

    def __init__(self, slave: int, timeout: float, report_all: bool, cycle: float,
                 coalesce: float = 0.0) -> None:
        self.coalesce = coalesce  # > 0: every block keeps its last read, this long fresh
        self._dev = ffi.new("emb_device *")
        dev = self._dev
        dev.slave = slave
        dev.timeout_ms = max(1, round(timeout * 1000))
        dev.mode = CODEC_MODE_ALL if report_all else CODEC_MODE_TRACK
        dev.cycle_ns = _ns(cycle)
        dev.due_ns = dev.notify_ns = _NEVER
        self._specs: list[BlockSpec] = []
        self._buffers: list[Block | None] = []
        self.set_blocks([])

    @property
    def slave(self) -> int:
        return int(self._dev.slave)

    # -- the plan ---------------------------------------------------------------------
    def set_blocks(self, specs: Sequence[BlockSpec], dues: Sequence[float] | None = None) -> None:
        """Install a new plan; ``dues``: each block's due time (default: due now)."""
        n = len(specs)
        blocks = ffi.new("emb_eblock[]", max(n, 1))
        buffers: list[Block | None] = []
        for k, spec in enumerate(specs):
            b = blocks[k]
            b.function = spec.function
            b.start = spec.start
            b.count = spec.size
            b.period_ns = _ns(spec.period)
            b.plan = spec.plan._plan if spec.plan is not None else ffi.NULL
            buf = None
            if spec.keep or self.coalesce > 0:
                bits = spec.function <= 2
                buf = Block(ffi.new("uint8_t[]" if bits else "uint16_t[]", spec.size), bits)
                b.data = buf._ptr
                b.keep = spec.keep
            buffers.append(buf)
        self._blocks = blocks
        self._pass = ffi.new("uint32_t[]", max(n, 1))
        self._specs = list(specs)  # keeps the plans alive while C points at them
        self._buffers = buffers
        dev = self._dev
        dev.blocks = blocks
        dev.pass_list = self._pass
        dev.n_blocks = n
        dev.n_pass = 0
        dev.index = 0
        dev.in_pass = 0
        if dues is None:
            self.all_due(0.0)
        else:
            for k, due in enumerate(dues):
                blocks[k].due_ns = _ns(due)

    def split(self, at: int, specs: Sequence[BlockSpec]) -> None:
        """Replace block ``at`` by ``specs`` (exception 02 bisection), which inherit its
        due time; the pass under way reads them in its place."""
        dev = self._dev
        old_pass = self.pass_blocks()
        index, in_pass = int(dev.index), int(dev.in_pass)
        dues = [self.due_of(k) for k in range(len(self._specs))]
        due = dues[at]
        grow = len(specs) - 1
        new_specs = self._specs[:at] + list(specs) + self._specs[at + 1:]
        self.set_blocks(new_specs, dues[:at] + [due] * len(specs) + dues[at + 1:])
        new_pass: list[int] = []
        for k in old_pass:
            if k < at:
                new_pass.append(k)
            elif k == at:
                new_pass.extend(range(at, at + len(specs)))
            else:
                new_pass.append(k + grow)
        for k, block in enumerate(new_pass):
            self._pass[k] = block
        dev.n_pass = len(new_pass)
        dev.index = index
        dev.in_pass = in_pass
        dev.due_ns = min((int(self._blocks[k].due_ns) for k in range(len(new_specs))),
                         default=_NEVER) if not in_pass else dev.due_ns

    # -- settings ---------------------------------------------------------------------
    @property
    def cycle(self) -> float:
        """The readCycle of a device with no blocks (0: never due)."""
        return _seconds(int(self._dev.cycle_ns))

    @cycle.setter
    def cycle(self, seconds: float) -> None:
        self._dev.cycle_ns = _ns(seconds)

    @property
    def report_all(self) -> bool:
        """Every item of every block is reported at each read (EMB_MODE_ALL)."""
        return bool(self._dev.mode == CODEC_MODE_ALL)

    @report_all.setter
    def report_all(self, on: bool) -> None:
        self._dev.mode = CODEC_MODE_ALL if on else CODEC_MODE_TRACK

    @property
    def notify_at(self) -> float:
        """The first pass ending after this time is handed to Python (inf: none)."""
        return _seconds(int(self._dev.notify_ns))

    @notify_at.setter
    def notify_at(self, at: float) -> None:
        self._dev.notify_ns = _ns(at)

    @property
    def active(self) -> bool:
        return bool(self._dev.active)

    @active.setter
    def active(self, on: bool) -> None:
        self._dev.active = 1 if on else 0

    @property
    def notify(self) -> bool:
        return bool(self._dev.notify)

    @notify.setter
    def notify(self, on: bool) -> None:
        self._dev.notify = 1 if on else 0

    # -- the pass and the schedule ------------------------------------------------------
    @property
    def due(self) -> float:
        """When the device's next pass begins (inf: never)."""
        return _seconds(int(self._dev.due_ns))

    @property
    def period(self) -> float:
        """The shortest scan rate of its blocks (its cycle when it has none)."""
        return min((spec.period for spec in self._specs), default=self.cycle)

    @property
    def in_pass(self) -> bool:
        return bool(self._dev.in_pass)

    @property
    def index(self) -> int:
        return int(self._dev.index)

    @index.setter
    def index(self, value: int) -> None:
        self._dev.index = value

    @property
    def taken(self) -> int:
        """How many blocks of the pass Python has taken the results of."""
        return int(self._dev.taken)

    @taken.setter
    def taken(self, value: int) -> None:
        self._dev.taken = value

    @property
    def passes(self) -> int:
        """Passes begun (the cycle number the pieces of large items are matched by)."""
        return int(self._dev.passes)

    def pass_blocks(self) -> list[int]:
        """Block indices of the pass under way (or the last one, once it ended)."""
        return list(ffi.unpack(self._pass, int(self._dev.n_pass)))

    def reported(self, block: int) -> int:
        """The count the block's last decode returned (see BlockDecoder.finish)."""
        return int(self._blocks[block].reported)

    def data(self, block: int) -> Block | None:
        """The block's own buffer (blocks with ``keep``), holding its last read."""
        buf = self._buffers[block]
        if buf is not None:
            buf.count = self._specs[block].size
        return buf

    def cached(self, function: int, start: int, count: int, since: float) -> list[int] | None:
        """The values (registers, or bits as 0/1) at ``start..start+count`` of function
        ``function`` from a block of this device read (its request sent) at or after
        ``since`` and within :attr:`coalesce` seconds (``time.monotonic()``), or None when
        no such block holds them all.  The worker's thread only."""
        if self.coalesce <= 0:
            return None
        since_ns = max(_ns(since), lib.emb_now_ns() - _ns(self.coalesce))
        for k, spec in enumerate(self._specs):
            buf = self._buffers[k]
            if (buf is None or spec.function != function or start < spec.start
                    or start + count > spec.start + spec.size):
                continue
            read_ns = int(self._blocks[k].read_ns)
            if read_ns and read_ns >= since_ns:
                return list(ffi.unpack(buf._ptr + (start - spec.start), count))
        return None

    def due_of(self, block: int) -> float:
        return _seconds(int(self._blocks[block].due_ns))

    def begin_pass(self, now: float) -> int:
        """Begin a pass (the blocks due at ``now``); 0 if none is due yet."""
        return int(lib.emb_dev_begin_pass(self._dev, _ns(now)))

    def end_pass(self, now: float) -> bool:
        """End the pass under way: count it and reschedule its blocks; True if it
        overran a block's period."""
        return bool(lib.emb_dev_end_pass(self._dev, _ns(now), _BOUNDS, len(CYCLE_BUCKETS)))

    def all_due(self, at: float) -> None:
        """Every block due at ``at`` (a start, a new plan, a new link, an offline probe)."""
        lib.emb_dev_all_due(self._dev, _ns(at))

    def counts(self) -> NativeCounts:
        """The device's counters, read live (any thread)."""
        c = self._dev.c
        return NativeCounts(
            requests=c.requests, responses=c.responses, cycles=c.cycles,
            overruns=c.overruns, last_cycle_time=c.last_cycle_ns / 1e9,
            total_cycle_time=c.total_cycle_ns / 1e9, max_cycle_time=c.max_cycle_ns / 1e9,
            cycle_hist=tuple(c.hist[0:_N_HIST]),
        )


class LineCounters:
    """A line's request counters (``emb_line_counters``), kept by the engines of its
    successive links."""

    def __init__(self) -> None:
        self._lc = ffi.new("emb_line_counters *")

    def counts(self) -> NativeCounts:
        """Read live (any thread)."""
        lc = self._lc
        return NativeCounts(requests=lc.requests, responses=lc.responses,
                            rtt_total=lc.rtt_ns / 1e9, discarded_bytes=lc.discarded,
                            heartbeats=lc.heartbeats)


class Waker:
    """How other threads interrupt a line's engine: a flag the engine reads between two
    transactions and an eventfd it polls while it waits."""

    def __init__(self) -> None:
        self._flag = ffi.new("int *")
        self.fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._close = weakref.finalize(self, os.close, self.fd)

    def signal(self) -> None:
        """Any thread: a job is queued."""
        self._flag[0] = 1
        if self._close.alive:
            os.eventfd_write(self.fd, 1)

    def clear(self) -> None:
        """The worker, before it takes the queued jobs."""
        self._flag[0] = 0
        with contextlib.suppress(BlockingIOError):
            os.eventfd_read(self.fd)

    @property
    def is_open(self) -> bool:
        return self._close.alive

    def close(self) -> None:
        self._close()


class Engine:
    """The engine of one open link (``emb_engine``): runs its devices' passes in C."""

    def __init__(self, ctx: Context, waker: Waker, counters: LineCounters, pace: float,
                 watch_fd: int | None) -> None:
        e = ffi.new("emb_engine *")
        e.lc = counters._lc
        e.ctx = ctx._ptr
        e.lk = ctx._link
        e.rsp = ctx._rsp
        e.regs = ctx.registers._ptr
        e.bits = ctx.bits._ptr
        e.wake_fd = waker.fd
        e.wake = waker._flag
        e.watch_fd = -1 if watch_fd is None else watch_fd
        e.timeout_ms = -1
        e.pace_ns = round(pace * 1e9)
        e.bounds_ns = _BOUNDS
        e.n_bounds = len(CYCLE_BUCKETS)
        self._e = e
        self._ctx = ctx
        self._counters = counters  # C points at them
        self.waker = waker
        self._devices: tuple[EngineDevice, ...] = ()
        self._ptrs = ffi.new("emb_device *[]", 1)

    def set_devices(self, devices: Sequence[EngineDevice]) -> None:
        devices = tuple(devices)
        if devices == self._devices:
            return
        self._ptrs = ffi.new("emb_device *[]", [d._dev for d in devices] or [ffi.NULL])
        self._e.devices = self._ptrs
        self._e.n_devices = len(devices)
        self._devices = devices

    def run(self, until: float, ready_at: float, owed: bool = False) -> int:
        """Poll until something needs Python (an ``EV_*``) or ``until``; ``ready_at``:
        no request before then (the pacing of the Python side); ``owed``: a queued job
        ran since the last read, so a job queued meanwhile waits for one read of a due
        block before ``EV_WAKE`` (fair line scheduling, csrc/emb_engine.c)."""
        e = self._e
        e.ready_ns = _ns(ready_at)
        e.owed = 1 if owed else 0
        e.timeout_ms = -1  # Python may have set another one
        return int(lib.emb_engine_run(e, _ns(until)))

    @property
    def ready_at(self) -> float:
        return _seconds(int(self._e.ready_ns))

    @property
    def owed(self) -> bool:
        """The read the last run owed is still owed (it came back before making one)."""
        return bool(self._e.owed)

    @property
    def event_device(self) -> int:
        return int(self._e.event_device)

    @property
    def event_errno(self) -> int:
        return int(self._e.event_errno)
