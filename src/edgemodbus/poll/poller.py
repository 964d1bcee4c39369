"""One polled slave on a line: its read cycle and fault handling.

A :class:`Poller` is attached to its line: the line's worker calls ``poll_step`` when it
is due, and each step reads one planned block, so writes queued by other threads run
between two blocks.  Each block has its own due time (its items' scan rate, see
schedule.py); a cycle is one pass over the blocks due when it begins.  What it reads goes
to its owner through a :class:`PollSink`.  Faults are handled per slave:

* a timeout (after ``retries``) ends this slave's cycle: the cycle's remaining blocks are
  not read and their items go Invalid ("device not responding"); after
  ``offlineAfterFailedCycles`` such cycles the slave is ``Offline`` and is probed with
  one request per backoff interval (doubling from readCycle up to maxBackoff), so a
  dead slave costs the others at most one response timeout (plus settling) per interval;
* an illegal-address exception (02) on a merged block splits the block in two, and
  again, until only the bad addresses fail; the split is kept for later cycles;
* CRC, protocol and other exception responses invalidate that block's items only.
"""

from __future__ import annotations

import bisect
import logging
import math
import time
from collections.abc import Sequence
from concurrent.futures import Future
from datetime import datetime, timezone
from typing import TYPE_CHECKING, cast

from .._ffi import Block
from ..codec import BlockDecoder, Change, ValueSpec
from ..config import DriverModbusRtuParameter, ParsedItem
from ..datatypes import Area, DeviceDriverStatus, ItemStatus
from ..errors import (
    CrcError,
    IllegalDataAddress,
    ModbusConnectionError,
    ModbusError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)
from ..line import LineWorker, Link
from ..stats import CYCLE_BUCKETS, DeviceStats
from .items import Assembly, ItemState, Slot, copy_runtime, is_news, set_item
from .planner import Piece, ReadBlock, bisect_block
from .schedule import build_plan as build_plan  # the CLI's plan command uses it
from .schedule import due_slots, next_due, reschedule
from .sink import Delivery, PollSink
from .writes import WriteOp, Writer

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
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
        self.retries = params.retries
        self.offline_after = params.offline_after_failed_cycles
        self.max_backoff = params.max_backoff / 1000
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
        self.by_name: dict[str, ItemState] = {}
        self.slots: list[Slot] = []
        self._pass: list[Slot] = []  # the slots of the cycle under way, in plan order
        self._assemblies: dict[ItemState, Assembly] = {}
        self._owner: dict[ItemState, Slot | Assembly] = {}  # what decodes each item
        self.cycle_no = 0  # counts the cycles begun, for the pieces of large items
        self._install(parsed)
        self.index = 0
        self.due = 0.0
        self.cycle_start = 0.0
        self.failed_cycles = 0
        self.offline = False
        self.backoff = self.cycle
        self.next_snapshot = 0.0
        # wrapped reports: (function, address, count) -> the items inside and a decoder
        self._report_decoders: dict[tuple[int, int, int],
                                    tuple[list[ItemState], BlockDecoder | None]] = {}

    @property
    def plan(self) -> list[ReadBlock]:
        return [slot.block for slot in self.slots]

    # -- lifecycle ---------------------------------------------------------------------
    def start(self, line: LineWorker) -> None:
        self.line = line
        self.active = True
        self._all_due_now()
        line.attach(self)

    def _all_due_now(self) -> None:
        """Read every block now (a start, a new plan, a new link), as a new cycle."""
        now = time.monotonic()
        self.index = 0
        for slot in self.slots:
            slot.due = now
        self.due = math.inf if self.report_only else now

    def stop(self) -> None:
        self.active = False
        self.status = DeviceDriverStatus.STOPPED

    def _install(self, parsed: Sequence[ParsedItem]) -> None:
        old = self.by_name
        enabled = [p for p in parsed if p.item.is_enable]
        items = [ItemState(p) for p in enabled]
        for state in items:
            prev = old.get(state.item.name)
            if prev is not None and prev.item is not state.item and prev.same_definition(state):
                copy_runtime(prev.item, state.item)
        self.items = items
        self.by_name = {s.item.name: s for s in items}
        self._report_decoders = {}
        blocks = build_plan(enabled, self.params)
        self._assemblies = {}  # filled by _make_slot: one per large item, for all its pieces
        self._owner = {}
        self.slots = [self._make_slot(b) for b in blocks]
        self._pass = []
        # report-only: nothing polled (readCycle 0 and no item with a rate of its own);
        # cycle: what offline probing backs off from (readCycle, else the fastest rate)
        self.report_only = self.params.read_cycle == 0 and not blocks
        self.cycle = (self.params.read_cycle or min((b.rate for b in blocks), default=0)) / 1000

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
        for state in whole:
            self._owner[state] = slot
        for _, asm in partial:
            self._owner[asm.state] = asm
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
            self._install(parsed)
            self._all_due_now()

        if self.line.on_worker():  # from a callback: the worker is between two reads
            swap()
            done: Future[None] = Future()
            done.set_result(None)
            return done
        return self.line.submit(swap)

    # -- the Poller protocol -----------------------------------------------------------
    def link_changed(self, up: bool, reason: str | None) -> None:
        if not self.active:
            return
        self._all_due_now()
        if self.report_only and up:
            self.status = DeviceDriverStatus.RUNNING  # ready for reports
            return
        if up:
            return
        self.status = DeviceDriverStatus.RECONNECTING
        for slot in self.slots:
            self._invalidate(slot, f"link down: {reason}")
        self.delivery.flush()

    def on_report(self, report: Report) -> None:
        """An unsolicited wrapped report (edge MCU): update the items of this slave whose
        registers (or bits) lie inside it, through the same codec and callbacks as
        polled values.  Worker thread."""
        if not self.active or report.slave != self.slave:
            return
        area = _REPORT_AREAS.get(report.function)
        if area is None:
            return  # an exception or a write's echo: nothing to store
        values = report.bits if area.is_bit else report.registers
        key = (report.function, report.address, len(values))
        entry = self._report_decoders.get(key)
        if entry is None:
            start, end = report.address, report.address + len(values)
            states = [s for s in self.items
                      if s.area is area and start <= s.offset and s.offset + s.size <= end]
            decoder = BlockDecoder(area, len(values), [(s.offset - start, s.shape)
                                                       for s in states]) if states else None
            entry = self._report_decoders[key] = (states, decoder)
        states, decoder = entry
        if decoder is None:
            return
        self.counters.reports += 1
        # Every item of the report, kept when it is news against what the item holds (it
        # may have been set by a poll since the last report): the decoder's own change
        # tracking only knows the reports.
        decoded = decoder.decode(Block.from_values(values, bits=area.is_bit), True)
        report_all = self.report_all
        news = [(states[i], value, error) for i, value, error in decoded
                if report_all or is_news(states[i], value, error)]
        if news:
            now = datetime.now(timezone.utc)
            reported = [set_item(state.item, value, error, now) for state, value, error in news]
            self._recheck([state for state, _, _ in news])
            self.counters.values_changed += len(reported)
            self.delivery.report(reported)
            self.delivery.flush()

    def poll_step(self, link: Link) -> None:
        """Read the next block of this cycle (a cycle begins with the blocks due then).
        The straight path (a good answer) is kept short: it runs once per block for
        every device of a gateway."""
        if not self.active:
            return
        index = self.index
        if index == 0:
            now = self.cycle_start = time.monotonic()
            if not self.slots:  # nothing to read: an empty cycle per readCycle
                self.cycle_no += 1
                self._end_cycle(failed=False)
                return
            self._pass = due_slots(self.slots, now)
            if not self._pass:  # woken early: nothing due yet
                self.due = next_due(self.slots)
                return
            self.cycle_no += 1
        slot = self._pass[index]
        link.set_response_timeout(self.timeout)
        self.counters.requests += 1
        try:
            data, changes = self._read_slot(link, slot)
        except ModbusError as exc:
            self._read_failed(link, slot, exc)
            return
        self._good_read(slot, data, changes)

    def _read_slot(self, link: Link, slot: Slot) -> tuple[Block, list[Change]]:
        """Read a block and decode its whole items (one C call on the libmodbus path)."""
        block = slot.block
        if slot.decoder is None:
            return link.read(self.slave, block.area, block.start, block.count), []
        return link.read_decode(self.slave, block.area, block.start, block.count,
                                slot.decoder, self.report_all)

    def _good_read(self, slot: Slot, data: Block, changes: list[Change]) -> None:
        self.counters.responses += 1
        self._apply(slot, data, changes)
        if self.status is not DeviceDriverStatus.RUNNING:
            self._back_online()
        self.index += 1
        if self.index >= len(self._pass):
            self._end_cycle(failed=False)

    def _read_failed(self, link: Link, slot: Slot, error: ModbusError) -> None:
        """The slow path: retries (timeouts and CRC errors only), then fault handling."""
        block = slot.block
        counters = self.counters
        retries = 0 if self.offline else self.retries
        while True:
            if isinstance(error, CrcError):
                counters.crc_errors += 1
            elif isinstance(error, ModbusTimeoutError):
                counters.timeouts += 1
            elif isinstance(error, ModbusExceptionResponse):
                counters.exceptions[error.code] = counters.exceptions.get(error.code, 0) + 1
            elif isinstance(error, ProtocolError):
                counters.protocol_errors += 1
            retryable = isinstance(error, (ModbusTimeoutError, CrcError))
            if not (retryable and retries > 0 and link.is_open):
                break
            retries -= 1
            counters.retries += 1
            counters.requests += 1
            try:
                data, changes = self._read_slot(link, slot)
            except ModbusError as exc:
                error = exc
                continue
            self._good_read(slot, data, changes)
            return
        slots = self._pass
        if isinstance(error, ModbusConnectionError):
            self.index = 0  # the line reports the link as down and reconnects
        elif isinstance(error, ModbusTimeoutError):
            reason = f"device not responding: {error}"
            counters.skipped_blocks += len(slots) - self.index - 1
            for rest in slots[self.index:]:
                self._invalidate(rest, reason)
            if self.offline or self.failed_cycles + 1 >= self.offline_after:
                # offline: the blocks not due in this cycle hold no fresh value either
                for other in [s for s in self.slots if s not in slots]:  # by identity
                    self._invalidate(other, reason)
            self._end_cycle(failed=True)
        elif isinstance(error, IllegalDataAddress) and len(block.pieces) > 1:
            halves = bisect_block(block)
            new = [self._make_slot(b) for b in halves]
            slots[self.index:self.index + 1] = new
            at = next(i for i, s in enumerate(self.slots) if s is slot)
            self.slots[at:at + 1] = new
            self.log.info(
                "%s: exception 02 on %s@%d+%d: split into %s", self.code,
                block.area.short_name, block.start, block.count,
                ", ".join(f"@{b.start}+{b.count}" for b in halves),
            )  # the halves are read next, within this cycle
        else:
            if self.status is not DeviceDriverStatus.RUNNING and not isinstance(
                error, ProtocolError
            ):
                self._back_online()  # an exception response: the slave is there
            self._invalidate(slot, str(error))
            self.index += 1
            if self.index >= len(slots):
                self._end_cycle(failed=False)

    def _apply(self, slot: Slot, data: Block, changes: list[Change]) -> None:
        """Store what a good read of ``slot`` changed: its whole items' ``changes`` (from
        the decoder) and the items assembled from pieces."""
        reported: list[DeviceAddressItem] = []
        now: datetime | None = None
        if slot.recheck:  # rare: after a write or a report, see _recheck
            slot.recheck = False
            if not self.report_all:
                whole = slot.whole
                changes = [c for c in changes if is_news(whole[c[0]], c[1], c[2])]
        if changes:
            now = datetime.now(timezone.utc)
            items = slot.items
            for index, value, error in changes:  # set_item, inlined: the hot loop
                item = items[index]
                if error is None:
                    item.value = value
                    if item.status is not _OK:
                        item.status = _OK
                    if item.error_reason is not None:
                        item.error_reason = None
                else:
                    item.status = _INVALID
                    item.error_reason = error
                item.update_ts = now
                reported.append(item)
        if slot.partial:
            values = data.to_list()
            for piece, asm in slot.partial:
                if asm.add(piece, values, self.cycle_no):
                    block = Block.from_values(asm.registers, bits=False)
                    state = asm.state
                    for _, value, error in asm.decoder.decode(block, self.report_all):
                        if self.report_all or is_news(state, value, error):
                            now = now or datetime.now(timezone.utc)
                            reported.append(set_item(state.item, value, error, now))
        if reported:
            self.counters.values_changed += len(reported)
            self.delivery.report(reported)

    # -- item state ----------------------------------------------------------------------
    def _invalidate(self, slot: Slot, reason: str) -> None:
        """Set the slot's items Invalid with ``reason``.  An item read in pieces fails
        once per cycle: the first of its pieces that fails reports it."""
        now = datetime.now(timezone.utc)
        reported = []
        states = slot.whole + [asm.state for _, asm in slot.partial
                               if asm.fail(self.cycle_no)]
        for state in states:
            item = state.item
            changed = item.status is not ItemStatus.INVALID or item.error_reason != reason
            set_item(item, None, reason, now)
            if changed or self.report_all:
                reported.append(item)
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
        for state in states:
            owner = self._owner.get(state)
            if owner is None or owner.decoder is None:
                continue
            owner.decoder.reset()
            if isinstance(owner, Slot):
                owner.recheck = True

    # -- cycles and fault isolation --------------------------------------------------------
    def _back_online(self) -> None:
        if self.offline:
            self.log.info("%s: slave %d answers again", self.code, self.slave)
        self.status = DeviceDriverStatus.RUNNING
        self.offline = False
        self.failed_cycles = 0
        self.backoff = self.cycle

    def _end_cycle(self, failed: bool) -> None:
        now = time.monotonic()
        elapsed = now - self.cycle_start
        counters = self.counters
        counters.cycles += 1
        counters.last_cycle_time = elapsed
        counters.total_cycle_time += elapsed
        counters.max_cycle_time = max(counters.max_cycle_time, elapsed)
        counters.cycle_hist[bisect.bisect_left(CYCLE_BUCKETS, elapsed)] += 1
        self.index = 0
        if failed:
            counters.failed_cycles += 1
            self.failed_cycles += 1
        else:
            self.failed_cycles = 0
        if failed and self.failed_cycles >= self.offline_after:
            if self.offline:
                self.backoff = min(self.backoff * 2, self.max_backoff)
            else:
                self.offline = True
                self.status = DeviceDriverStatus.OFFLINE
                self.backoff = min(self.cycle, self.max_backoff)
                self.log.warning("%s: slave %d offline after %d failed cycles; probing every "
                                 "%.3g s and backing off", self.code, self.slave,
                                 self.failed_cycles, self.backoff)
            self.due = now + self.backoff
            for slot in self.slots:  # the probe is a cycle over every block
                slot.due = self.due
        elif not self.slots:
            if elapsed > self.cycle:
                counters.overruns += 1
                self.due = now  # no burst of catch-up cycles
            else:
                self.due = self.cycle_start + self.cycle
        else:
            if reschedule(self._pass, self.cycle_start, now):
                counters.overruns += 1
            self.due = next_due(self.slots)
        self.delivery.flush()
        if self.snapshot_interval and now >= self.next_snapshot:
            self.next_snapshot = now + self.snapshot_interval
            self.sink.snapshot_due()

    # -- writes --------------------------------------------------------------------------
    def submit_writes(self, ops: list[WriteOp]) -> Future[tuple[bool, str | None]]:
        assert self.line is not None
        future = self.line.submit(lambda link: self._run_writes(link, ops))

        def count_unsent(done: Future[tuple[bool, str | None]]) -> None:
            # the line failed the job without running it (link down, line stopped): the
            # writes were not sent, and still count as failed writes
            if done.cancelled() or done.exception() is not None:
                self.counters.writes += len(ops)
                self.counters.write_errors += len(ops)

        future.add_done_callback(count_unsent)
        return future

    def _run_writes(self, link: Link, ops: list[WriteOp]) -> tuple[bool, str | None]:
        if not self.active:
            return False, "device stopped before the write was sent"
        link.set_response_timeout(self.timeout)
        return self.writer.run(link, ops, self._recheck)


_REPORT_AREAS = {area.read_function: area for area in Area}  # FC01-04 of a report

_OK = ItemStatus.OK
_INVALID = ItemStatus.INVALID
