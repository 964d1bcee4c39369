"""Movers: register ranges whose values follow the clock, and the demo's set of them.

A mover computes its registers from the time since it was added to a slave, when they
are read (no thread): :class:`CounterMover`, :class:`SineMover` (int16),
:class:`RandomWalkMover` (int16) and :class:`FloatSineMover` (float32, ABCD).
"""

from __future__ import annotations

import dataclasses
import math
import random
import struct
from typing import Protocol

from ..datatypes import Area


class Mover:
    """A register range whose values follow the clock (computed when read, no thread).

    ``values(elapsed)`` gives the raw 16-bit registers ``elapsed`` seconds after the
    mover was added to a slave.
    """

    area: Area
    address: int

    @property
    def count(self) -> int:
        raise NotImplementedError

    def values(self, elapsed: float) -> list[int]:
        raise NotImplementedError

    def _check(self) -> None:
        if self.area.is_bit:
            raise ValueError(f"{type(self).__name__}: movers drive registers, not {self.area}")
        if self.address < 0 or self.count < 1 or self.address + self.count > 0x10000:
            raise ValueError(f"{type(self).__name__}: bad address range")


@dataclasses.dataclass
class CounterMover(Mover):
    """``count`` registers counting up by ``step`` every ``interval_ms`` (wrapping at
    16 bits); register i holds ``start + i + step * ticks``."""

    area: Area = Area.HOLDING_REGISTER
    address: int = 0
    registers: int = 1
    interval_ms: float = 1000.0
    step: int = 1
    start: int = 0

    def __post_init__(self) -> None:
        if self.interval_ms <= 0:
            raise ValueError("CounterMover: interval_ms must be > 0")
        self._check()

    @property
    def count(self) -> int:
        return self.registers

    def values(self, elapsed: float) -> list[int]:
        ticks = int(elapsed * 1000.0 // self.interval_ms)
        return [(self.start + i + self.step * ticks) & 0xFFFF for i in range(self.registers)]


def _int16(value: float) -> int:
    """Round and clip to int16, as the raw (two's complement) register."""
    return max(-0x8000, min(0x7FFF, round(value))) & 0xFFFF


@dataclasses.dataclass
class SineMover(Mover):
    """``count`` int16 registers following ``offset + amplitude * sin(2 pi t / period_s)``;
    register i lags by i / registers of a period."""

    area: Area = Area.HOLDING_REGISTER
    address: int = 0
    registers: int = 1
    period_s: float = 10.0
    amplitude: float = 1000.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.period_s <= 0:
            raise ValueError("SineMover: period_s must be > 0")
        self._check()

    @property
    def count(self) -> int:
        return self.registers

    def values(self, elapsed: float) -> list[int]:
        out = []
        for i in range(self.registers):
            phase = 2.0 * math.pi * (elapsed / self.period_s - i / self.registers)
            out.append(_int16(self.offset + self.amplitude * math.sin(phase)))
        return out


@dataclasses.dataclass
class RandomWalkMover(Mover):
    """``count`` int16 registers each taking a +-``step`` random step every
    ``interval_ms``, kept within [low, high]; deterministic for a given ``seed``."""

    area: Area = Area.HOLDING_REGISTER
    address: int = 0
    registers: int = 1
    interval_ms: float = 500.0
    step: int = 10
    start: int = 0
    low: int = -1000
    high: int = 1000
    seed: int = 0

    def __post_init__(self) -> None:
        if self.interval_ms <= 0 or self.low > self.high:
            raise ValueError("RandomWalkMover: need interval_ms > 0 and low <= high")
        self._check()
        self._rng = random.Random(self.seed)
        self._current = [min(self.high, max(self.low, self.start))] * self.registers
        self._done = 0

    @property
    def count(self) -> int:
        return self.registers

    def values(self, elapsed: float) -> list[int]:
        due = int(elapsed * 1000.0 // self.interval_ms)
        # After a long quiet spell only the last steps matter to a reader.
        steps = min(max(0, due - self._done), 1000)
        self._done = max(self._done, due)
        for _ in range(steps):
            for i in range(self.registers):
                v = self._current[i] + self._rng.choice((-self.step, self.step))
                self._current[i] = min(self.high, max(self.low, v))
        return [_int16(v) for v in self._current]


@dataclasses.dataclass
class FloatSineMover(Mover):
    """A float32 at a register pair, big-endian word and byte order (ABCD, Application
    Protocol 4.2), following ``offset + amplitude * sin(2 pi t / period_s)``."""

    area: Area = Area.HOLDING_REGISTER
    address: int = 0
    period_s: float = 10.0
    amplitude: float = 100.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.period_s <= 0:
            raise ValueError("FloatSineMover: period_s must be > 0")
        self._check()

    @property
    def count(self) -> int:
        return 2

    def values(self, elapsed: float) -> list[int]:
        v = self.offset + self.amplitude * math.sin(2.0 * math.pi * elapsed / self.period_s)
        hi, lo = struct.unpack(">HH", struct.pack(">f", v))
        return [hi, lo]


class MoverHost(Protocol):
    """What :func:`add_demo_movers` needs of a slave (:class:`~edgemodbus.sim.Slave`, which
    imports this module)."""

    @property
    def slave_id(self) -> int: ...

    def add_mover(self, mover: Mover) -> Mover: ...


def add_demo_movers(slave: MoverHost) -> None:
    """The demo's moving values: HR 0 counts every second, HR 1 is an int16 sine
    (period 10 s, amplitude 1000), HR 2-3 a float32 ABCD sine (period 20 s,
    amplitude 50, offset 20), IR 0-3 random walks."""
    slave.add_mover(CounterMover(area=Area.HOLDING_REGISTER, address=0, interval_ms=1000))
    slave.add_mover(SineMover(area=Area.HOLDING_REGISTER, address=1, period_s=10.0))
    slave.add_mover(
        FloatSineMover(
            area=Area.HOLDING_REGISTER, address=2, period_s=20.0, amplitude=50.0, offset=20.0
        )
    )
    slave.add_mover(
        RandomWalkMover(area=Area.INPUT_REGISTER, address=0, registers=4, seed=slave.slave_id)
    )
