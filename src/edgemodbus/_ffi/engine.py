"""The line engine of csrc/emb_engine.c: a device's C state and the engine of one link
(the waker by which other threads interrupt it: waker.py).

Times cross as ``time.monotonic()`` seconds (CLOCK_MONOTONIC, the clock C reads);
counters are kept in C, where other threads read them live (:class:`NativeCounts`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

from ..stats import CYCLE_BUCKETS, NativeCounts
from .block import Block
from .codec import CODEC_MODE_ALL, CODEC_MODE_TRACK, CodecPlan
from .context import Context
from .native import MAX_READ_BITS, MAX_READ_REGISTERS, ffi, lib
from .outcomes import Clean, Failure, LineCounters, exception_counts
from .waker import Waker as Waker  # the engine's: line/ imports it from here

EV_DEADLINE: int = lib.EMB_EV_DEADLINE
EV_CYCLE: int = lib.EMB_EV_CYCLE
EV_FAILED: int = lib.EMB_EV_FAILED
EV_WAKE: int = lib.EMB_EV_WAKE
EV_INPUT: int = lib.EMB_EV_INPUT
EV_ERROR: int = lib.EMB_EV_ERROR
EV_REPORTS: int = lib.EMB_EV_REPORTS  # wrapped reports C did not apply (csrc/emb_report.c)
EV_TRACE: int = lib.EMB_EV_TRACE  # the frame trace has frames to log (Link.run_engine did)
EV_SPLIT: int = lib.EMB_EV_SPLIT  # exception 02 on a splittable block: Python splits it

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
    splittable: bool = False  # more than one piece: exception 02 splits it (EV_SPLIT)
    # wrapped reports inside the block may be applied in C (csrc/emb_report.c): per item
    # of ``plan``, its first register (or bit) in the block and its quantity, flat; None:
    # not here (a report of it goes to Python)
    report_spans: tuple[int, ...] | None = None


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
        dev.cycle_ns = dev.backoff_ns = _ns(cycle)
        dev.due_ns = dev.notify_ns = _NEVER
        self.set_policy(0, 1, cycle)
        self._specs: list[BlockSpec] = []
        self._buffers: list[Block | None] = []
        self._spans: list[Any] = []  # the blocks' report spans, which C points at
        self.set_blocks([])

    @property
    def slave(self) -> int:
        return int(self._dev.slave)

    def set_policy(self, retries: int, offline_after: int, max_backoff: float) -> None:
        """The fault policy the engine runs (csrc/emb_fault.c): a timeout or CRC error is
        read again ``retries`` times; ``offline_after`` failed cycles in a row take the
        slave offline, probed once per backoff (its cycle, doubling up to
        ``max_backoff`` seconds)."""
        dev = self._dev
        dev.retries = retries
        dev.offline_after = max(1, offline_after)
        dev.max_backoff_ns = _ns(max_backoff)

    # -- the plan ---------------------------------------------------------------------
    def set_blocks(self, specs: Sequence[BlockSpec], dues: Sequence[float] | None = None) -> None:
        """Install a new plan; ``dues``: each block's due time (default: due now)."""
        n = len(specs)
        blocks = ffi.new("emb_eblock[]", max(n, 1))
        buffers: list[Block | None] = []
        self._spans = []
        for k, spec in enumerate(specs):
            buffers.append(self._fill(blocks[k], spec))
        self._blocks = blocks
        self._pass = ffi.new("uint32_t[]", max(n, 1))
        self._reported_list = ffi.new("uint32_t[]", max(n, 1))
        self._specs = list(specs)  # keeps the plans alive while C points at them
        self._buffers = buffers
        dev = self._dev
        dev.blocks = blocks
        dev.pass_list = self._pass
        dev.rep_list = self._reported_list
        dev.n_rep = 0  # (the poller took the reports of the old plan)
        dev.n_blocks = n
        dev.n_pass = 0
        dev.index = 0
        dev.in_pass = 0
        if dues is None:
            self.all_due(0.0)
        else:
            for k, due in enumerate(dues):
                blocks[k].due_ns = _ns(due)

    def _fill(self, b: Any, spec: BlockSpec) -> Block | None:
        """Set the C block ``b`` from ``spec``; its own buffer, if it needs one."""
        b.function = spec.function
        b.start = spec.start
        b.count = spec.size
        b.period_ns = _ns(spec.period)
        b.plan = plan = spec.plan._plan if spec.plan is not None else ffi.NULL
        b.splittable = 1 if spec.splittable else 0
        spans = spec.report_spans  # (with a scale factor table, reports stay Python's)
        if spans and plan and not (plan.n_sf or plan.n_sf_src) and len(spans) == 2 * plan.n_items:
            b.rep_span = span = ffi.new("uint32_t[]", spans)
            self._spans.append(span)
            b.rep_ok = 1
        if not (spec.keep or self.coalesce > 0):
            return None
        bits = spec.function <= 2
        buf = Block(ffi.new("uint8_t[]" if bits else "uint16_t[]", spec.size), bits)
        b.data = buf._ptr
        b.keep = spec.keep
        return buf

    def split(self, at: int, specs: Sequence[BlockSpec]) -> None:
        """Replace block ``at`` by ``specs`` (an exception 02 bisection, planned by the
        poller): the engine puts them in its place (emb_dev_split), with its due time
        and its place in the pass under way, which goes on with the first of them.  The
        new arrays are allocated here, once per split, never in the engine's loop."""
        n = len(self._specs) + len(specs) - 1
        blocks = ffi.new("emb_eblock[]", n)
        pass_list = ffi.new("uint32_t[]", n)
        new = [self._fill(blocks[at + j], spec) for j, spec in enumerate(specs)]
        if lib.emb_dev_split(self._dev, blocks, pass_list, at, len(specs)) == -1:
            raise ValueError(f"engine: no block {at} to split (of {len(self._specs)})")
        reported = ffi.new("uint32_t[]", n)  # room for every block, as C renumbered them
        dev = self._dev
        reported[0:dev.n_rep] = ffi.unpack(dev.rep_list, int(dev.n_rep))
        dev.rep_list = self._reported_list = reported
        self._blocks, self._pass = blocks, pass_list
        self._specs[at:at + 1] = list(specs)
        self._buffers[at:at + 1] = new

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

    # -- the fault policy's outcomes (csrc/emb_fault.c) ----------------------------------
    @property
    def ended(self) -> bool:
        """A pass ended that Python has not taken yet (the engine listed it)."""
        return bool(self._dev.ended)

    def take_end(self) -> None:
        """Python takes the pass that ended."""
        self._dev.ended = 0

    @property
    def has_failures(self) -> bool:
        return bool(self._dev.fail_news)

    def failed(self, block: int) -> bool:
        """The block's last read failed (or was not made: the slave was silent)."""
        return bool(self._blocks[block].fail_kind)

    def take_failures(self) -> list[Failure]:
        """The failures Python has not taken yet, in plan order; they become known (the
        engine tells the same failure again only after :meth:`forget_failures`)."""
        dev = self._dev
        out: list[Failure] = []
        if not dev.fail_news:
            return out
        dev.fail_news = 0
        for k in range(int(dev.n_blocks)):
            b = self._blocks[k]
            if not b.fail_new:
                continue
            b.fail_new = 0
            b.fail_known = 1
            length = int(b.fail_rsp_len)
            out.append(Failure(k, int(b.fail_kind), int(b.fail_errno), int(b.fail_function),
                               int(b.fail_start), int(b.fail_count),
                               bytes(ffi.buffer(b.fail_rsp, min(length, lib.EMB_FAIL_RSP))),
                               length, int(b.fail_header)))
        return out

    def take_reports(self) -> list[tuple[int, int]]:
        """(block, count) of the wrapped reports the engine decoded into a block's plan
        (csrc/emb_report.c), in the order they came: read each decode (its decoder's
        ``finish(count)``) before the engine runs again."""
        dev, blocks = self._dev, self._blocks
        taken = ffi.unpack(self._reported_list, int(dev.n_rep)) if dev.n_rep else []
        dev.n_rep = 0
        for k in taken:
            blocks[k].rep_pending = 0
        return [(k, int(blocks[k].rep_n)) for k in taken]

    def forget_failures(self) -> None:
        """Items of the blocks were set from elsewhere (a write, a report): a failure of
        them is told again, as news."""
        for k in range(int(self._dev.n_blocks)):
            self._blocks[k].fail_known = 0

    def take_status(self) -> int:
        """The status changes (ST_* bits) the engine made since the last call."""
        ev = int(self._dev.status_ev)
        self._dev.status_ev = 0
        return ev

    def link_lost(self) -> None:
        """The link went down: the slave is Running again once it answers."""
        self._dev.running = 0

    @property
    def failed_cycles(self) -> int:
        """Failed cycles in a row."""
        return int(self._dev.failed_cycles)

    @property
    def offline(self) -> bool:
        return bool(self._dev.offline)

    @property
    def backoff(self) -> float:
        """The probe interval while offline (seconds)."""
        return _seconds(int(self._dev.backoff_ns))

    def counts(self) -> NativeCounts:
        """The device's counters, read live (any thread)."""
        c = self._dev.c
        return NativeCounts(
            requests=c.requests, responses=c.responses, cycles=c.cycles,
            overruns=c.overruns, last_cycle_time=c.last_cycle_ns / 1e9,
            total_cycle_time=c.total_cycle_ns / 1e9, max_cycle_time=c.max_cycle_ns / 1e9,
            cycle_hist=tuple(c.hist[0:_N_HIST]), timeouts=c.timeouts,
            crc_errors=c.crc_errors, protocol_errors=c.protocol_errors,
            exceptions=exception_counts(c.exceptions),
            exceptions_other=c.exceptions.other, retries=c.retries,
            failed_cycles=c.failed_cycles, skipped_blocks=c.skipped_blocks,
            reports=c.reports,
        )


class Engine:
    """The engine of one open link (``emb_engine``): runs its devices' passes in C."""

    def __init__(self, ctx: Context, waker: Waker, counters: LineCounters, pace: float,
                 watch_fd: int | None, clean: Clean) -> None:
        """``clean``: how the line is settled after a timeout and drained after a bad
        frame (line/link.py)."""
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
        e.settle_ms = round(clean.settle * 1000)
        e.settle_limit_ms = round(clean.settle_limit * 1000)
        e.quiet_ms = max(1, round(clean.quiet * 1000))
        e.drain_limit_ms = round(clean.drain_limit * 1000)
        # where a wrapped report's registers or bits are rebuilt (csrc/emb_report.c)
        self._scratch = (ffi.new("uint16_t[]", MAX_READ_REGISTERS),
                         ffi.new("uint8_t[]", MAX_READ_BITS))
        e.rep_regs, e.rep_bits = self._scratch
        self._e = e
        self._ctx = ctx
        self._counters = counters  # C points at them
        self.waker = waker
        self._devices: tuple[EngineDevice, ...] = ()
        self._ptrs = ffi.new("emb_device *[]", 1)
        self._ended = ffi.new("uint32_t[]", 1)
        e.ended_list = self._ended

    def set_devices(self, devices: Sequence[EngineDevice]) -> None:
        devices = tuple(devices)
        if devices == self._devices:
            return
        for device in devices:
            device.take_end()  # a pass listed by another engine: its list is gone
        self._ptrs = ffi.new("emb_device *[]", [d._dev for d in devices] or [ffi.NULL])
        self._ended = ffi.new("uint32_t[]", max(1, len(devices)))
        e = self._e
        e.devices = self._ptrs
        e.n_devices = len(devices)
        e.ended_list = self._ended
        e.n_ended = 0
        self._devices = devices

    @property
    def native(self) -> Any:
        """The ``emb_engine *`` (for the loop engine's links, _ffi/loop.py)."""
        return self._e

    def run(self, until: float, owed: bool = False) -> int:
        """Poll until something needs Python (an ``EV_*``) or ``until``; ``owed``: a
        queued job ran since the last read, so a job queued meanwhile waits for one read
        of a due block before ``EV_WAKE`` (fair line scheduling, csrc/emb_engine.c)."""
        e = self._e
        e.owed = 1 if owed else 0
        return int(lib.emb_engine_run(e, _ns(until)))

    def take_ended(self) -> list[int]:
        """The indices of the devices whose passes ended with something for Python
        (EV_CYCLE, or still listed when the engine came back for another reason)."""
        e = self._e
        n = int(e.n_ended)
        if not n:
            return []
        e.n_ended = 0
        ended = list(ffi.unpack(self._ended, n))
        for k in ended:
            self._devices[k].take_end()  # even if Python fails to handle it
        return ended

    @property
    def ready_at(self) -> float:
        """No request before this (the line's pacing, which the link's own requests
        keep here too)."""
        return _seconds(int(self._e.ready_ns))

    @ready_at.setter
    def ready_at(self, at: float) -> None:
        self._e.ready_ns = _ns(at)

    @property
    def timeout_ms(self) -> int:
        """The response timeout the engine last set on the context (-1: unknown)."""
        return int(self._e.timeout_ms)

    @timeout_ms.setter
    def timeout_ms(self, ms: int) -> None:
        self._e.timeout_ms = ms

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
