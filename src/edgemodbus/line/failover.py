"""Backup endpoints (docs/links.md): the connector of a line whose endpoint names
``alternates``.

The line opens its current target (the primary first).  After ``failoverAfter`` failed
connects in a row, or once every device on the line has failed ``failoverAfter`` cycles
in a row on the current link, it moves to the next target (after the last: the primary
again) and opens it at once.  While it is on an alternate, a watcher thread probes the
primary every ``failbackInterval`` (a TCP connect, or opening the serial port, on a
link of its own that it closes again) and moves the line back once a probe succeeds.
Moves are counted in the line's stats (``failovers``, ``failbacks``, ``activeEndpoint``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from ..errors import ModbusError
from ..stats import LineStats
from .connect import open_link
from .endpoint import SerialPort, TcpEndpoint
from .link import Link

if TYPE_CHECKING:
    from .worker import LineWorker

log = logging.getLogger("edgemodbus.line")

WATCH_PERIOD = 0.2  # seconds between two looks at the line's devices


class Failover:
    """The connector of a line with alternates (see the module docstring); ``start``
    its watcher once the line runs, ``stop`` it before the line stops."""

    def __init__(self, endpoint: SerialPort | TcpEndpoint) -> None:
        self.targets: tuple[SerialPort | TcpEndpoint, ...] = endpoint.targets()
        self.after = endpoint.failover_after
        self.probe_every = endpoint.failback_interval
        self.index = 0  # the target in use
        self._lock = threading.Lock()
        self._failed_connects = 0
        self._baseline: dict[int, int] = {}  # id(poller) -> failed cycles at link-up
        self._generation = -1  # the line's connects + reconnects the baseline is from
        self._next_probe = 0.0
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._line: LineWorker | None = None

    # -- the connector (the line's worker thread) -------------------------------------
    def open(self, line: LineWorker) -> Link:
        """Open the current target; on its ``failoverAfter``-th failed connect in a row
        move to the next and open that at once (its failure raises)."""
        with self._lock:
            index = self.index
            line.stats.active_endpoint = self.targets[index].describe()
        try:
            link = self._open(line, index)
        except ModbusError:
            with self._lock:
                self._failed_connects += 1
                moved = self._failed_connects >= self.after and self.index == index
                if moved:
                    self._move(line, (index + 1) % len(self.targets),
                               f"{self._failed_connects} failed connects")
                index = self.index
            if not moved:
                raise
            line.stats.connect_failures += 1  # the worker sees the next target's result
            link = self._open(line, index)
        with self._lock:
            self._failed_connects = 0
        return link

    def _open(self, line: LineWorker, index: int) -> Link:
        return open_link(self.targets[index], line.timing, line.stats,
                         on_report=line.dispatch_report)

    def _move(self, line: LineWorker, index: int, why: str) -> None:
        """Make ``index`` the current target (under the lock)."""
        old, self.index = self.index, index
        self._failed_connects = 0
        self._generation = -1
        self._next_probe = time.monotonic() + self.probe_every
        stats = line.stats
        stats.active_endpoint = self.targets[index].describe()
        if index == 0:
            stats.failbacks += 1
            log.warning("%s: back to the primary %s (%s)", line.endpoint.describe(),
                        stats.active_endpoint, why)
        else:
            stats.failovers += 1
            log.warning("%s: %s failed (%s): moving to %s", line.endpoint.describe(),
                        self.targets[old].describe(), why, stats.active_endpoint)

    # -- the watcher thread -----------------------------------------------------------
    def start(self, line: LineWorker) -> None:
        self._line = line
        line.stats.active_endpoint = self.targets[self.index].describe()
        self._thread = threading.Thread(
            target=self._watch, name=f"edgemodbus-failover {line.endpoint.describe()}",
            daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the watcher (idempotent); a probe under way ends within its connect
        timeout."""
        self._stopping.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def _watch(self) -> None:
        line = self._line
        assert line is not None
        while not self._stopping.wait(WATCH_PERIOD):
            try:
                self._check_cycles(line)
                self._probe(line)
            except Exception:  # a bug here must not stop the watching
                log.exception("%s: failover watcher failed", line.endpoint.describe())

    def _check_cycles(self, line: LineWorker) -> None:
        """Every device failed ``failoverAfter`` cycles in a row on this link: move on."""
        # each poller's failed cycles in a row (poll/poller.py), read without a lock
        counts = [(id(p), n) for p in line.pollers
                  if isinstance(n := getattr(p, "failed_cycles", None), int)]
        if not line.link_up or not counts:
            return
        generation = line.stats.connects + line.stats.reconnects
        with self._lock:
            if generation != self._generation:  # a new link: count from here
                self._generation = generation
                self._baseline = dict(counts)
                return
            failing = True
            for key, n in counts:
                base = self._baseline.setdefault(key, 0)
                if n < base:  # it answered since
                    self._baseline[key] = base = 0
                failing = failing and n - base >= self.after
            if not failing:
                return
            self._move(line, (self.index + 1) % len(self.targets),
                       f"{self.after} failed cycles of every device")
        line.connect_now()

    def _probe(self, line: LineWorker) -> None:
        """On an alternate: try the primary when a probe is due; back once it opens."""
        with self._lock:
            due = self.index != 0 and self.probe_every > 0 and \
                time.monotonic() >= self._next_probe
        if not due:
            return
        try:
            open_link(self.targets[0], line.timing, LineStats()).close()
        except (ModbusError, ValueError) as exc:
            log.debug("%s: probe of the primary failed: %s", line.endpoint.describe(), exc)
            with self._lock:
                self._next_probe = time.monotonic() + self.probe_every
            return
        if self._stopping.is_set():
            return
        with self._lock:
            if self.index == 0:
                return
            self._move(line, 0, "a probe of it succeeded")
        line.connect_now()
