"""Reads on demand from Sparkplug commands (docs/reporting.md): a DCMD with
``Device Control/Read`` = true reads every item of that device now (a String value: the
item it names, as born), an NCMD with
``Node Control/Read`` = true every attached device (Sparkplug B 3.0 leaves custom
control metrics to the edge node; the node declares ``Node Control/Read`` in its NBIRTH
beside ``Node Control/Rebirth``).  Each read is ``driver.read_now()``: a job on the
device's line, its values reported as any report, so they go out in DDATA.  The line
bounds the reads waiting (64 jobs; one more fails at once): each refused or failed read
is counted (``readsRefused``) and logged through the publisher's rate limiter."""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from ...errors import ModbusError
from .devices import NodeDevice
from .inbox import CommandLog, short_reason


class ReadRunner:
    """Starts reads on demand (any thread: read_now only queues a job); ``count(key)``
    counts ``reads`` (started) and ``readsRefused``."""

    def __init__(self, count: Callable[[str], None], logs: CommandLog) -> None:
        self._count = count
        self._logs = logs

    def read(self, dev: NodeDevice, names: list[str] | None = None) -> None:
        """Read ``names`` of ``dev`` (None: every item) now."""
        try:
            future = dev.driver.read_now(names)
        except (ModbusError, KeyError) as exc:  # not running; an item gone since the birth
            self._refused(dev.code, str(exc))
            return
        self._count("reads")
        future.add_done_callback(lambda done: self._done(dev.code, done))

    def _done(self, code: str, future: Future[Any]) -> None:
        if future.cancelled():
            self._refused(code, "cancelled")
        elif future.exception() is not None:
            self._refused(code, str(future.exception()))

    def _refused(self, code: str, reason: str) -> None:
        self._count("readsRefused")
        self._logs.event(logging.WARNING, "reads refused", code, "%s: read on demand "
                         "refused: %s", code, short_reason(reason))
