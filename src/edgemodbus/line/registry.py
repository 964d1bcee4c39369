"""The line registry: one :class:`LineWorker` per endpoint, shared by every device on
it (many slaves on one RS-485 line, many devices behind one serial server port)."""

from __future__ import annotations

import threading
from collections.abc import Callable

from .endpoint import Endpoint, LineTiming
from .worker import Connector, LineWorker


class LineRegistry:
    """Shares one :class:`LineWorker` among every user of the same endpoint (many slaves on one
    RS-485 line, many devices behind one serial server port)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lines: dict[tuple[str, ...], tuple[LineWorker, int]] = {}

    def acquire(self, endpoint: Endpoint, timing: LineTiming | None = None,
                connector: Callable[[], Connector] | None = None) -> LineWorker:
        """The line worker of ``endpoint``, started on first use; ``connector`` makes the
        connector of a new one (DTU links)."""
        with self._lock:
            entry = self._lines.get(endpoint.key)
            if entry is not None:
                line, users = entry
                if line.endpoint != endpoint:
                    raise ValueError(
                        f"line {endpoint.key[-1]} is already open as "
                        f"'{line.endpoint.describe()}'; this device asks for "
                        f"'{endpoint.describe()}': devices on one line must agree"
                    )
                self._lines[endpoint.key] = (line, users + 1)
                return line
            line = LineWorker(endpoint, timing, connector() if connector is not None else None)
            line.start()
            self._lines[endpoint.key] = (line, 1)
            return line

    def release(self, line: LineWorker) -> None:
        with self._lock:
            entry = self._lines.get(line.endpoint.key)
            if entry is None or entry[0] is not line:
                return
            _, users = entry
            if users > 1:
                self._lines[line.endpoint.key] = (line, users - 1)
                return
            del self._lines[line.endpoint.key]
        line.stop()

    def lines(self) -> list[LineWorker]:
        with self._lock:
            return [line for line, _ in self._lines.values()]


registry = LineRegistry()
