"""The per-device counters behind ``DriverModbusRtu.stats()``, with the cycle-time
histogram the Prometheus exporter reads."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

# upper bounds (seconds) of the cycle-time histogram behind the Prometheus exporter
CYCLE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


def _histogram(bounds: tuple[float, ...], counts: list[int], total: float) -> dict[str, Any]:
    """Cumulative buckets, Prometheus style: [[le, count <= le], ..., ["+Inf", all]]."""
    buckets: list[list[Any]] = []
    running = 0
    for le, n in zip((*bounds, "+Inf"), counts, strict=True):
        running += n
        buckets.append([le, running])
    return {"buckets": buckets, "sum": total, "count": running}


@dataclass
class Counters:
    """Per-device counters behind ``DriverModbusRtu.stats()``."""

    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)
    retries: int = 0
    cycles: int = 0
    failed_cycles: int = 0
    overruns: int = 0
    skipped_blocks: int = 0
    last_cycle_time: float = 0.0
    total_cycle_time: float = 0.0
    max_cycle_time: float = 0.0
    cycle_hist: list[int] = field(default_factory=lambda: [0] * (len(CYCLE_BUCKETS) + 1))
    callback_errors: int = 0
    callback_time: float = 0.0
    values_changed: int = 0
    writes: int = 0
    write_errors: int = 0
    reports: int = 0  # wrapped reports applied to this device

    def as_dict(self) -> dict[str, Any]:
        return {
            "requests": self.requests,
            "responses": self.responses,
            "timeouts": self.timeouts,
            "crcErrors": self.crc_errors,
            "protocolErrors": self.protocol_errors,
            "exceptions": dict(self.exceptions),
            "retries": self.retries,
            "cycles": self.cycles,
            "failedCycles": self.failed_cycles,
            "overruns": self.overruns,
            "skippedBlocks": self.skipped_blocks,
            "lastCycleTime": self.last_cycle_time,
            "avgCycleTime": self.total_cycle_time / self.cycles if self.cycles else 0.0,
            "maxCycleTime": self.max_cycle_time,
            "cycleTimeHistogram": _histogram(CYCLE_BUCKETS, self.cycle_hist,
                                             self.total_cycle_time),
            "callbackErrors": self.callback_errors,
            "callbackTime": self.callback_time,
            "valuesChanged": self.values_changed,
            "writes": self.writes,
            "writeErrors": self.write_errors,
            "reports": self.reports,
        }
