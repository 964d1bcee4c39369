"""How other threads interrupt a line's engine (csrc/emb_engine.c): the waker, a flag and
an eventfd."""

from __future__ import annotations

import contextlib
import os
import weakref

from .native import ffi


class Waker:
    """How other threads interrupt a line's engine: a flag the engine reads between two
    transactions and an eventfd it polls while it waits."""

    def __init__(self) -> None:
        self._flag = ffi.new("int *")
        self.fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._close = weakref.finalize(self, os.close, self.fd)

    def signal(self) -> None:
        """Any thread: a job is queued."""
        self._flag[0] = 1
        if self._close.alive:
            os.eventfd_write(self.fd, 1)

    def clear(self) -> None:
        """The worker, before it takes the queued jobs."""
        self._flag[0] = 0
        with contextlib.suppress(BlockingIOError):
            os.eventfd_read(self.fd)

    @property
    def is_open(self) -> bool:
        return self._close.alive

    def close(self) -> None:
        self._close()
