"""Accepting at the fd limit without spinning: when accept() fails for want of fds,
buffers or memory, a listening socket is left out of the poll for a while (50 ms,
doubling to 2 s) and the pending connections wait in the kernel's backlog.  A loop that
polled the socket again at once would wake for the same failure thousands of times a
second.  The DTU listener and the metrics exporter share this; the Modbus TCP server does
the same in C (csrc/emb_serve.c)."""

from __future__ import annotations

import errno
import math

__all__ = ["ACCEPT_ERRORS", "MAX_ACCEPT_PAUSE", "MIN_ACCEPT_PAUSE", "AcceptPause"]

ACCEPT_ERRORS = frozenset((errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM))
"""accept() errors that a moment's wait can cure (anything else is logged and skipped)."""

MIN_ACCEPT_PAUSE = 0.05
MAX_ACCEPT_PAUSE = 2.0
"""Seconds accepting pauses after an accept error (doubling from the first)."""


class AcceptPause:
    """The pause of one listening socket: ``until`` (monotonic seconds; inf while it is
    not paused) and the length of the last pause, which doubles on each failure in a
    row and starts again after an accept that worked."""

    __slots__ = ("pause", "until")

    def __init__(self) -> None:
        self.pause = 0.0
        self.until = math.inf

    def failed(self, now: float) -> float:
        """An accept failed with one of :data:`ACCEPT_ERRORS`: pause (the caller stops
        polling the socket); returns the pause in seconds."""
        self.pause = min(MAX_ACCEPT_PAUSE, max(MIN_ACCEPT_PAUSE, self.pause * 2))
        self.until = now + self.pause
        return self.pause

    def accepted(self) -> None:
        """An accept worked: the next failure pauses the shortest time again."""
        self.pause = 0.0

    def over(self, now: float) -> bool:
        """True once, when a pause has ended (the caller polls the socket again)."""
        if now < self.until:
            return False
        self.until = math.inf
        return True
