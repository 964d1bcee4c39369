"""The simulator: many Modbus RTU slaves on one simulated line, with fault injection."""

from __future__ import annotations

from .faults import ExceptionRange, Faults
from .movers import (
    CounterMover,
    FloatSineMover,
    Mover,
    MoverHost,
    RandomWalkMover,
    SineMover,
    add_demo_movers,
)
from .server import DtuClient, Simulator, main
from .slave import DEFAULT_SIZE, Slave, default_bit, default_register

__all__ = [
    "DEFAULT_SIZE",
    "CounterMover",
    "DtuClient",
    "ExceptionRange",
    "Faults",
    "FloatSineMover",
    "Mover",
    "MoverHost",
    "RandomWalkMover",
    "Simulator",
    "SineMover",
    "Slave",
    "add_demo_movers",
    "default_bit",
    "default_register",
    "main",
]
