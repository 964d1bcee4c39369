"""The line registry: one :class:`LineWorker` per endpoint, shared by every device on
it (many slaves on one RS-485 line, many devices behind one serial server port)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import fields

from .dtu_slot import DtuSlot
from .endpoint import DtuEndpoint, Endpoint, LineTiming, MqttDtuEndpoint, TcpEndpoint
from .failover import Failover
from .loop import LoopLine, loop_serves
from .loop_connect import Dialer
from .loop_pool import pool
from .mqtt_dtu import MqttDtuSlot, hubs
from .worker import Connector, LineWorker


class LineRegistry:
    """Shares one :class:`LineWorker` among every user of the same endpoint (many slaves on one
    RS-485 line, many devices behind one serial server port)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lines: dict[tuple[str, ...], tuple[LineWorker, int]] = {}
        # Modbus TCP host:port -> (its connections, lines open on it): one number per peer
        self._peers: dict[tuple[str, ...], tuple[int, int]] = {}

    def acquire(self, endpoint: Endpoint, timing: LineTiming | None = None,
                connector: Callable[[], Connector] | None = None) -> LineWorker:
        """The line worker of ``endpoint``, started on first use; ``connector`` makes the
        connector of a new one (DTU links; a line with alternates gets a
        :class:`Failover`)."""
        with self._lock:
            entry = self._lines.get(endpoint.key)
            if entry is not None:
                line, users = entry
                if line.endpoint != endpoint:
                    raise ValueError(
                        f"line {endpoint.key[-1]} is already open as "
                        f"'{line.endpoint.describe()}'; this device asks for "
                        f"'{endpoint.describe()}'{_differences(line.endpoint, endpoint)}: "
                        "devices on one line must agree"
                    )
                self._lines[endpoint.key] = (line, users + 1)
                return line
            self._claim_peer(endpoint)
            try:
                line = self._new_line(endpoint, timing, connector)
            except BaseException:
                self._release_peer(endpoint)
                raise
            self._lines[endpoint.key] = (line, 1)
            return line

    @staticmethod
    def _new_line(endpoint: Endpoint, timing: LineTiming | None,
                  connector: Callable[[], Connector] | None) -> LineWorker:
        """A started line worker with its connector: ``connector``'s, a DTU's on its
        broker (mqtt-dtu), or a :class:`Failover` for a line with alternates; a
        :class:`LoopLine` on a loop thread for a plain RTU DTU of a port with the
        engine "loop", and for an RTU-over-TCP endpoint with ``engine`` "loop" (its
        connector a non-blocking :class:`Dialer`; with alternates, echo or wrapped
        frames it keeps a thread: :func:`loop_serves`)."""
        failover = slot = None
        if isinstance(endpoint, MqttDtuEndpoint):
            slot = hubs.acquire(endpoint)  # the DTU on its broker's connection
        elif connector is None and not isinstance(endpoint, DtuEndpoint) and \
                endpoint.alternates:
            failover = Failover(endpoint)
        made = connector() if connector is not None else None
        line: LineWorker
        if isinstance(made, DtuSlot) and made.engine == "loop" and \
                isinstance(endpoint, DtuEndpoint) and loop_serves(endpoint):
            line = LoopLine(endpoint, timing, made, pool)  # on a loop thread: line/loop.py
        elif made is None and isinstance(endpoint, TcpEndpoint) and \
                endpoint.engine == "loop" and loop_serves(endpoint):
            if endpoint.loop_threads is not None:
                pool.configure(endpoint.loop_threads)
            line = LoopLine(endpoint, timing, Dialer(endpoint), pool)
        else:
            line = LineWorker(endpoint, timing, failover or slot or made)
        if slot is not None:
            slot.line = line
        line.start()
        if failover is not None:
            failover.start(line)
        return line

    def _claim_peer(self, endpoint: Endpoint) -> None:
        """A new line to a Modbus TCP peer: every line to it must name the same number
        of connections (under the lock)."""
        if not isinstance(endpoint, TcpEndpoint):
            return
        peer = endpoint.key[:3]
        connections, lines = self._peers.get(peer, (endpoint.connections, 0))
        if connections != endpoint.connections:
            raise ValueError(
                f"{endpoint.transport}://{endpoint.host}:{endpoint.port} is polled over "
                f"{connections} connection(s); this device asks for "
                f"{endpoint.connections}: devices of one endpoint must agree on connections")
        self._peers[peer] = (connections, lines + 1)

    def _release_peer(self, endpoint: Endpoint) -> None:
        if isinstance(endpoint, TcpEndpoint):
            peer = endpoint.key[:3]
            connections, lines = self._peers[peer]
            if lines > 1:
                self._peers[peer] = (connections, lines - 1)
            else:
                del self._peers[peer]

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
            self._release_peer(line.endpoint)
        if isinstance(line.connector, Failover):
            line.connector.stop()
        line.stop()
        if isinstance(line.connector, MqttDtuSlot):
            hubs.release(line.connector)
            line.connector = None  # the hub's client (and its wake-up sockets) can go

    def lines(self) -> list[LineWorker]:
        with self._lock:
            return [line for line, _ in self._lines.values()]


def _differences(old: Endpoint, new: Endpoint) -> str:
    """The settings two endpoints of one line disagree on, for the error."""
    if type(old) is not type(new):
        return ""
    names = [f.name for f in fields(old) if getattr(old, f.name) != getattr(new, f.name)]
    return f" (they differ in {', '.join(names)})" if names else ""


registry = LineRegistry()
