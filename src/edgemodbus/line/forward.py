"""Forward mode on a line: one request PDU from a gateway's TCP master sent to a slave
through the line worker's queue, and the slave's reply PDU handed back.

The job runs on the worker like a write (:meth:`LineWorker.submit`: before the next
read, between two transactions of the engine), through :meth:`Link.transact`, so the
line's pacing (request interval, t3.5 silence), settle after a timeout and drain after
a bad frame are those of every request.  What the request may be and how a failure
maps to an exception code is :mod:`edgemodbus.protocol.forward`.

A forward's timeout counts from the moment it was asked for (:func:`forward_future`),
time in the queue included: the job sends it with what is left of it, or, when nothing
is left, fails at once without sending (:class:`QueuedTooLongError`); the returned
future carries its ``deadline``, by which the gateway's server answers 0B even while
the line is still busy with something else.  After a timeout the worker backs off
from that slave (:mod:`edgemodbus.line.jobs`).

A forwarded request's failure is the line's (its counters) and the TCP master's (the
exception it gets), never the device's: no poller sees it, so it does not count towards
``offlineAfterFailedCycles`` nor change the device's status; and a device that is
Offline still gets forwarded requests (the TCP master asked for that slave).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError

from ..errors import ModbusError, ModbusExceptionResponse, ModbusTimeoutError
from ..protocol.forward import check_request, read_reply, read_span
from ..protocol.limits import MAX_UNIT_ID
from .link import Link

#: Less than this left of a forward's timeout: not sent (no slave answers that fast).
MIN_LEFT = 0.005


class QueuedTooLongError(ModbusTimeoutError):
    """A forward's timeout ran out while it waited on the line's queue: not sent."""


class ForwardFuture(Future[bytes]):
    """A forward's future; ``deadline`` (``time.monotonic()``): when its timeout, counted
    from the request's arrival, runs out."""

    def __init__(self, deadline: float) -> None:
        super().__init__()
        self.deadline = deadline


#: ``submit(job, reads)``: the worker's queue; ``reads``: the job changes nothing on a slave
Submit = Callable[[Callable[[Link], bytes], bool], "Future[bytes]"]
#: ``cached(slave, function, address, quantity)``: values a fresh polled block holds, or None
Cached = Callable[[int, int, int, int], "list[int] | None"]


def forward_future(submit: Submit, slave: int, pdu: bytes, timeout: float,
                   cached: Cached | None = None) -> ForwardFuture:
    """Queue the forward of ``pdu`` to ``slave`` with ``submit`` (the line worker's) and
    return its future, which fails as soon as the transaction failed: a timeout is
    answered after ``timeout``, not after the settle that follows it on the line.
    Cancelling the future before the worker took the job leaves the line untouched.
    ``cached`` (read coalescing): asked on the worker first for a read's values.
    Raises as :func:`forward_job` does, before anything is queued."""
    arrived = time.monotonic()
    result = ForwardFuture(arrived + timeout)

    def early(exc: ModbusError) -> None:
        _resolve(result, None, exc)

    job = submit(forward_job(slave, pdu, timeout, early, cached, arrived),
                 read_span(pdu) is not None)
    job.add_done_callback(lambda done: _resolve(
        result, None if done.cancelled() or done.exception() else done.result(),
        None if done.cancelled() else done.exception()))
    result.add_done_callback(lambda mine: mine.cancelled() and job.cancel())
    return result


def _resolve(future: Future[bytes], value: bytes | None, exc: BaseException | None) -> None:
    """Set ``future`` once (the first of the early failure and the job's end wins)."""
    if future.done():
        return
    try:
        if exc is not None:
            future.set_exception(exc)
        elif value is not None:
            future.set_result(value)
        else:
            future.cancel()
    except InvalidStateError:  # cancelled by its owner meanwhile
        pass


def forward_job(slave: int, pdu: bytes, timeout: float,
                early: Callable[[ModbusError], None] | None = None,
                cached: Cached | None = None,
                arrived: float | None = None) -> Callable[[Link], bytes]:
    """The worker job forwarding ``pdu`` to ``slave``, whose reply must come within
    ``timeout`` seconds of ``arrived`` (``time.monotonic()``; None: of the job's start);
    ``early`` is told of a failure before the line is cleaned up.
    A read that ``cached`` answers is replied from those values, with no line traffic.
    Raises here, before anything is queued: a
    :class:`~edgemodbus.protocol.forward.ForwardRequestError` for a PDU that is not
    forwarded, a ``ValueError`` for slave 0 (a broadcast gets no reply to pass back) or
    an id above 255, or a timeout that is not a positive number of seconds."""
    pdu = bytes(pdu)
    check_request(pdu)
    if not 1 <= slave <= MAX_UNIT_ID:
        raise ValueError(f"forward to slave {slave}: must be 1..{MAX_UNIT_ID} (0, broadcast, "
                         "gets no reply and is not forwarded)")
    if not (math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"forward timeout {timeout!r}: must be a positive number of seconds")
    span = read_span(pdu) if cached is not None else None

    def job(link: Link) -> bytes:
        if cached is not None and span is not None:
            values = cached(slave, *span)
            if values is not None:
                link.stats.forward_coalesced += 1
                return read_reply(span[0], values)
        left = timeout if arrived is None else arrived + timeout - time.monotonic()
        if left < MIN_LEFT:
            link.stats.forwarded += 1
            link.stats.forward_timeouts += 1
            link.stats.forward_expired += 1
            raise QueuedTooLongError(
                f"forward to slave {slave}: its timeout of {timeout * 1000:.0f} ms ran out "
                "while it waited for the line; not sent")
        return forward_on(link, slave, pdu, left, early)

    return job


def forward_on(link: Link, slave: int, pdu: bytes, timeout: float,
               early: Callable[[ModbusError], None] | None = None) -> bytes:
    """Send a checked request PDU to ``slave`` on ``link`` (worker thread) and return the
    reply PDU: a normal reply, or an exception reply (``function | 0x80``, code) as the
    slave sent it.  Raises :class:`~edgemodbus.errors.ModbusTimeoutError` when no reply
    came within ``timeout``, :class:`~edgemodbus.errors.ProtocolError` (``CrcError``
    among them) for a reply that does not answer the request,
    :class:`~edgemodbus.errors.ModbusConnectionError` when the link failed; ``early``
    hears of these (once counted) before the line is settled or drained."""
    stats = link.stats
    stats.forwarded += 1
    told = False

    def failed(exc: ModbusError) -> None:
        nonlocal told
        if isinstance(exc, ModbusExceptionResponse) or told:
            return  # an exception reply is an answer, passed through below
        told = True
        if isinstance(exc, ModbusTimeoutError):
            stats.forward_timeouts += 1
        else:
            stats.forward_errors += 1
        if early is not None:
            early(exc)

    try:
        adu = link.transact(slave, pdu, timeout, failed)  # checked in C (csrc/emb_check.c)
    except ModbusExceptionResponse as exc:  # a valid reply: passed through unchanged
        stats.forward_exceptions += 1
        return bytes((pdu[0] | 0x80, exc.code))
    except ModbusError as exc:  # also one before the request went out (link down)
        failed(exc)
        raise
    return link.reply_pdu(adu)
