"""What a loop link's run hands to its pollers (line/loop.py ``LoopWorker._step``), as
the line worker hands the blocking engine's events (line/worker.py ``_dispatch``): the
passes that ended, a split, a wrapped link's reports, a failure.  A poller's error is
logged and costs the other pollers nothing."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

from .._ffi.engine import Engine
from ..errors import ModbusConnectionError
from .link import ContextLink
from .poller_api import Poller

log = logging.getLogger("edgemodbus.line")


def hand_ended(engine: Engine, pollers: Sequence[Poller], where: str) -> None:
    """The passes that ended, each to its poller."""
    for ended in engine.take_ended():
        try:
            pollers[ended].engine_cycle()
        except Exception:
            log.exception("%s: poller failed", where)


def hand_split(pollers: Sequence[Poller], which: int, where: str) -> None:
    """Exception 02 on a splittable block of device ``which``."""
    try:
        pollers[which].engine_split()
    except Exception:
        log.exception("%s: poller failed", where)


def hand_reports(link: ContextLink, pollers: Sequence[Poller], which: int,
                 where: str) -> None:
    """A wrapped link took reports: those that came before the reply, then the reply's
    results (device ``which``, -1: taken while idle), then the rest."""
    link.collect()
    if 0 <= which < len(pollers):
        try:
            pollers[which].take_results()
        except Exception:
            log.exception("%s: poller failed", where)
    link.flush_reports()


def hand_failure(link: ContextLink, pollers: Sequence[Poller], which: int, err: int,
                 where: str) -> None:
    """The link failed (``err``) in a transaction of device ``which``: its poller
    hears it; the link's close reason says why (the caller closes it)."""
    link.collect()
    try:
        if 0 <= which < len(pollers):
            pollers[which].engine_failed(link, err)
    except ModbusConnectionError:
        pass
    except Exception:
        log.exception("%s: poller failed", where)
    if link.is_open:
        link.close_reason = f"link failed: {os.strerror(err)}"


__all__ = ["hand_ended", "hand_failure", "hand_reports", "hand_split"]
