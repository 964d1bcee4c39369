"""Writes from DCMD messages: one ``edgemodbus-sparkplug-cmd`` thread with an asyncio loop
runs them through ``write_addresses_async`` (many devices' writes in flight at once, each
device's in arrival order).  A confirmed write changes the item, so the driver reports it
and the new value goes out in DDATA; a refused one is counted.  Both are logged through
the publisher's rate limiter (inbox.py), naming at most a few short items."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Any

from ...datatypes import DataType
from ...line.log_limit import short_text
from ..loop_thread import LoopThread
from .commands import CommandMetric, command_value
from .devices import NodeDevice
from .inbox import CommandLog, short_reason
from .payloads import DATETIME

log = logging.getLogger("edgemodbus.sparkplug")

MAX_PENDING_WRITES = 256
_NAMED = 3  # items a log line names


def describe(items: list[tuple[str, Any]]) -> str:
    """``name=value`` of the first few items (a long name or text cut short: they come
    from the broker) and how many more."""
    def one(name: str, value: Any) -> str:
        shown = short_text(value) if isinstance(value, str) else repr(value)[:40]
        return f"{name if len(name) <= 32 else short_text(name)}={shown}"

    text = ", ".join(one(name, value) for name, value in items[:_NAMED])
    return text if len(items) <= _NAMED else f"{text} (+{len(items) - _NAMED} more)"


class WriteRunner:
    """The write thread; ``count(key)`` counts ``writes`` and ``writesRefused``."""

    def __init__(self, count: Callable[[str], None], logs: CommandLog) -> None:
        self._count = count
        self._logs = logs
        self._runner = LoopThread("edgemodbus-sparkplug-cmd")
        self._lock = threading.Lock()
        self.pending = 0

    def start(self) -> None:
        self._runner.start()

    def refused(self, code: str, what: str, reason: str) -> None:
        """A write refused before it reached the driver (unknown metric, no value...)."""
        self._count("writesRefused")
        self._logs.event(logging.WARNING, "DCMD writes refused", code,
                         "%s: DCMD write %s refused: %s", code, what, short_reason(reason))

    def command(self, dev: NodeDevice, metrics: list[CommandMetric]) -> None:
        """A DCMD's metrics for ``dev`` (by name or alias, as born) become one
        ``write_addresses``; one metric that cannot be written refuses the whole."""
        by_name, by_alias, kinds = dev.metrics, dev.by_alias, dev.kinds  # as born
        items: list[tuple[str, Any]] = []
        for metric in metrics:
            spec = (by_name.get(metric.name) if metric.name is not None
                    else by_alias.get(metric.alias) if metric.alias is not None else None)
            what = metric.label
            if spec is None:
                self.refused(dev.code, what, "no such metric in the device's DBIRTH")
                return
            try:
                value = command_value(metric, spec.datatype)
            except ValueError as exc:
                self.refused(dev.code, what, str(exc))
                return
            if spec.datatype == DATETIME and kinds.get(spec.name) is DataType.DATETIME:
                value = datetime.fromtimestamp(value / 1000, timezone.utc)
            items.append((spec.name, value))
        if items:
            self.submit(dev, items)

    def submit(self, dev: NodeDevice, items: list[tuple[str, Any]]) -> None:
        what = describe(items)
        if not self._runner.running:
            self.refused(dev.code, what, "the publisher is stopping")
            return
        with self._lock:
            busy = self.pending >= MAX_PENDING_WRITES
            if not busy:
                self.pending += 1
        if busy:
            self.refused(dev.code, what, f"{MAX_PENDING_WRITES} writes already pending")
            return
        if not self._runner.spawn(lambda: self._write(dev, items, what)):
            with self._lock:  # the loop is closing
                self.pending -= 1

    async def _write(self, dev: NodeDevice, items: list[tuple[str, Any]], what: str) -> None:
        try:
            ok, error = await dev.driver.write_addresses_async(items, exact=True)
            if ok:
                self._count("writes")
                self._logs.event(logging.INFO, "DCMD writes confirmed", dev.code,
                                 "%s: DCMD write %s confirmed by the slave", dev.code, what)
            else:
                self.refused(dev.code, what, error or "refused")
        except Exception as exc:  # never let a write kill the loop
            log.exception("%s: DCMD write failed", dev.code)
            self.refused(dev.code, what, f"internal error: {exc}")
        finally:
            with self._lock:
                self.pending -= 1

    def stop(self) -> None:
        self._runner.stop()
