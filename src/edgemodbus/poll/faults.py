"""What the engine's fault policy decided, in the words and states of a poller.

The policy itself runs in C beside the read (csrc/emb_fault.c), configured once per
device (:meth:`EngineDevice.set_policy`): retries of timeouts and CRC errors, settling
and draining the line, the end of a slave's cycle on a timeout ("device not
responding"), offline after ``offlineAfterFailedCycles`` failed cycles with a probe per
backoff interval (doubling from readCycle up to maxBackoff), exception 02 bisection.
The engine tells the poller its outcomes; this module words them: a failed block's
reason (:func:`reason_of`, the same text a failed read raises) and a status change
(:func:`status_change`).
"""

from __future__ import annotations

from typing import NamedTuple

from .._ffi.context import read_error_of
from .._ffi.engine import EngineDevice
from .._ffi.outcomes import FAIL_SILENT, ST_AGAIN, ST_BACK, ST_OFFLINE, Failure
from ..datatypes import DeviceDriverStatus


def reason_of(failure: Failure, slave: int) -> str:
    """The reason a failed block's items are Invalid with: the error of its own read,
    or "device not responding: ..." with the timeout that ended the slave's cycle."""
    f = failure
    error = read_error_of(f.errno, slave, f.function, f.start, f.size, f.reply, f.length,
                          f.header)
    if f.kind == FAIL_SILENT:
        return f"device not responding: {error}"
    return str(error)


class StatusChange(NamedTuple):
    """A status the engine moved the slave to, with its reason and what to log."""

    status: DeviceDriverStatus
    reason: str | None
    log: str | None  # a line for the device's log (INFO back online, WARNING offline)


def status_change(device: EngineDevice, events: int, code: str) -> list[StatusChange]:
    """The status changes of ``events`` (:meth:`EngineDevice.take_status`), in the order
    they happened: back online (it answered) before offline (a pass's end)."""
    out: list[StatusChange] = []
    slave = device.slave
    if events & ST_BACK:
        again = f"{code}: slave {slave} answers again" if events & ST_AGAIN else None
        out.append(StatusChange(DeviceDriverStatus.RUNNING, None, again))
    if events & ST_OFFLINE:
        n = device.failed_cycles
        out.append(StatusChange(
            DeviceDriverStatus.OFFLINE, f"offline after {n} failed cycles",
            f"{code}: slave {slave} offline after {n} failed cycles; probing every "
            f"{device.backoff:.3g} s and backing off"))
    return out
