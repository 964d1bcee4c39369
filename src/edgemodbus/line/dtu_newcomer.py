"""A connection at the DTU listener that has not registered yet (:class:`Newcomer`), the
listener's counters and the constants of its loop (:mod:`.dtu_listener`)."""

from __future__ import annotations

import math
import socket
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field

from .admission import ByteBudget
from .dtu_slot import DtuSlot

ACCEPT_BATCH = 64
"""Connections accepted per turn of the loop, so that registrations are read between
accepts when thousands of DTUs dial in at once (the caps count waiting connections)."""

EVICT_SCAN = 32
"""Oldest waiting connections looked at for one to evict when the port is full."""

BUDGET_BURST = 64
"""Bytes a newcomer may send at once before ``registrationByteRate`` applies."""

RESET = struct.pack("ii", 1, 0)  # SO_LINGER on, 0 s: close with RST, no TIME_WAIT here

COUNTERS = ("accepted", "registered", "unknown", "silent", "oversize", "evicted",
            "refusedPortCap",
            "refusedSourceCap", "refusedNotAllowed", "refusedDtuNotAllowed", "badKey",
            "duplicateRefused", "replaced", "contested", "refusedContested", "acceptErrors",
            "acceptPauses", "proxyNotAllowed", "proxyMissing", "proxyMalformed",
            "proxyLocal")


@dataclass(eq=False)
class Newcomer:
    """One connection waiting to register: its socket, addresses, deadlines, bytes."""

    sock: socket.socket
    peer: str
    source: str  # the peer's address without the port (the DTU's, behind a balancer)
    deadline: float
    budget: ByteBudget
    since: float  # accepted at (monotonic)
    buf: bytearray = field(default_factory=bytearray)
    quiet_at: float = math.inf  # when to look at the registration again if no byte comes
    resume_at: float = math.inf  # reading paused (byte rate) until then
    held: bool = False  # refused: kept unread until the deadline, then closed
    waiting: bool = True  # counted against the caps on connections waiting to register
    challenge: tuple[DtuSlot, bytes, int] | None = None  # keep-existing: slot, rest, answers
    proxied: bool = False  # from a load balancer, its PROXY v2 header not read yet

    def wake(self) -> float:
        return min(self.deadline, self.quiet_at, self.resume_at)


def evictable(newcomers: Iterable[Newcomer], idle_since: float) -> Newcomer | None:
    """Among the oldest :data:`EVICT_SCAN` newcomers, the first held as refused or silent
    since before ``idle_since`` (never a challenger), or None."""
    for k, newcomer in enumerate(newcomers):
        if k == EVICT_SCAN:
            break
        if newcomer.challenge is None and (
                newcomer.held or (not newcomer.buf and newcomer.since <= idle_since)):
            return newcomer
    return None


__all__ = ["ACCEPT_BATCH", "BUDGET_BURST", "COUNTERS", "EVICT_SCAN", "RESET", "Newcomer",
           "evictable"]
