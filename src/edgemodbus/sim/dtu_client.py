"""The DTU side of the simulator: a handle on one of its TCP connections (one it dialled
out, as a 4G/Ethernet DTU does, or one it accepted) to push reports and misbehave on, and
the edge MCU's wrapped framing::

    FF AA | register address (2 bytes, big-endian) | RTU frame with its CRC | 0D
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Protocol

from ..datatypes import Area
from ..protocol import rtu
from .actions import _Reset
from .line import _Line
from .slave import Slave

_WRAP_HEADER = b"\xff\xaa"


def _wrap(address: int, frame: bytes) -> bytes:
    """An edge MCU's wrapped frame: FF AA, register address (big-endian), RTU frame, 0D."""
    return _WRAP_HEADER + struct.pack(">H", address & 0xFFFF) + frame + b"\x0d"


class _Host(Protocol):
    """What a :class:`DtuClient` uses of its simulator (server.Simulator, which imports
    this module)."""

    def slave(self, slave_id: int) -> Slave: ...

    def _call(self, fn: Callable[[], None]) -> None: ...

    def _act(self, line: _Line, data: bytes | _Reset | None) -> None: ...

    def _close_line(self, line: _Line) -> None: ...


class DtuClient:
    """One dialled-in DTU connection of a :class:`Simulator` (see :meth:`Simulator.dial`)."""

    def __init__(self, sim: _Host, line: _Line) -> None:
        self._sim = sim
        self._line = line

    @property
    def closed(self) -> bool:
        return self._line.closed

    @property
    def heartbeats_sent(self) -> int:
        return self._line.heartbeats_sent

    def send(self, data: bytes) -> None:
        """Put raw bytes on the connection (heartbeats, garbage, hand-made frames)."""
        self._sim._call(lambda: self._sim._act(self._line, bytes(data)))

    def push_report(self, slave: int, area: Area, address: int, count: int) -> bytes:
        """Send an unsolicited wrapped report of ``count`` registers (or bits) of
        ``slave`` from ``address``, with the values the slave holds now; returns it."""
        target = self._sim.slave(slave)
        pdu = struct.pack(">BHH", area.read_function, address, count)
        out: list[bytes] = []

        def push() -> None:
            rpdu = target._execute(pdu)
            frame = _wrap(address, rtu.frame(slave, rpdu))
            out.append(frame)
            self._sim._act(self._line, frame)

        self._sim._call(push)
        return out[0]

    def close(self) -> None:
        """The DTU drops its connection."""
        self._sim._call(lambda: self._sim._close_line(self._line))
