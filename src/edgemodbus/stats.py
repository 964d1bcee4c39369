"""Counters: what a line's worker counts (:class:`LineStats`) and what a slave's poller
counts (:class:`DeviceStats`), both read by ``DriverModbusRtu.stats()`` and the Prometheus
exporter.  The request counters they share are defined once (:class:`RequestStats`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

# upper bounds (seconds) of the cycle-time histogram behind the Prometheus exporter
CYCLE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


def histogram(bounds: tuple[float, ...], counts: list[int], total: float) -> dict[str, Any]:
    """Cumulative buckets, Prometheus style: [[le, count <= le], ..., ["+Inf", all]]."""
    buckets: list[list[Any]] = []
    running = 0
    for le, n in zip((*bounds, "+Inf"), counts, strict=True):
        running += n
        buckets.append([le, running])
    return {"buckets": buckets, "sum": total, "count": running}


class NativeCounts(NamedTuple):
    """What the line engine counts in C (csrc/emb_engine.h), read live: the engine's
    thread is the only writer, so another thread reads them without stopping it."""

    requests: int = 0
    responses: int = 0
    rtt_total: float = 0.0  # lines
    discarded_bytes: int = 0  # lines
    heartbeats: int = 0  # lines (DTU streams)
    cycles: int = 0  # devices, from here on
    overruns: int = 0
    last_cycle_time: float = 0.0
    total_cycle_time: float = 0.0
    max_cycle_time: float = 0.0
    cycle_hist: tuple[int, ...] = (0,) * (len(CYCLE_BUCKETS) + 1)
    # how requests failed, counted once by the engine's fault policy (csrc/emb_fault.c)
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: tuple[tuple[int, int], ...] = ()  # (code, count)
    exceptions_other: int = 0  # codes past the engine's EMB_EXC_SLOTS distinct ones
    retries: int = 0  # devices
    failed_cycles: int = 0
    skipped_blocks: int = 0
    reports: int = 0  # wrapped reports applied in C (csrc/emb_report.c): lines, devices


def _no_counts() -> NativeCounts:
    return _NONE


_NONE = NativeCounts()


@dataclass(slots=True)
class RequestStats:
    """How requests ended: the counters a line and a device both keep."""

    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)  # by exception code
    reports: int = 0  # wrapped reports (line: received unsolicited; device: applied)
    # the engine's counters, added to the Python ones above (requests, responses)
    native: Callable[[], NativeCounts] = field(default=_no_counts, repr=False, compare=False)

    def as_dict(self) -> dict[str, Any]:
        native = self.native()
        exceptions = dict(self.exceptions)
        for code, n in native.exceptions:
            exceptions[code] = exceptions.get(code, 0) + n
        return {
            "requests": self.requests + native.requests,
            "responses": self.responses + native.responses,
            "timeouts": self.timeouts + native.timeouts,
            "crcErrors": self.crc_errors + native.crc_errors,
            "protocolErrors": self.protocol_errors + native.protocol_errors,
            "exceptions": exceptions,
            # exception responses whose code the engine could not count apart: it keeps
            # the first 8 distinct codes (csrc/emb_edev.h emb_exc_counts)
            "exceptionsOther": native.exceptions_other,
            "reports": self.reports + native.reports,
        }


@dataclass(slots=True)
class LineStats(RequestStats):
    """Counters of one line, updated by its worker only."""

    link_errors: int = 0
    connects: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    discarded_bytes: int = 0
    heartbeats: int = 0  # DTU heartbeat packets discarded
    dropped_frames: int = 0  # wrapped frames dropped (bad header, tail, CRC, length)
    rtt_total: float = 0.0
    # gateway forward mode (line/forward.py): requests forwarded, and how many of them
    # timed out, got an exception reply (passed through), or failed otherwise (a bad
    # reply, the link lost); they count in the counters above too, as every request.
    # Reads answered by coalescing never reach the line and count only in the last one.
    forwarded: int = 0
    forward_timeouts: int = 0
    forward_exceptions: int = 0
    forward_errors: int = 0
    forward_coalesced: int = 0  # forwarded reads answered from a fresh polled block
    forward_expired: int = 0  # timed out while queued: not sent (in forwardTimeouts too)
    # line scheduling (line/jobs.py): queued jobs run, those run while polling was due,
    # those run when polling was already late by more than its scan rate, jobs refused
    # (too many waiting), requests failed at once by a target's backoff, and unexpected
    # errors the worker recovered from
    jobs: int = 0
    jobs_ahead_of_polls: int = 0
    polls_delayed: int = 0
    jobs_refused: int = 0
    target_backoffs: int = 0
    worker_errors: int = 0
    # backup endpoints (line/failover.py): moves to the next endpoint, moves back to the
    # primary, and the endpoint in use ("" on a line without alternates)
    failovers: int = 0
    failbacks: int = 0
    active_endpoint: str = ""
    # MQTT DTUs (line/mqtt_dtu.py): uplink messages taken, and bytes of them lost (the
    # link's stream full, or no link: the DTU sent while its line was down)
    uplink_messages: int = 0
    uplink_dropped_bytes: int = 0

    def as_dict(self) -> dict[str, Any]:
        native = self.native()
        responses = self.responses + native.responses
        rtt = self.rtt_total + native.rtt_total
        return {
            **RequestStats.as_dict(self),  # (no zero-argument super in a slots dataclass)
            "linkErrors": self.link_errors,
            "connects": self.connects,
            "reconnects": self.reconnects,
            "connectFailures": self.connect_failures,
            "discardedBytes": self.discarded_bytes + native.discarded_bytes,
            "heartbeats": self.heartbeats + native.heartbeats,
            "droppedFrames": self.dropped_frames,
            "avgRoundTrip": rtt / responses if responses else 0.0,
            "forwarded": self.forwarded,
            "forwardTimeouts": self.forward_timeouts,
            "forwardExceptions": self.forward_exceptions,
            "forwardErrors": self.forward_errors,
            "forwardCoalesced": self.forward_coalesced,
            "forwardExpired": self.forward_expired,
            "jobs": self.jobs,
            "jobsAheadOfPolls": self.jobs_ahead_of_polls,
            "pollsDelayed": self.polls_delayed,
            "jobsRefused": self.jobs_refused,
            "targetBackoffs": self.target_backoffs,
            "workerErrors": self.worker_errors,
            "failovers": self.failovers,
            "failbacks": self.failbacks,
            "activeEndpoint": self.active_endpoint,
            "uplinkMessages": self.uplink_messages,
            "uplinkDroppedBytes": self.uplink_dropped_bytes,
        }


@dataclass(slots=True)
class DeviceStats(RequestStats):
    """Counters of one device (a slave's poller), updated on its line's worker."""

    callback_errors: int = 0
    callback_time: float = 0.0
    values_changed: int = 0
    writes: int = 0
    write_errors: int = 0
    reads_coalesced: int = 0  # reads on demand that joined a waiting one (poll/on_demand.py)

    def as_dict(self) -> dict[str, Any]:
        """The counters; cycles, their times, retries, failed cycles and skipped blocks
        are the engine's alone (the fault policy runs in C)."""
        c = self.native()
        return {
            **RequestStats.as_dict(self),  # (no zero-argument super in a slots dataclass)
            "retries": c.retries,
            "cycles": c.cycles,
            "failedCycles": c.failed_cycles,
            "overruns": c.overruns,
            "skippedBlocks": c.skipped_blocks,
            "lastCycleTime": c.last_cycle_time,
            "avgCycleTime": c.total_cycle_time / c.cycles if c.cycles else 0.0,
            "maxCycleTime": c.max_cycle_time,
            "cycleTimeHistogram": histogram(CYCLE_BUCKETS, list(c.cycle_hist),
                                            c.total_cycle_time),
            "callbackErrors": self.callback_errors,
            "callbackTime": self.callback_time,
            "valuesChanged": self.values_changed,
            "writes": self.writes,
            "writeErrors": self.write_errors,
            "readsCoalesced": self.reads_coalesced,
        }
