"""Commands from the broker are untrusted input: any client that may publish on the
node's NCMD/DCMD topics can send them.  Here they are checked (the caps of
commands.py), every refusal is counted, log lines go through a rate limiter with short
quoted prefixes of the sender's text, and rebirths are paced (Sparkplug 3.0 lets an edge
node answer a rebirth request when it can: requests within ``rebirthInterval`` of the
last rebirth are folded into one, done when the interval ends)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from ...line.log_limit import LogLimiter, short_text
from .commands import CommandMetric, node_command, parse_command, split_reads
from .devices import NodeDevice
from .payloads import DEVICE_READ, NODE_READ, REBIRTH

log = logging.getLogger("edgemodbus.sparkplug")

MAX_REASON_CHARS = 200
"""A refusal's reason in a log line (a driver's error may quote the value)."""


class CommandLog:
    """:class:`~edgemodbus.line.log_limit.LogLimiter` shared by paho's thread, the
    command thread and the Sparkplug thread (which flushes its summaries)."""

    def __init__(self, logger: logging.Logger = log, interval: float = 10.0,
                 burst: int = 3) -> None:
        self._lock = threading.Lock()
        self._limiter = LogLimiter(logger, interval, burst)

    def event(self, level: int, kind: str, source: str, msg: str, *args: object) -> None:
        with self._lock:
            self._limiter.event(level, kind, source, msg, *args)

    def flush(self, force: bool = False) -> None:
        with self._lock:
            self._limiter.flush(force)

    def next_due(self) -> float:
        with self._lock:
            return self._limiter.next_due()

    @property
    def suppressed(self) -> int:
        """Lines folded into summaries so far."""
        with self._lock:
            return self._limiter.suppressed


def short_reason(text: str) -> str:
    return text if len(text) <= MAX_REASON_CHARS else (
        f"{text[:MAX_REASON_CHARS]}... ({len(text)} chars)")


class RebirthPacer:
    """At most one rebirth per ``interval`` s (0: no limit); a request within it is
    folded into one rebirth when the interval ends.  Used by one thread."""

    def __init__(self, interval: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.interval = interval
        self._clock = clock
        self._last = -float("inf")
        self.due: float | None = None  # a folded request is done then (monotonic)

    def request(self) -> bool:
        """A rebirth asked: True to do it now, False when it is folded (done at
        :attr:`due`)."""
        now = self._clock()
        if self.due is None and now - self._last >= self.interval:
            self._last = now
            return True
        if self.due is None:
            self.due = self._last + self.interval
        return False

    def take_due(self) -> bool:
        """True (once) when a folded rebirth is due now."""
        now = self._clock()
        if self.due is None or now < self.due:
            return False
        self.due = None
        self._last = now
        return True


class CommandInbox:
    """NCMD and DCMD as paho's thread delivers them.  ``count(key)`` bumps a publisher
    counter, ``push`` queues an event for the Sparkplug thread, ``device(code)`` finds an
    attached device, ``write(dev, metrics)`` starts a DCMD's writes."""

    def __init__(self, count: Callable[[str], None], push: Callable[[tuple[Any, ...]], None],
                 device: Callable[[str], NodeDevice | None],
                 write: Callable[[NodeDevice, list[CommandMetric]], None],
                 logs: CommandLog,
                 read: Callable[[NodeDevice | None, list[str] | None], None]
                 = lambda _dev, _names: None) -> None:
        """``read(dev, names)`` starts a read on demand of ``dev`` (None: every device),
        of these items (None: every item)."""
        self._count = count
        self._push = push
        self._device = device
        self._write = write
        self._read = read
        self.logs = logs

    def refuse(self, counter: str, kind: str, source: str, msg: str, *args: object) -> None:
        """Count one refused command under ``counter`` and log it (rate-limited)."""
        self._count(counter)
        self.logs.event(logging.WARNING, kind, source, msg, *args)

    def node(self, payload: bytes) -> None:
        """An NCMD: ``Node Control/Rebirth`` = true queues a rebirth; anything else in it
        is refused (counted once per message, logged with its first metric)."""
        self._count("commands")
        try:
            rebirth, others = node_command(parse_command(payload))
            reads, _, others = split_reads(others, NODE_READ)
        except ValueError as exc:
            self.refuse("commandErrors", "NCMD refused", "NCMD",
                        "Sparkplug: NCMD refused: %s", exc)
            return
        if rebirth:
            self._push(("rebirth", "NCMD"))
        if reads:
            self._read(None, None)
        if others:
            self.refuse("commandErrors", "NCMD metrics ignored", "NCMD",
                        "Sparkplug: NCMD: %d metric(s) ignored, e.g. %s (only %s or %s = "
                        "true is supported)", len(others), others[0].label, REBIRTH, NODE_READ)

    def device_command(self, code: str, payload: bytes) -> None:
        """A DCMD for device ``code`` (the topic's last level)."""
        self._count("commands")
        dev = self._device(code)
        if dev is None:
            self.refuse("commandErrors", "DCMD for unknown devices", short_text(code),
                        "Sparkplug: DCMD for unknown device %s ignored", short_text(code))
            return
        if not dev.here():  # a fleet device whose DTU is connected to another instance
            self.refuse("commandsNotHeld", "DCMD for devices not held here", dev.code,
                        "%s: DCMD ignored: its DTU is not connected to this instance "
                        "(fleet: the edge node holding it takes its commands)", dev.code)
            return
        try:
            metrics = parse_command(payload)
        except ValueError as exc:
            self.refuse("writesRefused", "DCMD writes refused", dev.code,
                        "%s: DCMD write (payload) refused: %s", dev.code, exc)
            return
        try:
            whole, names, metrics = split_reads(metrics, DEVICE_READ, items=True)
            unknown = [n for n in names if n not in dev.metrics]  # as born
            if unknown:
                raise ValueError(f"{DEVICE_READ}: no metric {short_text(unknown[0])} in "
                                 "the device's DBIRTH")
        except ValueError as exc:
            # the text, not the exception: a log record holding its traceback would
            # keep paho's frames (and the client's sockets) alive
            self.refuse("readsRefused", "reads refused", dev.code,
                        "%s: DCMD refused: %s", dev.code, str(exc))
            return
        if metrics:
            self._write(dev, metrics)
        if whole or names:  # after the writes it came with: they are queued first
            self._read(dev, None if whole else list(dict.fromkeys(names)))

