"""Our simulator as a benchmark peer in its own process (so its CPU is not ours).

:class:`SimulatorProcess` starts :class:`edgemodbus.sim.Simulator` in a spawned
process serving raw RTU frames over TCP on 127.0.0.1 (an ephemeral port) and drives it
over a pipe: set registers, and choose which register ranges change between two reads.

Values change through :class:`FlipMover`, which inverts every bit of its registers on
each request that reads them.  Unlike the clock-driven movers it makes EVERY item in its
range change on every read, whatever the type (a bit of a register, a Boolean register
holding 0, a string), so the fraction of values that change per cycle is exactly the
fraction of items under a mover; a mover must not straddle two read blocks (it would
flip twice per cycle), so give it one item's registers or one whole block.

Faults (a slave answering late, say) are set with :meth:`SimulatorProcess.set_faults`,
and :meth:`SimulatorProcess.record_requests` logs when each request arrived at the
slave side (``time.monotonic()``, which on Linux is one clock for every process: the
benchmark compares it with its own).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

from edgemodbus.datatypes import Area
from edgemodbus.sim import Mover, Simulator

#: (slave id, area, first register, register count)
Range = tuple[int, Area, int, int]


class FlipMover(Mover):
    """``registers`` registers that are inverted (x ^ 0xFFFF) on every read of them."""

    def __init__(self, area: Area, address: int, initial: Sequence[int]) -> None:
        self.area = area
        self.address = address
        self._current = [v & 0xFFFF for v in initial]
        self._check()

    @property
    def count(self) -> int:
        return len(self._current)

    def values(self, elapsed: float) -> list[int]:
        self._current = [v ^ 0xFFFF for v in self._current]
        return self._current


#: (arrival time, slave id, function code) of one request, as recorded at the slave side
Arrival = tuple[float, int, int]


def _serve(conn: Connection, slave_ids: list[int], size: int) -> None:
    """The child: serve until told to stop (or until the parent goes away)."""
    arrivals: list[Arrival] = []
    with Simulator(slave_ids, size) as sim:
        conn.send(sim.serve_tcp("127.0.0.1", 0))
        while True:
            try:
                command, args = conn.recv()
            except EOFError:
                return
            if command == "stop":
                conn.send(None)
                return
            try:
                conn.send(("ok", _execute(sim, arrivals, command, args)))
            except Exception as exc:
                conn.send(("error", repr(exc)))


def _execute(sim: Simulator, arrivals: list[Arrival], command: str, args: Any) -> Any:
    if command == "set":
        for slave_id, area, address, values in args:
            sim.slave(slave_id).set_registers(area, address, values)
        return None
    if command == "flip":
        for slave in sim.slaves:
            slave.clear_movers()
        for slave_id, area, address, count in args:
            slave = sim.slave(slave_id)
            slave.add_mover(FlipMover(area, address, slave.get_registers(area, address, count)))
        return len(args)
    if command == "stats":
        return sim.stats()
    if command == "faults":
        slave_id, knobs = args
        sim.slave(slave_id).set_faults(**knobs)
        return None
    if command == "record":
        # list.append is atomic: the loop thread appends, this thread swaps the list out
        sim.on_request = (
            (lambda at, raw: arrivals.append((at, raw[0], raw[1]))) if args else None
        )
        return None
    if command == "arrivals":
        taken = arrivals[:]
        del arrivals[: len(taken)]
        return taken
    raise ValueError(f"unknown command {command!r}")


class SimulatorProcess:
    """A :class:`Simulator` with ``slave_ids`` in a spawned process; use as a context
    manager (the process is stopped, or killed, on exit)."""

    def __init__(self, slave_ids: Sequence[int], size: int = 2000) -> None:
        self.slave_ids = list(slave_ids)
        self.size = size
        self.port = 0
        self._conn: Connection | None = None
        self._proc: multiprocessing.process.BaseProcess | None = None

    def __enter__(self) -> SimulatorProcess:
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve, args=(child, self.slave_ids, self.size), name="bench-simulator",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            if not parent.poll(30):
                raise RuntimeError("simulator process did not start")
            self.port = int(parent.recv())
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, command: str, args: Any = None) -> Any:
        assert self._conn is not None, "not started"
        self._conn.send((command, args))
        if not self._conn.poll(30):
            raise RuntimeError(f"simulator process did not answer {command!r}")
        status, result = self._conn.recv()
        if status != "ok":
            raise RuntimeError(f"simulator process: {command}: {result}")
        return result

    def set_registers(self, writes: Sequence[tuple[int, Area, int, Sequence[int]]]) -> None:
        """Set registers: (slave id, area, address, values) each."""
        self._call("set", [(s, a, addr, list(v)) for s, a, addr, v in writes])

    def flip(self, ranges: Sequence[Range]) -> int:
        """Replace every mover by one :class:`FlipMover` per range; returns how many."""
        return int(self._call("flip", list(ranges)))

    def stats(self) -> dict[str, Any]:
        result: dict[str, Any] = self._call("stats")
        return result

    def set_faults(self, slave_id: int, **knobs: Any) -> None:
        """Set fault knobs of one slave (see :class:`edgemodbus.sim.Faults`)."""
        self._call("faults", (slave_id, knobs))

    def record_requests(self, on: bool = True) -> None:
        """Start (or stop) logging every request's arrival at the slave side."""
        self._call("record", on)

    def arrivals(self) -> list[Arrival]:
        """The requests logged since the last call: (``time.monotonic()`` when the request
        arrived, slave id, function code), oldest first."""
        return [(float(t), int(sid), int(fc)) for t, sid, fc in self._call("arrivals")]

    def close(self) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is not None:
            try:
                conn.send(("stop", None))
                conn.poll(10)
            except OSError:
                pass
            conn.close()
        if proc is not None:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
