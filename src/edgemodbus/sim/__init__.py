"""A multi-slave Modbus RTU slave with fault injection, for the demo and for tests.

One :class:`Simulator` plays every slave of one RS-485 "line". It serves raw RTU frames
(slave id + PDU + CRC-16/MODBUS, no MBAP header) over TCP, as a transparent DTU or serial
server would, and over a pseudo-terminal whose slave side a master opens as a serial
port. Every TCP connection is a line of its own (its own receive buffer); the slaves and
their data are shared by all lines.

Values start DERIVED FROM THEIR ADDRESS (:func:`default_register`, :func:`default_bit`),
so a value that came from the wrong request is detectable. Per-slave movers make values
change over time (computed lazily from the clock at request time), and per-slave
:class:`Faults` knobs, settable at runtime from any thread, misbehave on the wire in the
ways real slaves, adapters and DTUs do.

One background thread runs a ``selectors`` loop for every listener, connection and pty
(loop.py). The package is pure Python (stdlib only) and never touches libmodbus, so it
can check the master library from the outside.

Modules: slave.py (a slave: data areas and request handling), faults.py (its fault
knobs), movers.py (values that follow the clock), line.py and loop.py (lines and the
loop thread), server.py (:class:`Simulator`), dtu_client.py (DTU-client mode and wrapped
frames), fleet.py (:class:`DtuFleet`: thousands of DTUs dialling in, each with its own
slaves, on one asyncio loop; dialling.py: the open files and source addresses it needs;
fleet_procs.py: :class:`FleetProcesses`, a fleet shared out over processes), cli.py
(``edgemodbus simulate``).
"""

from __future__ import annotations

from .cli import main
from .dialling import loopback_sources, raise_open_files_limit
from .dtu_client import DtuClient
from .faults import ExceptionRange, Faults
from .fleet import FLEET_SIZE, DtuFleet, FleetDtu
from .fleet_procs import FleetProcesses
from .movers import (
    CounterMover,
    FloatSineMover,
    Mover,
    MoverHost,
    RandomWalkMover,
    SineMover,
    add_demo_movers,
)
from .server import Simulator
from .slave import DEFAULT_SIZE, Slave, default_bit, default_register

__all__ = [
    "DEFAULT_SIZE",
    "FLEET_SIZE",
    "CounterMover",
    "DtuClient",
    "DtuFleet",
    "ExceptionRange",
    "Faults",
    "FleetDtu",
    "FleetProcesses",
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
    "loopback_sources",
    "main",
    "raise_open_files_limit",
]
