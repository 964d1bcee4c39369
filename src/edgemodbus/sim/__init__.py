"""The simulator: many Modbus RTU slaves on one simulated line, with fault injection."""

from __future__ import annotations

from .server import (
    DEFAULT_SIZE,
    CounterMover,
    DtuClient,
    Faults,
    FloatSineMover,
    Mover,
    RandomWalkMover,
    Simulator,
    SineMover,
    Slave,
    add_demo_movers,
    default_bit,
    default_register,
    main,
)

__all__ = [
    "DEFAULT_SIZE",
    "CounterMover",
    "DtuClient",
    "Faults",
    "FloatSineMover",
    "Mover",
    "RandomWalkMover",
    "Simulator",
    "SineMover",
    "Slave",
    "add_demo_movers",
    "default_bit",
    "default_register",
    "main",
]
