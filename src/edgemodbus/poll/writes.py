"""Writes: a batch of (item, value) pairs planned into requests, and their execution.

:func:`plan_writes` normalizes and encodes the values and merges contiguous registers
(or coils) of one area into as few requests as the protocol allows.  :class:`Writer`
sends them on the worker and stores what the slave confirmed, with the fallbacks a slave
forces (remembered once seen): FC16 refused -> FC06 register by register; FC22 refused
-> read-modify-write with FC03 + FC06.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from .._ffi import Block
from ..codec import BlockDecoder, Float32, encode, float32_short, normalize_value, register_bit
from ..config import DriverModbusRtuParameter
from ..datatypes import Area
from ..errors import IllegalFunction, ModbusConnectionError, ModbusError, ModbusTimeoutError
from ..line import Link
from ..protocol.limits import MAX_WRITE_BITS, MAX_WRITE_REGISTERS
from ..stats import DeviceStats
from .items import ItemState, holds, set_state
from .sink import Delivery
from .store import ItemStore

if TYPE_CHECKING:
    from ..config import DeviceAddressItem



@dataclass
class WriteOp:
    """One write request: consecutive coils or registers of one area, or one bit."""

    area: Area
    address: int
    registers: list[int] = field(default_factory=list)
    bits: list[bool] = field(default_factory=list)
    bit: int | None = None
    updates: list[tuple[ItemState, Any]] = field(default_factory=list)
    function: int | None = None  # an action's function code (5, 6, 15, 16); None: ours

    @property
    def names(self) -> str:
        """The items it writes; an address action's request (no item): its address."""
        return ", ".join(st.item.name for st, _ in self.updates) or \
            f"{self.area.short_name}:{self.address}"


def plan_writes(by_name: Mapping[str, ItemState], items: list[tuple[str, Any]],
                exact: bool = False) -> list[WriteOp]:
    """Normalize, encode and group a batch of writes (raises ValueError naming the item).

    ``by_name`` holds the device's items (``Poller.by_name``).  Contiguous registers (or
    coils) of one area are merged into one request, up to the protocol's limits;
    bit-in-register items are written one by one.  ``exact`` (commands from a broker):
    a value the item cannot hold as given is refused (:func:`exact_problem`) instead of
    rounded, cut or converted.
    """
    return merge_writes(prepare_writes(by_name, items, exact))


#: How far a value computed by an engineering-units step may be from the one asked and
#: still be the same: float rounding of the step's arithmetic (0.3 under a 0..1000 ->
#: 0..100 range is raw 3, read back as 0.30000000000000004), far below a raw step.
SCALED_REL_TOL = 1e-12


def exact_problem(asked: Any, held: Any, scaled: bool = False) -> str | None:
    """Why the value an item would hold after a write (``held``: its encoded registers
    decoded) is not the value ``asked`` (normalized), or None when it is: numbers equal
    exactly (12.5 to a UInt16 with dataMultiplier 0.5 is 25 on the wire, 12.5 back;
    12.3 would be 12.5), to within float rounding for a ``scaled`` item (an offset, a
    range, a scale factor, or a multiplier neither whole nor 1/n: SCALED_REL_TOL), a
    Float (32-bit) item's value when its shortest float32 text is the number asked (0.1
    is taken, 0.1000000001 is not: the float32 of both is one value), text, bytes and
    times unchanged (no cut, no rounded seconds)."""
    numbers = all(isinstance(x, (int, float)) and not isinstance(x, bool)
                  for x in (asked, held))
    if numbers and isinstance(held, float) and math.isnan(held):
        same = isinstance(asked, float) and math.isnan(asked)
    elif numbers and isinstance(held, Float32) and math.isfinite(held):
        same = held == asked or float32_short(held) == asked
    elif numbers and scaled and isinstance(held, float):
        same = held == asked or math.isclose(held, asked, rel_tol=SCALED_REL_TOL)
    else:  # numbers compare exactly (an int with a float too); bools, text, bytes, times
        same = bool(asked == held)
    if same:
        return None
    return f"it would hold {short_value(held)}, not {short_value(asked)}"


def short_value(value: Any) -> str:
    """A value for a message: a long text or bytes cut to a short prefix."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:40]}... ({len(text)} characters)"


def prepare_writes(
    by_name: Mapping[str, ItemState], items: list[tuple[str, Any]], exact: bool = False
) -> list[WriteOp]:
    """Normalize and encode a batch of writes, one request per item (not merged yet);
    raises ValueError naming the item (``exact``: see :func:`plan_writes`)."""
    if not items:
        raise ValueError("nothing to write")
    seen: set[str] = set()
    single: list[WriteOp] = []
    for name, raw in items:
        state = by_name.get(name)
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
        if exact and isinstance(raw, bool) and not isinstance(value, bool):
            raise ValueError(f"{name}: cannot write {raw!r} exactly: a boolean for a "
                             f"{(spec.converted_type or spec.data_type).value} item")
        if state.area is Area.COIL or state.bit is not None:
            on = bool(encode(spec, value)[0])
            problem = exact_problem(value, on) if exact else None
            if problem is not None:
                raise ValueError(f"{name}: cannot write {short_value(raw)} exactly: {problem}")
            raw_bit = None if state.bit is None else register_bit(spec)
            single.append(WriteOp(state.area, state.offset, bits=[on], bit=raw_bit,
                                  updates=[(state, on)]))
            continue
        registers = encode(spec, value)
        decoded = BlockDecoder(state.area, len(registers), [(0, spec)]).decode_values(
            Block.from_values(registers, bits=False)
        )[0]
        m = spec.multiplier  # raw * m rounds (0.3); raw * 10 and raw / 10 do not
        scaled = spec.scaled or not (m.is_integer() or (1 / m).is_integer())
        problem = exact_problem(value, decoded, scaled) if exact else None
        if problem is not None:
            raise ValueError(f"{name}: cannot write {short_value(raw)} exactly: {problem}")
        single.append(WriteOp(state.area, state.offset, registers=registers,
                              updates=[(state, decoded)]))
    return single


def merge_writes(ops: list[WriteOp]) -> list[WriteOp]:
    """Contiguous coils or registers of one area in one request, up to the protocol's
    limits (bits of registers stay alone)."""
    ops.sort(key=lambda o: (o.area.value, o.address))
    merged: list[WriteOp] = []
    for op in ops:
        last = merged[-1] if merged else None
        if last is not None and last.area is op.area and last.bit is None and op.bit is None:
            if op.area is Area.COIL and last.address + len(last.bits) == op.address and len(
                last.bits
            ) < MAX_WRITE_BITS:
                last.bits.extend(op.bits)
                last.updates.extend(op.updates)
                continue
            if op.area is Area.HOLDING_REGISTER and (
                last.address + len(last.registers) == op.address
                and len(last.registers) + len(op.registers) <= MAX_WRITE_REGISTERS
            ):
                last.registers.extend(op.registers)
                last.updates.extend(op.updates)
                continue
        merged.append(op)
    return merged


class Writer:
    """Sends the write requests of one slave and stores the values it confirmed.
    Worker thread only."""

    def __init__(self, code: str, params: DriverModbusRtuParameter, log: logging.Logger,
                 counters: DeviceStats, delivery: Delivery) -> None:
        self.code = code
        self.log = log
        self.slave = params.slave_id
        self.report_all = params.report_mode == "cycle"
        self.write_single_fc = params.write_single_register_function
        self.counters = counters
        self.delivery = delivery
        self.no_fc16 = False
        self.no_fc22 = False

    def run(self, link: Link, ops: list[WriteOp],
            recheck: Callable[[list[ItemState]], None], store: ItemStore[ItemState],
            whole: bool = False) -> tuple[bool, str | None]:
        """Send ``ops`` in order; a confirmed write's values go into ``store`` (the
        device's, store.py: items of a plan replaced since are left to the next read)
        and ``recheck`` is told which items it set.  ``whole`` (an action): the first
        failure stops the batch, the rest is not sent."""
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
                if isinstance(exc, ModbusTimeoutError):  # each would cost another timeout
                    errors.extend(f"{o.names}: not sent (no answer to the one before)"
                                  for o in ops[i + 1:])
                    break
                if whole:
                    errors.extend(f"{o.names}: not sent" for o in ops[i + 1:])
                    if i:
                        errors.append("written before the failure: "
                                      + ", ".join(o.names for o in ops[:i]))
                    break
                continue
            recheck([state for state, _ in op.updates])
            confirmed = [
                set_state(store, state, value, None, now)
                for state, value in op.updates
                if store.owns(state) and (self.report_all or not holds(store, state, value))
            ]
            if confirmed:
                self.counters.values_changed += len(confirmed)
                self.delivery.notify(confirmed)
                written += confirmed
        if written:
            # One write, one update: the item callbacks above, and one batch now (the
            # next read of the written value is no news, see Poller._recheck); an item
            # already in this cycle's batch goes out once, with its written value.
            queued = {id(item) for item in self.delivery.batch}
            self.delivery.batch += [item for item in written if id(item) not in queued]
            self.delivery.flush()
        return (False, "; ".join(errors)) if errors else (True, None)

    def _execute(self, link: Link, op: WriteOp) -> None:
        slave = self.slave
        if op.function is not None:
            self._execute_as(link, op)
            return
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

    def _execute_as(self, link: Link, op: WriteOp) -> None:
        """An action's request with exactly its function code, no fallback (MODBUS
        Application Protocol v1.1b3: 6.5 FC05, 6.6 FC06, 6.11 FC15, 6.12 FC16)."""
        slave, fc = self.slave, op.function
        if fc == 5:
            for k, on in enumerate(op.bits):
                link.write_coil(slave, op.address + k, on)
        elif fc == 15:
            link.write_coils(slave, op.address, op.bits)
        elif fc == 6:
            for k, value in enumerate(op.registers):
                link.write_register(slave, op.address + k, value)
        elif fc == 16:
            link.write_registers(slave, op.address, op.registers)
        else:
            raise ValueError(f"function code {fc!r} does not write (use 5, 6, 15 or 16)")

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
