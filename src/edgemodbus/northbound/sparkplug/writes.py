"""Writes from DCMD messages: one ``edgemodbus-sparkplug-cmd`` thread with an asyncio loop
runs them through ``write_addresses_async`` (many devices' writes in flight at once, each
device's in arrival order).  A confirmed write changes the item, so the driver reports it
and the new value goes out in DDATA; a refused one is logged and counted."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Any

from ...datatypes import DataType
from ..loop_thread import LoopThread
from .devices import NodeDevice
from .payloads import DATETIME, command_value, parse_command

log = logging.getLogger("edgemodbus.sparkplug")

MAX_PENDING_WRITES = 256


class WriteRunner:
    """The write thread; ``count(key)`` counts ``writes`` and ``writesRefused``."""

    def __init__(self, count: Callable[[str], None]) -> None:
        self._count = count
        self._runner = LoopThread("edgemodbus-sparkplug-cmd")
        self._lock = threading.Lock()
        self.pending = 0

    def start(self) -> None:
        self._runner.start()

    def refused(self, code: str, what: str, reason: str) -> None:
        """A write refused before it reached the driver (unknown metric, no value...)."""
        self._count("writesRefused")
        log.warning("%s: DCMD write %s refused: %s", code, what, reason)

    def command(self, dev: NodeDevice, payload: bytes) -> None:
        """A DCMD for ``dev``: its metrics (by name or alias, as born) become one
        ``write_addresses``; one metric that cannot be written refuses the whole."""
        try:
            metrics = parse_command(payload)
        except ValueError as exc:
            self.refused(dev.code, "(payload)", str(exc))
            return
        by_name, by_alias, kinds = dev.metrics, dev.by_alias, dev.kinds  # as born
        items: list[tuple[str, Any]] = []
        for metric in metrics:
            spec = (by_name.get(metric.name) if metric.name is not None
                    else by_alias.get(metric.alias) if metric.alias is not None else None)
            what = repr(metric.name) if metric.name is not None else f"alias {metric.alias}"
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
        what = ", ".join(f"{name}={value!r}" for name, value in items)
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
            ok, error = await dev.driver.write_addresses_async(items)
            if ok:
                self._count("writes")
                log.info("%s: DCMD write %s confirmed by the slave", dev.code, what)
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
