"""What the line engine's fault policy (csrc/emb_fault.c) hands Python: a block's
failure, the status changes, the counters of a line; and how it cleans the line."""

from __future__ import annotations

from typing import Any, NamedTuple

from ..stats import NativeCounts
from .native import ffi, lib

FAIL_OWN: int = lib.EMB_FAIL_OWN  # the block's own read failed
FAIL_SILENT: int = lib.EMB_FAIL_SILENT  # the slave did not answer (this block or before)
ST_BACK: int = lib.EMB_ST_BACK  # the slave answers (again)
ST_OFFLINE: int = lib.EMB_ST_OFFLINE  # the slave went offline
ST_AGAIN: int = lib.EMB_ST_AGAIN  # with ST_BACK: it had been offline


class Clean(NamedTuple):
    """How the engine cleans the line after a failed read (seconds): settle after a
    timeout (0: not at all) up to ``settle_limit``; a stray frame ends after ``quiet``;
    drain the rest of a bad frame up to ``drain_limit``."""

    settle: float
    settle_limit: float
    quiet: float
    drain_limit: float


class Failure(NamedTuple):
    """A block's failure as the engine left it (csrc/emb_fault.c): ``kind`` FAIL_OWN (its
    own read failed with ``errno``) or FAIL_SILENT (the slave did not answer the read of
    ``function``/``start``/``size``); ``reply``: the rejected reply's first bytes,
    ``length`` its length, ``header`` its header size (1, or 7 for MBAP)."""

    block: int
    kind: int
    errno: int
    function: int
    start: int
    size: int
    reply: bytes
    length: int
    header: int


def exception_counts(counts: Any) -> tuple[tuple[int, int], ...]:
    """(code, count) of the exception codes counted apart (an ``emb_exc_counts``), in
    order of code."""
    return tuple(sorted((counts.code[i], counts.n[i]) for i in range(lib.EMB_EXC_SLOTS)
                        if counts.n[i]))


class LineCounters:
    """A line's request counters (``emb_line_counters``), kept by the engines of its
    successive links."""

    def __init__(self) -> None:
        self._lc = ffi.new("emb_line_counters *")

    def counts(self) -> NativeCounts:
        """Read live (any thread)."""
        lc = self._lc
        return NativeCounts(requests=lc.requests, responses=lc.responses,
                            rtt_total=lc.rtt_ns / 1e9, discarded_bytes=lc.discarded,
                            heartbeats=lc.heartbeats, timeouts=lc.timeouts,
                            crc_errors=lc.crc_errors, protocol_errors=lc.protocol_errors,
                            exceptions=exception_counts(lc.exceptions),
                            exceptions_other=lc.exceptions.other, reports=lc.reports)
