"""A poller's fault policy: what a failed read does to the slave's cycle and status.

* a timeout (after ``retries``) ends this slave's cycle: the cycle's remaining blocks are
  not read and their items go Invalid ("device not responding"); after
  ``offlineAfterFailedCycles`` such cycles the slave is ``Offline`` and is probed with
  one request per backoff interval (doubling from readCycle up to maxBackoff), so a
  dead slave costs the others at most one response timeout (plus settling) per interval;
* an illegal-address exception (02) on a merged block splits the block in two, and
  again, until only the bad addresses fail; the split is kept for later cycles;
* CRC, protocol and other exception responses invalidate that block's items only.

:class:`FaultPolicy` is a part of :class:`~edgemodbus.poll.poller.Poller`, kept here
for size: it uses the poller's state, declared below.
"""

from __future__ import annotations

import logging
import time

from .._ffi import Block
from .._ffi.engine import BlockSpec, EngineDevice
from ..codec import Change
from ..datatypes import DeviceDriverStatus
from ..errors import (
    CrcError,
    IllegalDataAddress,
    ModbusConnectionError,
    ModbusError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)
from ..line import Link
from ..stats import DeviceStats
from .items import Slot
from .planner import ReadBlock, bisect_block
from .sink import Delivery, PollSink


class FaultPolicy:
    """Retries, cycle ends, offline and backoff, exception 02 bisection (see above)."""

    # the poller's state (poller.py)
    code: str
    log: logging.Logger
    slave: int
    timeout: float
    retries: int
    offline_after: int
    max_backoff: float
    report_all: bool
    snapshot_interval: float
    counters: DeviceStats
    delivery: Delivery
    sink: PollSink
    status: DeviceDriverStatus
    slots: list[Slot]
    device: EngineDevice
    cycle: float
    failed_cycles: int
    offline: bool
    backoff: float
    next_snapshot: float

    @property
    def _pass(self) -> list[Slot]:
        raise NotImplementedError

    def _set_status(self, status: DeviceDriverStatus, reason: str | None) -> None:
        """Set the device's status; a change is told to the listeners.  Worker thread."""
        if status is not self.status:
            self.status = status
            self.delivery.status(status, reason)

    def _read_slot(self, link: Link, slot: Slot) -> tuple[Block, list[Change]]:
        raise NotImplementedError

    def _good_read(self, slot: Slot, data: Block, changes: list[Change]) -> None:
        raise NotImplementedError

    def _next_block(self) -> None:
        raise NotImplementedError

    def _invalidate(self, slot: Slot, reason: str) -> None:
        raise NotImplementedError

    def _make_slot(self, block: ReadBlock) -> Slot:
        raise NotImplementedError

    def _spec(self, slot: Slot) -> BlockSpec:
        raise NotImplementedError

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
            link.set_response_timeout(self.timeout)
            try:
                data, changes = self._read_slot(link, slot)
            except ModbusError as exc:
                error = exc
                continue
            self._good_read(slot, data, changes)
            return
        device = self.device
        slots = self._pass
        index = device.index
        if isinstance(error, ModbusConnectionError):
            return  # the line reports the link as down; every block is read on the next
        if isinstance(error, ModbusTimeoutError):
            reason = f"device not responding: {error}"
            counters.skipped_blocks += len(slots) - index - 1
            for rest in slots[index:]:
                self._invalidate(rest, reason)
            if self.offline or self.failed_cycles + 1 >= self.offline_after:
                # offline: the blocks not due in this cycle hold no fresh value either
                for other in [s for s in self.slots if s not in slots]:  # by identity
                    self._invalidate(other, reason)
            self._end_cycle(failed=True)
        elif isinstance(error, IllegalDataAddress) and len(block.pieces) > 1:
            halves = bisect_block(block)
            new = [self._make_slot(b) for b in halves]
            at = next(i for i, s in enumerate(self.slots) if s is slot)
            self.slots[at:at + 1] = new
            device.split(at, [self._spec(s) for s in new])
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
            self._next_block()
        self._update_notify()

    def _back_online(self) -> None:
        if self.offline:
            self.log.info("%s: slave %d answers again", self.code, self.slave)
        self._set_status(DeviceDriverStatus.RUNNING, None)
        self.offline = False
        self.failed_cycles = 0
        self.backoff = self.cycle

    def _update_notify(self) -> None:
        """Have the engine come back at the end of the next pass even without news
        while the poller must see it: the status or the failed-cycle count may move,
        or every value is reported every cycle."""
        self.device.notify = (self.report_all or self.failed_cycles > 0
                              or self.status is not DeviceDriverStatus.RUNNING)

    def _end_cycle(self, failed: bool) -> None:
        """End the pass in Python (a failed one, or one stepped in Python)."""
        now = time.monotonic()
        device = self.device
        device.end_pass(now)
        counters = self.counters
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
                self._set_status(DeviceDriverStatus.OFFLINE,
                                 f"offline after {self.failed_cycles} failed cycles")
                self.backoff = min(self.cycle, self.max_backoff)
                self.log.warning("%s: slave %d offline after %d failed cycles; probing every "
                                 "%.3g s and backing off", self.code, self.slave,
                                 self.failed_cycles, self.backoff)
            device.all_due(now + self.backoff)  # the probe is a cycle over every block
        self._cycle_done(now)

    def _cycle_done(self, now: float) -> None:
        self.delivery.flush()
        self._update_notify()
        if self.snapshot_interval and now >= self.next_snapshot:
            self._snapshot(now)

    def _snapshot(self, now: float) -> None:
        """Publish the snapshot; the engine hands over the first pass that ends after
        the next one is due."""
        self.next_snapshot = self.device.notify_at = now + self.snapshot_interval
        self.delivery.snapshot_due()
