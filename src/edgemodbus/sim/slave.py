"""One simulated slave: its four data areas (values derived from their address), its
movers and fault knobs, and the handling of one request into the bytes that go on the
wire, and when.
"""

from __future__ import annotations

import collections
import dataclasses
import random
import struct
import threading
import time
from array import array
from collections.abc import Mapping, Sequence
from typing import Any

from ..datatypes import Area
from ..protocol import rtu
from ..protocol.limits import max_read
from .actions import _RESET, _Action, _spread
from .faults import Faults
from .movers import Mover

DEFAULT_SIZE = 10_000

_READ_AREA = {
    rtu.READ_COILS: Area.COIL,
    rtu.READ_DISCRETE_INPUTS: Area.DISCRETE_INPUT,
    rtu.READ_HOLDING_REGISTERS: Area.HOLDING_REGISTER,
    rtu.READ_INPUT_REGISTERS: Area.INPUT_REGISTER,
}

# Exception codes (Application Protocol v1.1b3, 7).
_ILLEGAL_FUNCTION, _ILLEGAL_ADDRESS, _ILLEGAL_VALUE, _SLAVE_FAILURE = 0x01, 0x02, 0x03, 0x04


def default_register(slave: int, address: int) -> int:
    """Initial value of holding and input register ``address`` of ``slave``."""
    return (slave * 1000 + address) & 0xFFFF


def default_bit(slave: int, address: int) -> bool:
    """Initial value of coil and discrete input ``address`` of ``slave``."""
    return (address + slave) % 2 == 0


class _Exc(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class Slave:
    """One slave: four data areas, movers, fault knobs and counters. Thread-safe."""

    def __init__(self, slave_id: int, size: int = DEFAULT_SIZE) -> None:
        if not 1 <= slave_id <= rtu.MAX_SLAVE_ID:
            raise ValueError(f"slave id {slave_id} out of 1..{rtu.MAX_SLAVE_ID}")
        if not 1 <= size <= 0x10000:
            raise ValueError(f"size {size} out of 1..65536")
        self.slave_id = slave_id
        self.size = size
        self.faults = Faults()
        self._lock = threading.Lock()
        regs = array("H", [default_register(slave_id, a) for a in range(size)])
        bits = bytearray(1 if default_bit(slave_id, a) else 0 for a in range(size))
        self._regs = {Area.HOLDING_REGISTER: regs, Area.INPUT_REGISTER: array("H", regs)}
        self._bits = {Area.COIL: bits, Area.DISCRETE_INPUT: bytearray(bits)}
        self._movers: list[tuple[Mover, float]] = []
        self._ticks: dict[str, tuple[int, int]] = {}
        self._requests = 0
        self._replies = 0
        self._exceptions = 0
        self._broadcasts = 0
        self._held = b""  # a reply held back by hold_reply_every
        self._faults_injected: collections.Counter[str] = collections.Counter()

    def __repr__(self) -> str:
        return f"Slave({self.slave_id}, size={self.size})"

    # -- data access from the test/demo side

    def get_registers(self, area: Area, address: int, count: int = 1) -> list[int]:
        """Raw 16-bit values of a holding/input register range (movers applied)."""
        regs = self._reg_area(area)
        self._check_range(address, count)
        with self._lock:
            self._apply_movers(area, address, count)
            return list(regs[address : address + count])

    def set_registers(self, area: Area, address: int, values: Sequence[int]) -> None:
        """Set registers; values in -32768..65535 (negative ones as two's complement)."""
        regs = self._reg_area(area)
        self._check_range(address, len(values))
        for v in values:
            if not -0x8000 <= v <= 0xFFFF:
                raise ValueError(f"register value {v} out of 16 bits")
        with self._lock:
            for i, v in enumerate(values):
                regs[address + i] = v & 0xFFFF

    def set_float32(self, area: Area, address: int, value: float) -> None:
        """Store a float32 at a register pair, ABCD (big-endian) order."""
        self.set_registers(area, address, struct.unpack(">HH", struct.pack(">f", value)))

    def get_bits(self, area: Area, address: int, count: int = 1) -> list[bool]:
        bits = self._bit_area(area)
        self._check_range(address, count)
        with self._lock:
            return [bool(b) for b in bits[address : address + count]]

    def set_bits(self, area: Area, address: int, values: Sequence[bool | int]) -> None:
        bits = self._bit_area(area)
        self._check_range(address, len(values))
        with self._lock:
            for i, v in enumerate(values):
                bits[address + i] = 1 if v else 0

    def add_mover(self, mover: Mover) -> Mover:
        """Drive a register range from the clock, starting now; returns the mover."""
        self._reg_area(mover.area)
        self._check_range(mover.address, mover.count)
        with self._lock:
            self._movers.append((mover, time.monotonic()))
        return mover

    def clear_movers(self) -> None:
        """Stop every mover; registers keep their last computed values."""
        with self._lock:
            self._movers.clear()

    def set_faults(self, **knobs: Any) -> None:
        """Set several :class:`Faults` knobs at once, atomically for the serving thread."""
        names = {f.name for f in dataclasses.fields(Faults)}
        unknown = set(knobs) - names
        if unknown:
            raise AttributeError(f"unknown fault knob(s): {', '.join(sorted(unknown))}")
        with self._lock:
            for name, value in knobs.items():
                setattr(self.faults, name, value)

    def stats(self) -> dict[str, Any]:
        """requests (unicast frames for us), replies (frames put on the wire),
        exceptions (exception replies built), broadcasts (broadcasts executed) and
        faults (times each knob acted, by knob name)."""
        with self._lock:
            return {
                "requests": self._requests,
                "replies": self._replies,
                "exceptions": self._exceptions,
                "broadcasts": self._broadcasts,
                "faults": dict(self._faults_injected),
            }

    # -- helpers

    def _reg_area(self, area: Area) -> array[int]:
        if area.is_bit:
            raise ValueError(f"{area} is a bit area")
        return self._regs[area]

    def _bit_area(self, area: Area) -> bytearray:
        if not area.is_bit:
            raise ValueError(f"{area} is a register area")
        return self._bits[area]

    def _check_range(self, address: int, count: int) -> None:
        if address < 0 or count < 0 or address + count > self.size:
            raise IndexError(f"range {address}+{count} outside 0..{self.size - 1}")

    def _apply_movers(self, area: Area, address: int, count: int) -> None:
        """Refresh movers overlapping [address, address+count). Lock held."""
        if not self._movers:
            return
        now = time.monotonic()
        regs = self._regs[area]
        for mover, t0 in self._movers:
            if (
                mover.area is area
                and mover.address < address + count
                and (address < mover.address + mover.count)
            ):
                for i, v in enumerate(mover.values(now - t0)):
                    regs[mover.address + i] = v

    def _every(self, knob: str, n: int) -> bool:
        """Count one more opportunity for an "every N" knob; True on every Nth."""
        if n <= 0:
            self._ticks.pop(knob, None)
            return False
        last_n, seen = self._ticks.get(knob, (n, 0))
        seen = (0 if last_n != n else seen) + 1
        self._ticks[knob] = (n, seen)
        return seen % n == 0

    def _fault(self, knob: str) -> None:
        self._faults_injected[knob] += 1

    # -- serving (called on the loop thread)

    def _handle(self, raw: bytes, pdu: bytes, rng: random.Random, can_close: bool) -> list[_Action]:
        """Answer one unicast request: the actions to put on the wire."""
        with self._lock:
            self._requests += 1
            f = self.faults
            if f.silent:
                self._fault("silent")
                return []
            if self._every("close_every", f.close_every):
                self._fault("close_every")
                return [(0.0, None)] if can_close else []
            actions: list[_Action] = []
            if f.echo_request:
                self._fault("echo_request")
                actions.append((0.0, raw))
            if f.random_reply_count > 0:
                f.random_reply_count -= 1
                self._fault("random_reply_count")
                frame = rng.randbytes(rng.randint(3, 16))
            elif self._every("raw_reply_every", f.raw_reply_every if f.raw_reply else 0):
                self._execute(pdu)
                self._fault("raw_reply_every")
                frame = bytes(f.raw_reply)
            else:
                rpdu = self._execute(pdu)
                if f.exception_for_other_function:
                    self._fault("exception_for_other_function")
                    other = 0x04 if pdu[0] == 0x03 else 0x03
                    code = rpdu[1] if rpdu[0] & 0x80 else _SLAVE_FAILURE
                    rpdu = bytes([0x80 | other, code])
                if rpdu[0] & 0x80:
                    self._exceptions += 1
                elif rpdu[0] in _READ_AREA and self._every(
                    "wrong_byte_count_every", f.wrong_byte_count_every
                ):
                    self._fault("wrong_byte_count_every")
                    rpdu = _wrong_byte_count(rpdu)
                address = self.slave_id
                if f.answer_as is not None:
                    self._fault("answer_as")
                    address = f.answer_as
                body = bytearray([address & 0xFF]) + rpdu
                if self._every("patch_every", f.patch_every if f.patch else 0):
                    self._fault("patch_every")
                    for index, value in dict(f.patch).items():
                        if 0 <= index < len(body):
                            body[index] = value & 0xFF
                buf = bytearray(rtu.frame(body[0], bytes(body[1:])))
                # Evaluate every knob so each one's count advances on every reply.
                drop = self._every("drop_every", f.drop_every)
                bad_data = self._every("corrupt_data_every", f.corrupt_data_every)
                bad_crc = self._every("corrupt_crc_every", f.corrupt_crc_every)
                truncate = self._every("truncate_every", f.truncate_every)
                if drop:
                    self._fault("drop_every")
                    return actions
                if bad_data:
                    self._fault("corrupt_data_every")
                    buf[-3] ^= 0x01  # last byte before the CRC is always data
                if bad_crc:
                    self._fault("corrupt_crc_every")
                    buf[-2] ^= 0x01
                if truncate:
                    self._fault("truncate_every")
                    del buf[max(1, len(buf) // 2) :]
                frame = bytes(buf)
            if f.noise_before:
                self._fault("noise_before")
                frame = f.noise_before + frame
            if f.trailing_garbage:
                self._fault("trailing_garbage")
                frame = frame + f.trailing_garbage
            if self._every("hold_reply_every", f.hold_reply_every):
                self._fault("hold_reply_every")
                self._held += frame
                return actions
            if self._held:
                frame, self._held = self._held + frame, b""
            delay = max(0.0, f.delay)
            if delay > 0 and (f.delay_every <= 0 or self._every("delay_every", f.delay_every)):
                self._fault("delay")
            else:
                delay = 0.0
            if self._every("cut_every", f.cut_every):
                self._fault("cut_every")
                half = frame[: max(1, len(frame) // 2)]
                end: list[_Action] = [(delay, _RESET if f.cut_with_reset else None)]
                return actions + [(delay, half)] + (end if can_close else [])
            if f.byte_delay > 0:
                self._fault("byte_delay")
            elif f.split_reply > 1:
                self._fault("split_reply")
            self._replies += 1
            return actions + _spread(frame, delay, f.split_reply, f.split_pause, f.byte_delay)

    def _handle_broadcast(self, pdu: bytes) -> list[_Action]:
        """Execute a broadcast write (Serial Line 2.1: never answered, unless
        ``answer_broadcast``)."""
        with self._lock:
            f = self.faults
            if f.silent:
                self._fault("silent")
                return []
            self._broadcasts += 1
            rpdu = self._execute(pdu)
            if not f.answer_broadcast:
                return []
            self._fault("answer_broadcast")
            self._replies += 1
            return [(max(0.0, f.delay), rtu.frame(self.slave_id, rpdu))]

    def _execute(self, pdu: bytes) -> bytes:
        """Execute a request PDU; the response PDU (or exception PDU). Lock held."""
        fc = pdu[0]
        try:
            if fc in self.faults.refused_functions:
                self._fault("refused_functions")
                raise _Exc(_ILLEGAL_FUNCTION)
            if fc in _READ_AREA:
                return self._read(fc, pdu)
            if fc == rtu.WRITE_SINGLE_COIL:
                return self._write_coil(pdu)
            if fc == rtu.WRITE_SINGLE_REGISTER:
                return self._write_register(pdu)
            if fc == rtu.WRITE_MULTIPLE_COILS:
                return self._write_coils(pdu)
            if fc == rtu.WRITE_MULTIPLE_REGISTERS:
                return self._write_registers(pdu)
            if fc == rtu.MASK_WRITE_REGISTER:
                return self._mask_write(pdu)
            raise _Exc(_ILLEGAL_FUNCTION)
        except _Exc as e:
            return bytes([(fc | 0x80) & 0xFF, e.code])

    def _validate(self, area: Area, address: int, count: int) -> None:
        """Address range (exception 02), then the fault knob ranges."""
        if address + count > self.size:
            raise _Exc(_ILLEGAL_ADDRESS)
        for r_area, start, end, code in list(self.faults.exception_ranges):
            if r_area is area and address < end and start < address + count:
                raise _Exc(code)

    def _read(self, fc: int, pdu: bytes) -> bytes:
        # 6.1-6.4: quantity 1..2000 bits / 1..125 registers, else 03; range, else 02.
        area = _READ_AREA[fc]
        address, count = struct.unpack_from(">HH", pdu, 1)
        if not 1 <= count <= max_read(area):
            raise _Exc(_ILLEGAL_VALUE)
        self._validate(area, address, count)
        if area.is_bit:
            data = rtu.pack_bits(self._bits[area][address : address + count])
        else:
            self._apply_movers(area, address, count)
            data = struct.pack(f">{count}H", *self._regs[area][address : address + count])
        return bytes([fc, len(data)]) + data

    def _write_coil(self, pdu: bytes) -> bytes:
        # 6.5: value 0xFF00 = ON, 0x0000 = OFF, anything else 03; reply echoes the request.
        address, value = struct.unpack_from(">HH", pdu, 1)
        if value not in (0x0000, 0xFF00):
            raise _Exc(_ILLEGAL_VALUE)
        self._validate(Area.COIL, address, 1)
        self._bits[Area.COIL][address] = 1 if value else 0
        return pdu[:5]

    def _write_register(self, pdu: bytes) -> bytes:
        # 6.6: reply echoes the request.
        address, value = struct.unpack_from(">HH", pdu, 1)
        self._validate(Area.HOLDING_REGISTER, address, 1)
        self._regs[Area.HOLDING_REGISTER][address] = value
        return pdu[:5]

    def _write_coils(self, pdu: bytes) -> bytes:
        # 6.11: quantity 1..0x07B0 and byte count N = ceil(quantity / 8), else 03.
        address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
        if not 1 <= count <= 0x07B0 or nbytes != (count + 7) // 8 or len(pdu) != 6 + nbytes:
            raise _Exc(_ILLEGAL_VALUE)
        self._validate(Area.COIL, address, count)
        bits = self._bits[Area.COIL]
        for i in range(count):
            bits[address + i] = (pdu[6 + i // 8] >> (i % 8)) & 1
        return pdu[:5]

    def _write_registers(self, pdu: bytes) -> bytes:
        # 6.12: quantity 1..0x007B and byte count 2 * quantity, else 03.
        address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
        if not 1 <= count <= 0x007B or nbytes != 2 * count or len(pdu) != 6 + nbytes:
            raise _Exc(_ILLEGAL_VALUE)
        self._validate(Area.HOLDING_REGISTER, address, count)
        regs = self._regs[Area.HOLDING_REGISTER]
        regs[address : address + count] = array("H", struct.unpack_from(f">{count}H", pdu, 6))
        return pdu[:5]

    def _mask_write(self, pdu: bytes) -> bytes:
        # 6.16: Result = (Current AND And_Mask) OR (Or_Mask AND (NOT And_Mask)); echo.
        address, and_mask, or_mask = struct.unpack_from(">HHH", pdu, 1)
        self._validate(Area.HOLDING_REGISTER, address, 1)
        regs = self._regs[Area.HOLDING_REGISTER]
        regs[address] = (regs[address] & and_mask) | (or_mask & ~and_mask & 0xFFFF)
        return pdu[:7]


def answer(
    slaves: Mapping[int, Slave], raw: bytes, rng: random.Random, can_close: bool
) -> list[_Action] | None:
    """What the slaves of one line put on the wire for the request frame ``raw`` (address,
    PDU, CRC checked by the caller): a unicast request is handled by the slave it
    addresses, a broadcast write by every slave (Serial Line 2.1: answered only by those
    with ``answer_broadcast``, a collision).  None: no slave has the address (silence)."""
    address, pdu = raw[0], raw[1:-2]
    if address == 0:
        actions: list[_Action] = []
        if pdu[0] in rtu.WRITE_FUNCTIONS:  # Serial Line 2.1: broadcast is for writes only
            for slave in list(slaves.values()):
                actions += slave._handle_broadcast(pdu)
        return actions
    target = slaves.get(address)
    if target is None:
        return None
    return target._handle(raw, pdu, rng, can_close)


def _wrong_byte_count(rpdu: bytes) -> bytes:
    unit = 2 if rpdu[0] in (rtu.READ_HOLDING_REGISTERS, rtu.READ_INPUT_REGISTERS) else 1
    data = rpdu[2:]
    data = data[:-unit] if len(data) > unit else data + bytes(unit)
    return bytes([rpdu[0], len(data)]) + data
