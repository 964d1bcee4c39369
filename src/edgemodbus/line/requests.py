"""The request helpers of a line worker (reads, writes, forwarded requests), each a job
on its queue (:meth:`LineWorker.submit`), kept apart for size."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import TypeVar

from ..datatypes import Area
from .endpoint import LineTiming
from .forward import forward_future
from .link import Link
from .poller_api import Poller

T = TypeVar("T")


class LineRequests:
    """Mixed into :class:`~edgemodbus.line.worker.LineWorker`: what other threads ask of
    the line, through its :meth:`submit`."""

    __slots__ = ()

    timing: LineTiming
    _pollers: list[Poller]
    _changed: float  # monotonic end of the last job that may have written a slave

    def submit(self, fn: Callable[[Link], T], reads: bool = False,
               slave: int | None = None) -> Future[T]:
        raise NotImplementedError

    def read(self, slave: int, area: Area, address: int, count: int) -> Future[list[int]]:
        """Read registers (ints) or bits (0/1 ints) from one slave."""
        return self.submit(lambda link: link.read(slave, area, address, count).to_list(),
                           reads=True)

    def write_coil(self, slave: int, address: int, value: bool) -> Future[None]:
        return self.submit(lambda link: link.write_coil(slave, address, value))

    def write_register(self, slave: int, address: int, value: int) -> Future[None]:
        return self.submit(lambda link: link.write_register(slave, address, value))

    def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> Future[None]:
        values = list(values)
        return self.submit(lambda link: link.write_coils(slave, address, values))

    def write_registers(self, slave: int, address: int, values: Sequence[int]) -> Future[None]:
        values = list(values)
        return self.submit(lambda link: link.write_registers(slave, address, values))

    def mask_write_register(self, slave: int, address: int, and_mask: int,
                            or_mask: int) -> Future[None]:
        return self.submit(lambda link: link.mask_write_register(slave, address, and_mask,
                                                                 or_mask))

    def forward(self, slave: int, pdu: bytes, timeout: float | None = None) -> Future[bytes]:
        """Forward a request PDU to ``slave`` like a write; the future's result is the
        reply PDU, its failure comes before the line's settle (see
        :mod:`edgemodbus.line.forward`, which raises here for a PDU that is not
        forwarded).  ``timeout``: default the line's response timeout."""
        wait = self.timing.response_timeout if timeout is None else timeout
        return forward_future(self._submit_forward(slave), slave, pdu, wait, self._cached)

    def _submit_forward(self, slave: int) -> Callable[[Callable[[Link], bytes], bool],
                                                       Future[bytes]]:
        def submit(fn: Callable[[Link], bytes], reads: bool) -> Future[bytes]:
            return self.submit(fn, reads, slave)
        return submit

    def _cached(self, slave: int, function: int, address: int, count: int) -> list[int] | None:
        """Read coalescing (worker thread): the values a block of a device polling
        ``slave`` read since the last job that may have written, within that device's
        ``forwardCoalesce`` age; None if no such block covers the span."""
        for poller in self._pollers:
            device = poller.device
            if device.slave == slave:
                values = device.cached(function, address, count, self._changed)
                if values is not None:
                    return values
        return None
