"""One polled slave on a line: its read plan, item state, fault handling and writes.

A :class:`Poller` is a bus poller: the line's worker thread calls ``poll_step`` when it
is due, and each step reads one planned block, so writes queued by other threads run
between two blocks.  Faults are handled per slave:

* a timeout (after ``retries``) ends this slave's cycle: its remaining blocks are not
  read and their items go Invalid ("device not responding"); after
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
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any, cast

from .._ffi import Block
from ..codec import BlockDecoder, Change, ValueSpec, encode, normalize_value, register_bit
from ..codec import jsonable as _jsonable
from ..config import DriverModbusRtuParameter, ParsedItem
from ..datatypes import Area, DeviceDriverStatus, ItemStatus
from ..errors import (
    CrcError,
    IllegalDataAddress,
    IllegalFunction,
    ModbusConnectionError,
    ModbusError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)
from ..line import LineWorker as Bus  # the poller's line; renamed when device.py moves
from ..line import Link
from .planner import Piece, PlanItem, ReadBlock, bisect_block, plan_reads

if TYPE_CHECKING:
    from ..config import DeviceAddressItem
    from ..driver import DriverModbusRtu
    from ..protocol.wrapped import Report

_MAX_WRITE_REGISTERS = 123  # FC16 (Modbus Application Protocol v1.1b3, 6.12)
_MAX_WRITE_COILS = 1968  # FC15 (6.11)


# upper bounds (seconds) of the cycle-time histogram behind the Prometheus exporter
CYCLE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


def _histogram(bounds: tuple[float, ...], counts: list[int], total: float) -> dict[str, Any]:
    """Cumulative buckets, Prometheus style: [[le, count <= le], ..., ["+Inf", all]]."""
    buckets: list[list[Any]] = []
    running = 0
    for le, n in zip((*bounds, "+Inf"), counts, strict=True):
        running += n
        buckets.append([le, running])
    return {"buckets": buckets, "sum": total, "count": running}


@dataclass
class Counters:
    """Per-device counters behind ``DriverModbusRtu.stats()``."""

    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)
    retries: int = 0
    cycles: int = 0
    failed_cycles: int = 0
    overruns: int = 0
    skipped_blocks: int = 0
    last_cycle_time: float = 0.0
    total_cycle_time: float = 0.0
    max_cycle_time: float = 0.0
    cycle_hist: list[int] = field(default_factory=lambda: [0] * (len(CYCLE_BUCKETS) + 1))
    callback_errors: int = 0
    callback_time: float = 0.0
    values_changed: int = 0
    writes: int = 0
    write_errors: int = 0
    reports: int = 0  # wrapped reports applied to this device

    def as_dict(self) -> dict[str, Any]:
        return {
            "requests": self.requests,
            "responses": self.responses,
            "timeouts": self.timeouts,
            "crcErrors": self.crc_errors,
            "protocolErrors": self.protocol_errors,
            "exceptions": dict(self.exceptions),
            "retries": self.retries,
            "cycles": self.cycles,
            "failedCycles": self.failed_cycles,
            "overruns": self.overruns,
            "skippedBlocks": self.skipped_blocks,
            "lastCycleTime": self.last_cycle_time,
            "avgCycleTime": self.total_cycle_time / self.cycles if self.cycles else 0.0,
            "maxCycleTime": self.max_cycle_time,
            "cycleTimeHistogram": _histogram(CYCLE_BUCKETS, self.cycle_hist,
                                             self.total_cycle_time),
            "callbackErrors": self.callback_errors,
            "callbackTime": self.callback_time,
            "valuesChanged": self.values_changed,
            "writes": self.writes,
            "writeErrors": self.write_errors,
            "reports": self.reports,
        }


class ItemState:
    """A configured item with what the driver needs to read, decode and write it."""

    __slots__ = ("area", "bit", "item", "offset", "size", "spec")

    def __init__(self, parsed: ParsedItem) -> None:
        # the ParsedItem itself is not kept: a gateway holds tens of thousands of these
        self.item: DeviceAddressItem = parsed.item
        self.area: Area = parsed.address.area
        self.offset: int = parsed.address.offset
        self.bit: int | None = parsed.address.bit
        self.size: int = 1 if self.area.is_bit else parsed.registers
        self.spec = ValueSpec(
            name=parsed.item.name,
            data_type=parsed.data_type,
            data_format=parsed.data_format,
            quantity=parsed.quantity,
            bit=parsed.address.bit,
            multiplier=parsed.multiplier,
            converted_type=parsed.converted_type,
            deadband=parsed.deadband or 0.0,
            encoding=parsed.encoding,
        )

    def same_definition(self, other: ItemState) -> bool:
        return (self.item.name, self.area, self.offset, self.spec) == (
            other.item.name, other.area, other.offset, other.spec
        )

    def snapshot(self) -> dict[str, Any]:
        item = self.item
        return {
            "address": item.address,
            "value": _jsonable(item.value),
            "status": _status_text(item.status),
            "updateTs": item.update_ts.isoformat() if item.update_ts else None,
            "errorReason": item.error_reason,
        }


class _Assembly:
    """Registers of an item larger than one block, gathered over several blocks.  One
    per item, shared by the slots of all its pieces; the item is decoded only when every
    piece arrived in the same cycle (``pieces``: item offset -> size, of ``cycle``)."""

    __slots__ = ("cycle", "decoder", "failed", "pieces", "registers", "state")

    def __init__(self, state: ItemState) -> None:
        self.state = state
        self.registers = [0] * state.size
        self.cycle = -1
        self.failed = -1  # the last cycle in which a piece failed
        self.pieces: dict[int, int] = {}
        self.decoder = BlockDecoder(state.area, state.size, [(0, state.spec)])

    def add(self, piece: Piece, values: list[int], cycle: int) -> bool:
        """Store a piece read in ``cycle``; True once all pieces of that cycle are in."""
        if cycle != self.cycle:
            self.cycle = cycle
            self.pieces.clear()
        start = piece.block_offset
        self.registers[piece.item_offset:piece.item_offset + piece.size] = values[
            start:start + piece.size
        ]
        self.pieces[piece.item_offset] = piece.size
        return sum(self.pieces.values()) == len(self.registers)  # pieces never overlap

    def fail(self, cycle: int) -> bool:
        """A piece failed in ``cycle``: what arrived in it cannot complete the item.
        False if another piece already failed in that cycle (the item is Invalid)."""
        first = self.failed != cycle
        self.failed = self.cycle = cycle
        self.pieces.clear()
        self.decoder.reset()  # the next complete read reports the item again
        return first


@dataclass
class _Slot:
    """One planned read and how to decode it."""

    block: ReadBlock
    whole: list[ItemState]
    decoder: BlockDecoder | None
    partial: list[tuple[Piece, _Assembly]]
    items: list[DeviceAddressItem] = field(init=False)  # whole[i].item, for the hot loop
    # the decoder was reset because an item was set from outside it (a write, a report):
    # its next reports are filtered by what the items hold (_news)
    recheck: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        self.items = [state.item for state in self.whole]


@dataclass
class WriteOp:
    """One write request: consecutive coils or registers of one area, or one bit."""

    area: Area
    address: int
    registers: list[int] = field(default_factory=list)
    bits: list[bool] = field(default_factory=list)
    bit: int | None = None
    updates: list[tuple[ItemState, Any]] = field(default_factory=list)

    @property
    def names(self) -> str:
        return ", ".join(st.item.name for st, _ in self.updates)


class Poller:
    """The poller of one slave.  All state below is touched by the bus worker only,
    except ``status``, ``items`` and ``counters`` which other threads read."""

    def __init__(
        self,
        driver: DriverModbusRtu,
        code: str,
        params: DriverModbusRtuParameter,
        parsed: Sequence[ParsedItem],
        logger: logging.Logger,
    ) -> None:
        self.driver = driver
        self.code = code
        self.log = logger
        self.slave = params.slave_id
        self.cycle = params.read_cycle / 1000
        self.report_only = params.read_cycle == 0  # wrapped reports only, never polled
        self.timeout = params.read_timeout / 1000
        self.retries = params.retries
        self.offline_after = params.offline_after_failed_cycles
        self.max_backoff = params.max_backoff / 1000
        self.report_all = params.report_mode == "cycle"
        self.write_single_fc = params.write_single_register_function
        self.snapshot_interval = params.snapshot_interval / 1000
        self.params = params
        self.counters = Counters()
        self.status = DeviceDriverStatus.CONNECTING
        self.active = False
        self.bus: Bus | None = None
        self.items: list[ItemState] = []
        self.by_name: dict[str, ItemState] = {}
        self.slots: list[_Slot] = []
        self._assemblies: dict[ItemState, _Assembly] = {}
        self._owner: dict[ItemState, _Slot | _Assembly] = {}  # what decodes each item
        self.cycle_no = 0  # counts the cycles begun, for the pieces of large items
        self._install(parsed)
        self.index = 0
        self.due = 0.0
        self.cycle_start = 0.0
        self.failed_cycles = 0
        self.offline = False
        self.backoff = self.cycle
        self.no_fc16 = False
        self.no_fc22 = False
        self.batch: list[DeviceAddressItem] = []
        self.next_snapshot = 0.0
        # wrapped reports: (function, address, count) -> the items inside and a decoder
        self._report_decoders: dict[tuple[int, int, int],
                                    tuple[list[ItemState], BlockDecoder | None]] = {}

    @property
    def plan(self) -> list[ReadBlock]:
        return [slot.block for slot in self.slots]

    # -- lifecycle ---------------------------------------------------------------------
    def start(self, bus: Bus) -> None:
        self.bus = bus
        self.active = True
        self.due = math.inf if self.report_only else time.monotonic()
        bus.attach(self)

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
                _copy_runtime(prev.item, state.item)
        self.items = items
        self.by_name = {s.item.name: s for s in items}
        self._report_decoders = {}
        blocks = build_plan(enabled, self.params)
        self._assemblies = {}  # filled by _make_slot: one per large item, for all its pieces
        self._owner = {}
        self.slots = [self._make_slot(b) for b in blocks]

    def _make_slot(self, block: ReadBlock) -> _Slot:
        whole: list[ItemState] = []
        specs: list[tuple[int, ValueSpec]] = []
        partial: list[tuple[Piece, _Assembly]] = []
        for piece in block.pieces:
            state = self.items[cast(int, piece.key)]
            if piece.item_offset == 0 and piece.size == state.size:
                whole.append(state)
                specs.append((piece.block_offset, state.spec))
            else:
                partial.append((piece, self._assembly(state)))
        decoder = BlockDecoder(block.area, block.count, specs) if specs else None
        slot = _Slot(block, whole, decoder, partial)
        for state in whole:
            self._owner[state] = slot
        for _, asm in partial:
            self._owner[asm.state] = asm
        return slot

    def _assembly(self, state: ItemState) -> _Assembly:
        asm = self._assemblies.get(state)
        if asm is None:
            asm = self._assemblies[state] = _Assembly(state)
        return asm

    def replace_items(self, parsed: Sequence[ParsedItem]) -> Future[None]:
        """Swap in a new address list on the worker, between two reads."""
        assert self.bus is not None

        def swap(_link: Link | None = None) -> None:
            self._install(parsed)
            self.index = 0
            self.due = math.inf if self.report_only else time.monotonic()

        if self.bus.on_worker():  # from a callback: the worker is between two reads
            swap()
            done: Future[None] = Future()
            done.set_result(None)
            return done
        return self.bus.submit(swap)

    # -- the Poller protocol -----------------------------------------------------------
    def link_changed(self, up: bool, reason: str | None) -> None:
        if not self.active:
            return
        self.index = 0
        if self.report_only:
            self.due = math.inf
            if up:
                self.status = DeviceDriverStatus.RUNNING  # ready for reports
                return
        else:
            self.due = time.monotonic()
        if up:
            return
        self.status = DeviceDriverStatus.RECONNECTING
        for slot in self.slots:
            self._invalidate(slot, f"link down: {reason}")
        self._flush_batch()

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
            decoder = BlockDecoder(area, len(values), [(s.offset - start, s.spec)
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
                if report_all or _news(states[i], value, error)]
        if news:
            now = datetime.now(timezone.utc)
            reported = [_set_item(state.item, value, error, now) for state, value, error in news]
            self._recheck([state for state, _, _ in news])
            self.counters.values_changed += len(reported)
            self._report(reported)
            self._flush_batch()

    def poll_step(self, link: Link) -> None:
        """Read the next block of this cycle.  The straight path (a good answer) is kept
        short: it runs once per block for every device of a gateway."""
        if not self.active:
            return
        index = self.index
        if index == 0:
            self.cycle_start = time.monotonic()
            self.cycle_no += 1
        slots = self.slots
        if not slots:
            self._end_cycle(failed=False)
            return
        slot = slots[index]
        link.set_response_timeout(self.timeout)
        self.counters.requests += 1
        try:
            data, changes = self._read_slot(link, slot)
        except ModbusError as exc:
            self._read_failed(link, slot, exc)
            return
        self._good_read(slot, data, changes)

    def _read_slot(self, link: Link, slot: _Slot) -> tuple[Block, list[Change]]:
        """Read a block and decode its whole items (one C call on the libmodbus path)."""
        block = slot.block
        if slot.decoder is None:
            return link.read(self.slave, block.area, block.start, block.count), []
        return link.read_decode(self.slave, block.area, block.start, block.count,
                                slot.decoder, self.report_all)

    def _good_read(self, slot: _Slot, data: Block, changes: list[Change]) -> None:
        self.counters.responses += 1
        self._apply(slot, data, changes)
        if self.status is not DeviceDriverStatus.RUNNING:
            self._back_online()
        self.index += 1
        if self.index >= len(self.slots):
            self._end_cycle(failed=False)

    def _read_failed(self, link: Link, slot: _Slot, error: ModbusError) -> None:
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
        slots = self.slots
        if isinstance(error, ModbusConnectionError):
            self.index = 0  # the bus reports the link as down and reconnects
        elif isinstance(error, ModbusTimeoutError):
            reason = f"device not responding: {error}"
            counters.skipped_blocks += len(slots) - self.index - 1
            for rest in slots[self.index:]:
                self._invalidate(rest, reason)
            self._end_cycle(failed=True)
        elif isinstance(error, IllegalDataAddress) and len(block.pieces) > 1:
            halves = bisect_block(block)
            slots[self.index:self.index + 1] = [self._make_slot(b) for b in halves]
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

    def _apply(self, slot: _Slot, data: Block, changes: list[Change]) -> None:
        """Store what a good read of ``slot`` changed: its whole items' ``changes`` (from
        the decoder) and the items assembled from pieces."""
        reported: list[DeviceAddressItem] = []
        now: datetime | None = None
        if slot.recheck:  # rare: after a write or a report, see _recheck
            slot.recheck = False
            if not self.report_all:
                whole = slot.whole
                changes = [c for c in changes if _news(whole[c[0]], c[1], c[2])]
        if changes:
            now = datetime.now(timezone.utc)
            items = slot.items
            for index, value, error in changes:  # _set_item, inlined: the hot loop
                item = items[index]
                fields = item.__dict__
                if error is None:
                    fields["value"] = value
                    if fields["status"] is not _OK:
                        fields["status"] = _OK
                    if fields["error_reason"] is not None:
                        fields["error_reason"] = None
                else:
                    fields["status"] = _INVALID
                    fields["error_reason"] = error
                fields["update_ts"] = now
                reported.append(item)
        if slot.partial:
            values = data.to_list()
            for piece, asm in slot.partial:
                if asm.add(piece, values, self.cycle_no):
                    block = Block.from_values(asm.registers, bits=False)
                    state = asm.state
                    for _, value, error in asm.decoder.decode(block, self.report_all):
                        if self.report_all or _news(state, value, error):
                            now = now or datetime.now(timezone.utc)
                            reported.append(_set_item(state.item, value, error, now))
        if reported:
            self.counters.values_changed += len(reported)
            self._report(reported)

    # -- item state ----------------------------------------------------------------------
    def _invalidate(self, slot: _Slot, reason: str) -> None:
        """Set the slot's items Invalid with ``reason``.  An item read in pieces fails
        once per cycle: the first of its pieces that fails reports it."""
        now = datetime.now(timezone.utc)
        reported = []
        states = slot.whole + [asm.state for _, asm in slot.partial
                               if asm.fail(self.cycle_no)]
        for state in states:
            item = state.item
            changed = item.status is not ItemStatus.INVALID or item.error_reason != reason
            _set_item(item, None, reason, now)
            if changed or self.report_all:
                reported.append(item)
        if reported:
            self._report(reported)
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
            if isinstance(owner, _Slot):
                owner.recheck = True

    def _report(self, items: list[DeviceAddressItem]) -> None:
        """Add items to this cycle's batch and call the per-item callback for each."""
        self.batch += items
        self._notify(items)

    def _notify(self, items: list[DeviceAddressItem]) -> None:
        """Call the per-item callback for each item."""
        callback = self.driver.address_updated_callback
        if callback is None:
            return
        started = time.perf_counter()
        for item in items:
            try:
                callback(item)
            except Exception:
                self.counters.callback_errors += 1
                self.log.exception("%s: address_updated_callback failed for item %r",
                                   self.code, item.name)
        self.counters.callback_time += time.perf_counter() - started

    def _flush_batch(self) -> None:
        batch, self.batch = self.batch, []
        callback = self.driver.addresses_updated_callback
        if not batch or callback is None:
            return
        started = time.perf_counter()
        try:
            callback(batch)
        except Exception:
            self.counters.callback_errors += 1
            self.log.exception("%s: addresses_updated_callback failed (%d items)",
                               self.code, len(batch))
        self.counters.callback_time += time.perf_counter() - started

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
        elif elapsed > self.cycle:
            counters.overruns += 1
            self.due = now  # no burst of catch-up cycles
        else:
            self.due = self.cycle_start + self.cycle
        self._flush_batch()
        if self.snapshot_interval and now >= self.next_snapshot:
            self.next_snapshot = now + self.snapshot_interval
            self.driver._publish(self)

    # -- writes --------------------------------------------------------------------------
    def submit_writes(self, ops: list[WriteOp]) -> Future[tuple[bool, str | None]]:
        assert self.bus is not None
        future = self.bus.submit(lambda link: self._run_writes(link, ops))

        def count_unsent(done: Future[tuple[bool, str | None]]) -> None:
            # the bus failed the job without running it (link down, bus stopped): the
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
        errors: list[str] = []
        now = datetime.now(timezone.utc)
        written: list[DeviceAddressItem] = []
        for i, op in enumerate(ops):
            self.counters.writes += 1
            try:
                self._execute(link, op)
            except ModbusError as exc:
                self.counters.write_errors += 1
                errors.append(f"{op.names}: {exc}")
                if isinstance(exc, ModbusConnectionError):
                    errors.extend(f"{o.names}: not sent (link down)" for o in ops[i + 1:])
                    break
                continue
            self._recheck([state for state, _ in op.updates])
            confirmed = [
                _set_item(state.item, value, None, now)
                for state, value in op.updates
                if self.report_all or not _holds(state.item, value, None)
            ]
            if confirmed:
                self.counters.values_changed += len(confirmed)
                self._notify(confirmed)
                written += confirmed
        if written:
            # One write, one update: the item callbacks above, and one batch now (the
            # next read of the written value is no news, see _recheck); an item already
            # in this cycle's batch goes out once, with its written value.
            queued = {id(item) for item in self.batch}
            self.batch += [item for item in written if id(item) not in queued]
            self._flush_batch()
        return (False, "; ".join(errors)) if errors else (True, None)

    def _execute(self, link: Link, op: WriteOp) -> None:
        slave = self.slave
        if op.area is Area.COIL:
            if len(op.bits) == 1:
                link.write_coil(slave, op.address, op.bits[0])
            else:
                link.write_coils(slave, op.address, op.bits)
            return
        if op.bit is not None:
            self._write_bit(link, op.address, op.bit, op.bits[0])
            return
        regs = op.registers
        if len(regs) == 1 and self.write_single_fc == 6:
            link.write_register(slave, op.address, regs[0])
            return
        if not self.no_fc16:
            try:
                link.write_registers(slave, op.address, regs)
                return
            except IllegalFunction:
                self.no_fc16 = True
                self.log.warning("%s: slave %d refuses FC16; writing with FC06 from now on",
                                 self.code, slave)
        for offset, value in enumerate(regs):
            link.write_register(slave, op.address + offset, value)

    def _write_bit(self, link: Link, address: int, bit: int, on: bool) -> None:
        """Set one bit of a holding register: FC22 mask write (6.16), else read-modify-
        write with FC03 + FC06 (not atomic against other masters; logged once)."""
        slave = self.slave
        if not self.no_fc22:
            try:
                link.mask_write_register(slave, address, 0xFFFF ^ (1 << bit), int(on) << bit)
                return
            except IllegalFunction:
                self.no_fc22 = True
                self.log.warning("%s: slave %d refuses FC22; bit writes use read-modify-write",
                                 self.code, slave)
        current = link.read(slave, Area.HOLDING_REGISTER, address, 1).to_list()[0]
        value = (current | (1 << bit)) if on else (current & ~(1 << bit) & 0xFFFF)
        link.write_register(slave, address, value)


def build_plan(items: Sequence[ParsedItem], params: DriverModbusRtuParameter) -> list[ReadBlock]:
    """The read blocks of a device's enabled items; piece keys index ``items``."""
    plan_items = [
        PlanItem(i, p.address.area, p.address.offset, 1 if p.address.area.is_bit else p.registers)
        for i, p in enumerate(items)
        if p.item.is_enable
    ]
    return plan_reads(
        plan_items,
        max_registers=params.max_block_read_register_count,
        max_bits=params.max_block_read_bit_count,
        max_gap=params.max_merge_address_gap,
        continuous=params.is_block_read_require_address_continuous,
    )


def plan_writes(device: Poller, items: list[tuple[str, Any]]) -> list[WriteOp]:
    """Normalize, encode and group a batch of writes (raises ValueError naming the item).

    Contiguous registers (or coils) of one area are merged into one request, up to the
    protocol's limits; bit-in-register items are written one by one.
    """
    if not items:
        raise ValueError("nothing to write")
    seen: set[str] = set()
    single: list[WriteOp] = []
    for name, raw in items:
        state = device.by_name.get(name)
        if state is None:
            raise ValueError(f"unknown item {name!r}")
        if name in seen:
            raise ValueError(f"{name}: written twice in one batch")
        seen.add(name)
        if not state.area.writable:
            raise ValueError(
                f"{name}: {state.item.address} is a read-only "
                f"{'discrete input' if state.area.is_bit else 'input register'}; "
                "only coils and holding registers can be written"
            )
        spec = state.spec
        value = normalize_value(name, spec.converted_type or spec.data_type, raw)
        if state.area is Area.COIL or state.bit is not None:
            on = bool(encode(spec, value)[0])
            raw_bit = None if state.bit is None else register_bit(spec)
            single.append(WriteOp(state.area, state.offset, bits=[on], bit=raw_bit,
                                  updates=[(state, on)]))
            continue
        registers = encode(spec, value)
        decoded = BlockDecoder(state.area, len(registers), [(0, spec)]).decode_values(
            Block.from_values(registers, bits=False)
        )[0]
        single.append(WriteOp(state.area, state.offset, registers=registers,
                              updates=[(state, decoded)]))
    return _merge(single)


def _merge(ops: list[WriteOp]) -> list[WriteOp]:
    ops.sort(key=lambda o: (o.area.value, o.address))
    merged: list[WriteOp] = []
    for op in ops:
        last = merged[-1] if merged else None
        if last is not None and last.area is op.area and last.bit is None and op.bit is None:
            if op.area is Area.COIL and last.address + len(last.bits) == op.address and len(
                last.bits
            ) < _MAX_WRITE_COILS:
                last.bits.extend(op.bits)
                last.updates.extend(op.updates)
                continue
            if op.area is Area.HOLDING_REGISTER and (
                last.address + len(last.registers) == op.address
                and len(last.registers) + len(op.registers) <= _MAX_WRITE_REGISTERS
            ):
                last.registers.extend(op.registers)
                last.updates.extend(op.updates)
                continue
        merged.append(op)
    return merged


_REPORT_AREAS = {area.read_function: area for area in Area}  # FC01-04 of a report

_OK = ItemStatus.OK
_INVALID = ItemStatus.INVALID
_RUNTIME_FIELDS = ("value", "status", "update_ts", "error_reason")


def _set_item(
    item: DeviceAddressItem, value: Any, error: str | None, now: datetime
) -> DeviceAddressItem:
    """Store a read result: the value and Ok, or Invalid with the reason (the last good
    value stays).  Writes the item's ``__dict__`` directly: these runtime fields are not
    validated on assignment, and pydantic's ``__setattr__`` (with its fields-set
    bookkeeping) costs several times more on the hot path and memory per item."""
    fields = item.__dict__
    if error is None:
        fields["value"] = value
        if fields["status"] is not _OK:
            fields["status"] = _OK
        if fields["error_reason"] is not None:
            fields["error_reason"] = None
    else:
        fields["status"] = _INVALID
        fields["error_reason"] = error
    fields["update_ts"] = now
    return item


def _same(held: Any, value: Any) -> bool:
    """Whether an item's value is exactly ``value`` (same type; NaN matches NaN)."""
    return type(held) is type(value) and (held == value or (held != held and value != value))


def _holds(item: DeviceAddressItem, value: Any, error: str | None) -> bool:
    """Whether ``item`` is already Ok with ``value``: a change the decoder sees against
    its own last report (e.g. after a confirmed write) that is no news to the host."""
    return error is None and item.status is _OK and _same(item.value, value)


def _news(state: ItemState, value: Any, error: str | None) -> bool:
    """Whether a decoded result differs from what the item holds, as the change mode
    reports it: another error reason, or a value not exactly the held one and, for
    numbers with a deadband, more than the deadband away from it."""
    item = state.item
    if error is not None:
        return item.status is not _INVALID or item.error_reason != error
    if item.status is not _OK:
        return True
    held = item.value
    if _same(held, value):
        return False
    deadband = state.spec.deadband
    if deadband and _is_number(held) and _is_number(value):
        return not abs(value - held) <= deadband
    return True


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _copy_runtime(src: DeviceAddressItem, dst: DeviceAddressItem) -> None:
    for name in _RUNTIME_FIELDS:
        dst.__dict__[name] = src.__dict__[name]


def _status_text(status: Any) -> str:
    return str(getattr(status, "value", status))
