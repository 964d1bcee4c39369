"""Forward mode on a line: one request PDU from a gateway's TCP master sent to a slave
through the line worker's queue, and the slave's reply PDU handed back.

The job runs on the worker like a write (:meth:`LineWorker.submit`: before the next
read, between two transactions of the engine), through :meth:`Link.transact`, so the
line's pacing (request interval, t3.5 silence), settle after a timeout and drain after
a bad frame are those of every request.  What the request may be and how a failure
maps to an exception code is :mod:`edgemodbus.protocol.forward`.

A forwarded request's failure is the line's (its counters) and the TCP master's (the
exception it gets), never the device's: no poller sees it, so it does not count towards
``offlineAfterFailedCycles`` nor change the device's status; and a device that is
Offline still gets forwarded requests (the TCP master asked for that slave).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ..errors import ModbusError, ModbusExceptionResponse, ModbusTimeoutError
from ..protocol.forward import check_reply, check_request
from .link import Link


def forward_job(slave: int, pdu: bytes, timeout: float) -> Callable[[Link], bytes]:
    """The worker job forwarding ``pdu`` to ``slave``, whose reply must come within
    ``timeout`` seconds.  Raises here, before anything is queued: a
    :class:`~edgemodbus.protocol.forward.ForwardRequestError` for a PDU that is not
    forwarded, a ``ValueError`` for slave 0 (a broadcast gets no reply to pass back) or
    an id above 255, or a timeout that is not a positive number of seconds."""
    pdu = bytes(pdu)
    check_request(pdu)
    if not 1 <= slave <= 255:
        raise ValueError(f"forward to slave {slave}: must be 1..255 (0, broadcast, gets no "
                         "reply and is not forwarded)")
    if not (math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"forward timeout {timeout!r}: must be a positive number of seconds")
    return lambda link: forward_on(link, slave, pdu, timeout)


def forward_on(link: Link, slave: int, pdu: bytes, timeout: float) -> bytes:
    """Send a checked request PDU to ``slave`` on ``link`` (worker thread) and return the
    reply PDU: a normal reply, or an exception reply (``function | 0x80``, code) as the
    slave sent it.  Raises :class:`~edgemodbus.errors.ModbusTimeoutError` when no reply
    came within ``timeout``, :class:`~edgemodbus.errors.ProtocolError` (``CrcError``
    among them) for a reply that does not answer the request,
    :class:`~edgemodbus.errors.ModbusConnectionError` when the link failed."""
    stats = link.stats
    stats.forwarded += 1
    try:
        adu = link.transact(slave, pdu, lambda _s, request, reply: check_reply(
            request, link.reply_pdu(reply)), timeout)
    except ModbusExceptionResponse as exc:  # a valid reply: passed through unchanged
        stats.forward_exceptions += 1
        return bytes((pdu[0] | 0x80, exc.code))
    except ModbusTimeoutError:
        stats.forward_timeouts += 1
        raise
    except ModbusError:
        stats.forward_errors += 1
        raise
    return link.reply_pdu(adu)
