"""Counters: what a line's worker counts (:class:`LineStats`), reported by the driver's
stats and the metrics exporter."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class LineStats:
    """Counters of one line, updated by its worker only."""

    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    protocol_errors: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)
    link_errors: int = 0
    connects: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    discarded_bytes: int = 0
    heartbeats: int = 0  # DTU heartbeat packets discarded
    reports: int = 0  # wrapped report frames received unsolicited
    dropped_frames: int = 0  # wrapped frames dropped (bad header, tail, CRC, length)
    rtt_total: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "requests": self.requests,
            "responses": self.responses,
            "timeouts": self.timeouts,
            "crcErrors": self.crc_errors,
            "protocolErrors": self.protocol_errors,
            "exceptions": dict(self.exceptions),
            "linkErrors": self.link_errors,
            "connects": self.connects,
            "reconnects": self.reconnects,
            "connectFailures": self.connect_failures,
            "discardedBytes": self.discarded_bytes,
            "heartbeats": self.heartbeats,
            "reports": self.reports,
            "droppedFrames": self.dropped_frames,
            "avgRoundTrip": self.rtt_total / self.responses if self.responses else 0.0,
        }
