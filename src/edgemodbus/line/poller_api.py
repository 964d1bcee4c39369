"""What a line worker runs: the :class:`Poller` protocol, the driver's device polling
as the worker sees it (poll/poller.py implements it)."""

from __future__ import annotations

from typing import Protocol

from .._ffi.engine import EngineDevice
from .link import Link


class Poller(Protocol):
    """What the line worker runs: the driver's device polling.  The link's engine runs
    the passes over :attr:`device` and the worker calls the poller only for what needs
    Python."""

    device: EngineDevice
    """The poller's plan and schedule as the engine runs them."""

    @property
    def due(self) -> float:
        """``time.monotonic()`` of the next step (read by the worker on every step)."""
        ...

    def engine_cycle(self) -> None:
        """The engine ended a pass of this poller that Python must see (listed by the
        engine: :meth:`Link.take_ended`)."""
        ...

    def engine_failed(self, link: Link, err: int) -> None:
        """The link failed (errno ``err``) on a read of the engine's pass."""
        ...

    def engine_split(self) -> None:
        """Exception 02 on the pass's next block, which the poller may split."""
        ...

    def take_results(self) -> None:
        """Store the results of the blocks the engine read so far in this pass."""
        ...


    def link_changed(self, up: bool, reason: str | None, offline: bool = False) -> None:
        """The line went up or down (called on the worker thread); ``offline``: down
        because the line's worker failed (an unexpected error, LineWorker._recover), not
        its link: the device is Offline with ``reason`` until the line is back, rather
        than Reconnecting."""
        ...
