"""One polled slave on a line: its read cycle and what its faults mean.

A :class:`Poller` is attached to its line.  Its plan lives in C as well
(:class:`~edgemodbus._ffi.engine.EngineDevice`: every block with its own due time, its
items' scan rate, see schedule.py); a cycle is one pass over the blocks due when it
begins.  The line's engine runs whole passes in C, the fault policy included (retries,
settling, offline and backoff: csrc/emb_fault.c, configured once here), on every link
kind and with the frame trace on too, and hands the poller only its outcomes
(:meth:`Poller.engine_cycle` for a pass with news, failures or a status change;
:meth:`Poller.take_results` before wrapped reports or a job; :meth:`Poller.engine_split`
to split a block answered with exception 02; :meth:`Poller.engine_failed` when the link
failed).  Writes queued by other threads run between two blocks.  What it reads goes to
its owner through a :class:`PollSink`.  faults.py words the outcomes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any, cast

from .._ffi import Block
from .._ffi.engine import BlockSpec, EngineDevice
from ..codec import BlockDecoder, Change, ValueSpec
from ..config import DriverModbusRtuParameter, ParsedItem
from ..datatypes import DeviceDriverStatus
from ..errors import ModbusConnectionError
from ..line import LineWorker, Link
from ..line.link import READ_FC
from ..stats import DeviceStats
from .faults import reason_of, status_change
from .items import Assembly, ItemState, Slot, is_news, owner_of, set_state, store_changes
from .on_demand import DemandReads, answer, read_slots, slots_holding
from .periodic import PeriodicReports, reports_all
from .planner import Piece, ReadBlock, bisect_block
from .reports import ReportDecoders, store_taken
from .schedule import build_plan as build_plan  # the CLI's plan command uses it
from .schedule import item_rate
from .sink import Delivery, PollSink
from .store import ItemStore, check_free
from .writes import WriteOp, Writer

if TYPE_CHECKING:
    from ..config import DeviceAddressItem, ItemReading
    from ..protocol.wrapped import Report


class Poller:
    """The poller of one slave.  All state below is touched by the line's worker only,
    except ``status``, ``items`` and ``counters`` which other threads read."""

    def __init__(
        self,
        sink: PollSink,
        code: str,
        params: DriverModbusRtuParameter,
        parsed: Sequence[ParsedItem],
        logger: logging.Logger,
    ) -> None:
        self.sink = sink
        self.code = code
        self.log = logger
        self.slave = params.slave_id
        self.timeout = params.read_timeout / 1000
        self.report_all = params.report_mode == "cycle"
        self.snapshot_interval = params.snapshot_interval / 1000
        self.params = params
        self.counters = DeviceStats()
        self.delivery = Delivery(sink, self.counters, logger, code)
        self.writer = Writer(code, params, logger, self.counters, self.delivery)
        self.status = DeviceDriverStatus.CONNECTING
        self.active = False
        self.line: LineWorker | None = None
        self.items: list[ItemState] = []
        self.slots: list[Slot] = []  # in plan order: slot k is the device's block k
        self._assemblies: dict[ItemState, Assembly] = {}
        # the items' values (store.py), bound at start
        self.store: ItemStore[ItemState] = ItemStore([])
        self.demand_slots: list[Slot] = []  # on-demand items' blocks (poll/on_demand.py)
        self.periodic: PeriodicReports | None = None  # poll/periodic.py
        self.reads = DemandReads(self.counters)  # poll/on_demand.py
        self.device = EngineDevice(self.slave, self.timeout, self.report_all, 0.0,
                                   coalesce=params.forward_coalesce / 1000)
        self.device.set_policy(params.retries, params.offline_after_failed_cycles,
                               params.max_backoff / 1000)
        self.counters.native = self.device.counts  # the engine counts requests and faults
        self._install(parsed)
        self.next_snapshot = 0.0  # the first cycle's end publishes one
        if self.snapshot_interval:
            self.device.notify_at = 0.0

    @property
    def by_name(self) -> dict[str, ItemState]:
        """The items in force by name (made on first use: store.py)."""
        return self.store.by_name()

    def _owner(self, state: ItemState) -> Slot | Assembly | None:
        """What decodes ``state`` in the plan in force (None: a state of an older plan)."""
        return owner_of(state, self.slots, self._assemblies) if self.store.owns(state) else None

    @property
    def plan(self) -> list[ReadBlock]:
        return [slot.block for slot in self.slots]

    @property
    def due(self) -> float:
        """When the next pass begins (``time.monotonic()``; inf: never)."""
        return self.device.due

    @property
    def failed_cycles(self) -> int:
        return self.device.failed_cycles

    @property
    def offline(self) -> bool:
        return self.device.offline

    # -- lifecycle ---------------------------------------------------------------------
    def start(self, line: LineWorker) -> None:
        self.line = line
        self.active = self.device.active = True
        self._all_due_now()
        self.store.bind()  # ItemInUseError: another running driver polls an item
        line.attach(self)

    def _all_due_now(self) -> None:
        """Read every block now (a start, a new plan, a new link), as a new cycle."""
        self.device.all_due(time.monotonic())

    def stop(self) -> None:
        self.active = self.device.active = self.store.active = False
        self.status = DeviceDriverStatus.STOPPED

    def _set_status(self, status: DeviceDriverStatus, reason: str | None) -> None:
        """Set the device's status; a change is told to the listeners.  Worker thread."""
        if status is not self.status:
            self.status = status
            self.delivery.status(status, reason)

    def _install(self, parsed: Sequence[ParsedItem]) -> None:
        self.take_reports()  # into the items they came for
        old_store = self.store
        old = old_store.by_name() if old_store.states else {}
        enabled = [p for p in parsed if p.item.is_enable]
        items = [ItemState(p, i) for i, p in enumerate(enabled)]
        # a new item object of an unchanged definition keeps the state of the old one
        self.carry: dict[int, ItemReading] = {}
        for state in items:
            prev = old.get(state.item.name)
            if prev is not None and prev.item is not state.item and prev.same_definition(state):
                self.carry[state.index] = old_store.reading(prev.index)
        self.items = items
        self.store = ItemStore(items)
        self._reports = ReportDecoders(items)
        blocks = build_plan(enabled, self.params)
        self._assemblies = {}  # filled by _make_slot: one per large item, for all its pieces
        self.slots = [self._make_slot(b) for b in blocks]
        # report-only: nothing polled (readCycle 0 and no item with a rate of its own);
        # cycle: what offline probing backs off from (readCycle, else the fastest rate)
        self.demand_slots = [self._make_slot(b)
                             for b in build_plan(enabled, self.params, demand=True)]
        self.report_only = not blocks and (self.params.read_cycle == 0
                                           or bool(self.demand_slots))
        self.cycle = (self.params.read_cycle or min((b.rate for b in blocks), default=0)) / 1000
        self.device.cycle = self.cycle
        # reportMode/reportEvery per item (poll/periodic.py): the engine reports every
        # item only when all of them report by cycle
        self.report_all = self.writer.report_all = self.device.report_all = reports_all(
            items, self.params)
        # every pass's end: to report every item, or (no block to read) to go Running
        self.device.notify = self.report_all or not self.slots
        self.device.set_blocks([self._spec(slot) for slot in self.slots])
        now = time.monotonic()
        self.periodic = PeriodicReports.build(
            items, [item_rate(p, self.params) for p in enabled], self.params, now)
        if self.periodic is not None:
            self.device.notify_at = min(self.device.notify_at, self.periodic.next_due)

    def _spec(self, slot: Slot) -> BlockSpec:
        """What the engine reads for ``slot``, and the plan it decodes it with."""
        block = slot.block
        plan = slot.decoder.begin(self.report_all)[0] if slot.decoder is not None else None
        spans = self._reports.spans(slot) if self.params.framing == "wrapped-report" else None
        return BlockSpec(READ_FC[block.area], block.start, block.count, block.rate / 1000,
                         plan, bool(slot.partial), len(block.pieces) > 1, spans)

    def _make_slot(self, block: ReadBlock) -> Slot:
        whole: list[ItemState] = []
        specs: list[tuple[int, ValueSpec]] = []
        partial: list[tuple[Piece, Assembly]] = []
        for piece in block.pieces:
            state = self.items[cast(int, piece.key)]
            if piece.item_offset == 0 and piece.size == state.size:
                whole.append(state)
                specs.append((piece.block_offset, state.shape))
            else:
                partial.append((piece, self._assembly(state)))
        decoder = BlockDecoder(block.area, block.count, specs) if specs else None
        slot = Slot(block, whole, decoder, partial)
        return slot

    def _assembly(self, state: ItemState) -> Assembly:
        asm = self._assemblies.get(state)
        if asm is None:
            asm = self._assemblies[state] = Assembly(state)
        return asm

    def replace_items(self, parsed: Sequence[ParsedItem]) -> Future[None]:
        """Swap in a new address list on the worker, between two reads."""
        assert self.line is not None

        def swap(_link: Link | None = None) -> None:
            previous = self.store
            check_free([p.item for p in parsed], (previous,))  # before any change
            self._install(parsed)
            self.store.bind(self.carry, previous)
            previous.active = False
            self._all_due_now()

        if self.line.on_worker():  # from a callback: the worker is between two reads
            swap()
            done: Future[None] = Future()
            done.set_result(None)
            return done
        return self.line.submit(swap)

    def submit_read(self, names: Sequence[str] | None) -> Future[dict[str, dict[str, Any]]]:
        """Read these items (None: all) now, by a job on the line's queue or a waiting one
        (poll/on_demand.py): their snapshot entries by name.  KeyError: an unknown item."""
        line = cast(LineWorker, self.line)  # (set at start; reads come after it)
        missing = [n for n in names or () if n not in self.by_name]
        if missing:
            raise KeyError(f"no item named {missing[0]!r} on device {self.code} "
                           f"({len(self.by_name)} items)")

        def run(link: Link, started: Callable[[], None]) -> dict[str, dict[str, Any]]:
            started()
            if not self.active:
                raise ModbusConnectionError(f"{self.code}: device stopped before the read")
            self.take_results()  # what the pass under way read first
            states = self.items if names is None else [
                self.by_name[n] for n in dict.fromkeys(names) if n in self.by_name]
            wanted = set(states)
            self.reads.token -= 1  # the assemblies' "cycle" of this read: never a pass's
            link.set_response_timeout(self.timeout)
            reported = read_slots(link, self.slave, self.store,
                                  slots_holding(self.slots + self.demand_slots, wanted),
                                  wanted, self.counters, self.reads.token)
            if reported:
                self.delivery.report(reported)
                self.delivery.flush()
            return answer(self.store, states)

        return self.reads.submit(names, lambda started: line.submit(
            lambda link: run(link, started), reads=True, slave=self.slave))

    def submit_snapshot(self) -> Future[None]:
        """Publish the snapshot now, on the worker (Delivery.snapshot_due)."""
        assert self.line is not None
        return self.line.submit(lambda _link: self.delivery.snapshot_due())

    # -- the Poller protocol -----------------------------------------------------------
    def link_changed(self, up: bool, reason: str | None, offline: bool = False) -> None:
        if not self.active:
            return
        self.take_reports()
        self._all_due_now()
        if self.report_only and up:
            self._set_status(DeviceDriverStatus.RUNNING, None)  # ready for reports
            return
        if up:
            return
        status = DeviceDriverStatus.OFFLINE if offline else DeviceDriverStatus.RECONNECTING
        self._set_status(status, reason if offline else f"link down: {reason}")
        self.device.link_lost()
        self.device.forget_failures()  # its items now say "link down"
        for slot in self.slots:
            self._invalidate(slot, f"link down: {reason}")
        self.delivery.flush()

    def on_report(self, report: Report) -> None:
        """An unsolicited wrapped report (edge MCU) the engine did not apply in C: update
        the items of this slave whose registers (or bits) lie inside it, through the same
        codec and callbacks as polled values (poll/reports.py).  Worker thread."""
        if not self.active or report.slave != self.slave:
            return
        self.take_reports()  # the reports the engine applied came before this one
        news = self._reports.news(report, self.store, self.report_all)
        if news is None:
            return
        self.counters.reports += 1
        if news:
            now = datetime.now(timezone.utc)
            reported = [set_state(self.store, s, v, e, now) for s, v, e in news]
            self._recheck([state for state, _, _ in news])
            self._deliver(reported)
            self.delivery.flush()

    def take_reports(self) -> None:
        """Store what the wrapped reports the engine applied in C changed (poll/reports.py
        store_taken), before anything else sets the items: they came first."""
        taken = self.device.take_reports()
        if taken:
            reported: list[DeviceAddressItem] = []
            store_taken(taken, self.slots, self.store, datetime.now(timezone.utc), reported)
            if reported:
                self.device.forget_failures()  # a block failing again says so again
                self._deliver(reported)

    # -- the engine's events ----------------------------------------------------------------
    def take_results(self) -> None:
        """Store what the blocks the engine read in this pass reported, those not taken
        yet (before Python acts on the device: a pass's end, a split, a job), and the
        failures the engine put on blocks (each told once)."""
        self.take_reports()
        device, report_all, slots = self.device, self.report_all, self.slots
        order = device.pass_blocks()
        upto = device.index if device.in_pass else len(order)
        reported: list[DeviceAddressItem] = []
        now = datetime.now(timezone.utc)  # one time stamp for the pass's reports
        for k in order[device.taken:upto]:
            slot = slots[k]
            n = device.reported(k)  # 0 after a failure
            plain = not (report_all or slot.partial or slot.recheck)
            if not n and (plain or device.failed(k)):
                continue  # the usual block: nothing changed (a failed one: below)
            decoder = slot.decoder
            if plain and decoder is not None:  # the usual block that changed
                store_changes(self.store, slot, decoder, n, now, reported)
                continue
            changes = decoder.finish(n, report_all) if decoder else []
            self._apply(slot, device.data(k) if slot.partial else None, changes, now,
                        reported)
        device.taken = upto
        if device.has_failures:
            for failure in device.take_failures():
                self._invalidate(slots[failure.block], reason_of(failure, self.slave))
        self._deliver(reported)  # callbacks: they may re-plan (update_addresses) at once
        events = device.take_status()
        if events:
            for change in status_change(device, events, self.code):
                if change.log:
                    level = logging.WARNING if change.reason else logging.INFO
                    self.log.log(level, "%s", change.log)
                self._set_status(change.status, change.reason)

    def engine_cycle(self) -> None:
        """The engine ended a pass Python must see (news, failures, a status change, or
        one the poller asked for)."""
        self.device.take_end()
        if not self.active:  # stopped while the engine ran: its reports dropped
            self.device.take_reports()
            return
        self.take_results()
        if not self.slots and self.status is not DeviceDriverStatus.RUNNING:
            # nothing to read (on-demand items only): a pass on an open link is Running
            self._set_status(DeviceDriverStatus.RUNNING, None)
            self.device.notify = self.report_all
        self._cycle_done(time.monotonic())

    def engine_split(self) -> None:
        """Exception 02 on the pass's next block, of several pieces: split it in two
        (the halves read next, within this pass; the split kept for later cycles)."""
        if not self.active:
            return
        self.take_results()
        device = self.device
        at = device.pass_blocks()[device.index]
        block = self.slots[at].block
        halves = bisect_block(block)
        new = [self._make_slot(b) for b in halves]
        self.slots[at:at + 1] = new
        device.split(at, [self._spec(s) for s in new])
        self.log.info(
            "%s: exception 02 on %s@%d+%d: split into %s", self.code,
            block.area.short_name, block.start, block.count,
            ", ".join(f"@{b.start}+{b.count}" for b in halves),
        )

    def engine_failed(self, link: Link, err: int) -> None:
        """The link failed (errno ``err``) on a read of the engine's pass: the results
        so far, then the link is closed (the line reports it down and reconnects)."""
        device = self.device
        block = self.slots[device.pass_blocks()[device.index]].block
        try:
            if self.active:
                self.take_results()
        finally:  # the link is closed whatever the results did
            link.read_failed(err, self.slave, block.area, block.start, block.count)

    def _cycle_done(self, now: float) -> None:
        """A pass ended: the items due for a period report join its batch (periodic.py),
        the batch goes out, the snapshot when due."""
        periodic = self.periodic
        if periodic is not None and now >= periodic.next_due:
            self.delivery.report(periodic.due(now))
        self.delivery.flush()
        if self.snapshot_interval and now >= self.next_snapshot:
            self._snapshot(now)
        if periodic is not None:
            snapshot = self.next_snapshot if self.snapshot_interval else float("inf")
            self.device.notify_at = min(snapshot, periodic.next_due)

    def _snapshot(self, now: float) -> None:
        """Publish the snapshot; the engine hands over the first pass that ends after
        the next one is due."""
        self.next_snapshot = self.device.notify_at = now + self.snapshot_interval
        self.delivery.snapshot_due()

    def _apply(self, slot: Slot, data: Block | None, changes: list[Change], now: datetime,
               reported: list[DeviceAddressItem]) -> None:
        """Store what a good read of ``slot`` changed, stamped ``now``: its whole items'
        ``changes`` (from the decoder) and the items assembled from pieces (from
        ``data``); the items set are appended to ``reported``."""
        if slot.recheck:  # rare: after a write or a report, see _recheck
            slot.recheck = False
            if not self.report_all:
                whole = slot.whole
                changes = [c for c in changes if is_news(self.store, whole[c[0]], c[1], c[2])]
        if changes:
            self.store.apply(slot.whole, changes, now, reported)
        if slot.partial and data is not None:
            values = data.to_list()
            cycle = self.device.passes
            for piece, asm in slot.partial:
                if asm.add(piece, values, cycle):
                    block = Block.from_values(asm.registers, bits=False)
                    state = asm.state
                    for _, value, error in asm.decoder.decode(block, self.report_all):
                        if self.report_all or is_news(self.store, state, value, error):
                            reported.append(set_state(self.store, state, value, error, now))

    def _deliver(self, reported: list[DeviceAddressItem]) -> None:
        """Hand the items just set to the callbacks (the batch goes at the cycle's end)."""
        if reported:
            self.counters.values_changed += len(reported)
            self.delivery.report(reported)

    # -- item state ----------------------------------------------------------------------
    def _invalidate(self, slot: Slot, reason: str) -> None:
        """Set the slot's items Invalid with ``reason``.  An item read in pieces fails
        once per cycle: the first of its pieces that fails reports it."""
        now = datetime.now(timezone.utc)
        reported = []
        cycle = self.device.passes
        states = slot.whole + [asm.state for _, asm in slot.partial if asm.fail(cycle)]
        store = self.store
        for state in states:
            changed = is_news(store, state, None, reason)
            set_state(store, state, None, reason, now)
            if changed or self.report_all:
                reported.append(state.item)
        if reported:
            self.delivery.report(reported)
        if slot.decoder is not None:
            slot.decoder.reset()  # the next good read reports every item again

    def _recheck(self, states: list[ItemState]) -> None:
        """These items were just set from outside their poll decoder (a confirmed write,
        a wrapped report), whose change tracking still holds the value it last read.
        Make it report them on the next read, where only news is kept: the written value
        read back is not published a second time, and a value the slave went back to
        (a write it clamped or another master undid) is not missed."""
        self.device.forget_failures()  # a block failing again says so again
        for state in states:
            owner = self._owner(state)
            if owner is None or owner.decoder is None:
                continue
            owner.decoder.reset()
            if isinstance(owner, Slot):
                owner.recheck = True

    # -- writes --------------------------------------------------------------------------
    def submit_writes(self, ops: list[WriteOp],
                      whole: bool = False) -> Future[tuple[bool, str | None]]:
        assert self.line is not None
        future = self.line.submit(lambda link: self._run_writes(link, ops, whole),
                                  slave=self.slave)  # a silent slave: the line backs off

        def count_unsent(done: Future[tuple[bool, str | None]]) -> None:
            # the line failed the job without running it (link down, line stopped): the
            # writes were not sent, and still count as failed writes
            if done.cancelled() or done.exception() is not None:
                self.counters.writes += len(ops)
                self.counters.write_errors += len(ops)

        future.add_done_callback(count_unsent)
        return future

    def _run_writes(self, link: Link, ops: list[WriteOp],
                    whole: bool = False) -> tuple[bool, str | None]:
        if not self.active:
            return False, "device stopped before the write was sent"
        self.take_reports()
        link.set_response_timeout(self.timeout)
        return self.writer.run(link, ops, self._recheck, self.store, whole)

