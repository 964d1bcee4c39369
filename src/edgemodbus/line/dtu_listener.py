"""Listen mode (``rtu-over-tcp-server``): DTUs that dial in to us.

Most 4G/Ethernet DTUs are TCP clients: they connect to a server, optionally send a
registration packet (IMEI, ICCID, a serial number) and then pass RTU frames through
unchanged.  One :class:`DtuListener` thread serves each listen port (a ``selectors``
loop: accept, read registrations with a deadline, no busy loop); every identified
connection is handed to the :class:`DtuSlot` of its DTU id, the connector of that DTU's
line (one line, one worker thread per DTU, shared by the devices that name the id).

* Identification per port: ``registration`` text / hex / regex (with an optional fixed
  length), or none: then the port's one configured DTU takes the connection.  The
  registration rule is in :mod:`edgemodbus.line.registration` (:func:`identify`).
* An unknown or silent peer is logged with its address and closed when the
  registration timeout runs out (held until then, so a misconfigured DTU cannot
  reconnect in a tight loop); it never takes another DTU's place.
* A DTU that reconnects replaces its old connection: the listener shuts the old socket
  down (its fd stays valid until the worker closes it) and asks the line to switch.
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from ..errors import ModbusConnectionError, ModbusError
from .connect import open_socket_link
from .endpoint import DtuEndpoint
from .link import Link
from .registration import Identified, IdIndex, PortSettings, identify
from .worker import LineWorker

log = logging.getLogger("edgemodbus.dtu")

NOT_CONNECTED = "DTU not connected"


class DtuSlot:
    """The connector of one DTU's line: holds the socket the listener handed over until
    the line worker opens a link on it, and the socket in use (to replace it)."""

    def __init__(self, endpoint: DtuEndpoint, port: PortSettings) -> None:
        self.endpoint = endpoint
        self.port = port
        self.line: LineWorker | None = None
        self._lock = threading.Lock()
        self._pending: tuple[socket.socket, str, bytes] | None = None
        self._current: socket.socket | None = None
        self.peer: str | None = None
        self.connections = 0
        self.replaced = 0

    @property
    def dtu_id(self) -> str:
        return self.endpoint.dtu_id

    def attach(self, line: LineWorker | None) -> None:
        """The line worker this slot feeds (None: detached)."""
        with self._lock:
            self.line = line

    def offer(self, sock: socket.socket, peer: str, rest: bytes = b"") -> None:
        """A new connection of this DTU (listener thread): it replaces the old one.
        ``rest``: what the DTU sent after its registration, for the link."""
        with self._lock:
            stale = self._pending
            self._pending = (sock, peer, rest)
            self.connections += 1
            current = self._current
            if current is not None or stale is not None:
                self.replaced += 1
            if current is not None:
                with contextlib.suppress(OSError):  # the worker sees a link error
                    current.shutdown(socket.SHUT_RDWR)
            line = self.line
        if stale is not None:
            stale[0].close()
        if current is not None or stale is not None:
            log.info("%s: reconnected from %s; replacing its previous connection",
                     self.endpoint.describe(), peer)
        if line is not None:
            line.connect_now()

    def open(self, line: LineWorker) -> Link:
        """The line worker takes the handed-over socket (Connector protocol)."""
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                raise ModbusConnectionError(
                    f"{NOT_CONNECTED} (dtuId {self.dtu_id!r}, listening on "
                    f"{self.port.host}:{self.port.port})"
                )
            sock, peer, rest = pending
            self._current = sock
            self.peer = peer
        ep = self.endpoint

        def release() -> None:
            with self._lock:
                if self._current is sock:
                    self._current = None

        try:
            link = open_socket_link(sock, ep, line.timing, line.stats, release,
                                    line.dispatch_report)
        except (ModbusError, ValueError, OSError):
            release()
            sock.close()
            raise
        # what the DTU sent after its registration, taken as received now: reports are
        # applied at once, heartbeats counted; on a plain RTU link they answer nothing
        link.feed(rest)
        link.flush_reports()
        return link

    def close(self) -> None:
        """Forget a connection not taken yet (the line worker is gone)."""
        with self._lock:
            pending, self._pending = self._pending, None
            self.line = None
        if pending is not None:
            pending[0].close()


@dataclass
class _Newcomer:
    sock: socket.socket
    peer: str
    deadline: float
    buf: bytearray = field(default_factory=bytearray)
    unknown: bool = False
    quiet_at: float = math.inf  # when to look at the registration again if no byte comes


class DtuListener:
    """One listen port and its thread: accepts DTUs, identifies them, hands them over."""

    def __init__(self, settings: PortSettings) -> None:
        self.settings = settings
        self._slots: dict[str, DtuSlot] = {}
        self._ids = IdIndex(settings.registration)  # the slots' ids, for identify()
        self._lock = threading.Lock()
        self.stats: dict[str, int] = {"accepted": 0, "registered": 0, "unknown": 0,
                                      "silent": 0}
        family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((settings.host, settings.port))
            sock.listen(socket.SOMAXCONN)  # DTUs dial in by the thousand after an outage
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise ValueError(f"listenPort {settings.port}: cannot listen on "
                             f"{settings.host}:{settings.port}: {exc.strerror or exc}") from None
        self._sock = sock
        self.port = int(sock.getsockname()[1])
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(sock, selectors.EVENT_READ, None)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._newcomers: dict[int, _Newcomer] = {}
        self._stopping = False
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"edgemodbus-dtu-listener :{self.port}")
        self._thread.start()

    # -- slots (any thread) ----------------------------------------------------------------
    def add_slot(self, slot: DtuSlot) -> None:
        with self._lock:
            self._slots[slot.dtu_id] = slot
            self._ids.add(slot.dtu_id)

    def remove_slot(self, slot: DtuSlot) -> None:
        with self._lock:
            if self._slots.get(slot.dtu_id) is slot:
                del self._slots[slot.dtu_id]
                self._ids.remove(slot.dtu_id)
        slot.close()

    def slot_count(self) -> int:
        with self._lock:
            return len(self._slots)

    def stop(self) -> None:
        self._stopping = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")
        self._thread.join(10.0)
        for newcomer in self._newcomers.values():
            newcomer.sock.close()
        self._newcomers.clear()
        self._sel.close()
        self._sock.close()
        self._wake_r.close()
        self._wake_w.close()

    # -- the loop ----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stopping:
                timeout = None
                if self._newcomers:
                    first = min(min(n.deadline, n.quiet_at) for n in self._newcomers.values())
                    timeout = max(0.0, first - time.monotonic())
                for key, _ in self._sel.select(timeout):
                    if key.fileobj is self._sock:
                        self._accept()
                    elif key.fileobj is self._wake_r:
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(64)
                    else:
                        self._on_data(key.data)
                self._expire()
        except Exception:
            log.exception("DTU listener on port %d failed", self.port)

    def _accept(self) -> None:
        while True:
            try:
                conn, addr = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE: leave it in the backlog for now
                log.warning("DTU listener :%d: accept failed: %s", self.port, exc)
                return
            peer = f"{addr[0]}:{addr[1]}"
            self.stats["accepted"] += 1
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            if self.settings.registration == "none":
                self._hand_over_single(conn, peer)
                continue
            conn.setblocking(False)
            newcomer = _Newcomer(conn, peer, time.monotonic() + self.settings.timeout)
            self._newcomers[conn.fileno()] = newcomer
            self._sel.register(conn, selectors.EVENT_READ, newcomer)

    def _hand_over_single(self, conn: socket.socket, peer: str) -> None:
        with self._lock:
            slots = list(self._slots.values())
        if len(slots) != 1:
            self.stats["unknown"] += 1
            log.warning("DTU listener :%d: %s connected but %d DTUs are configured on this "
                        "port without registration; closed", self.port, peer, len(slots))
            conn.close()
            return
        self._register(slots[0], conn, peer)

    def _register(self, slot: DtuSlot, conn: socket.socket, peer: str,
                  rest: bytes = b"") -> None:
        self.stats["registered"] += 1
        conn.setblocking(True)
        log.info("DTU %r registered from %s on port %d", slot.dtu_id, peer, self.port)
        slot.offer(conn, peer, rest)

    def _drop(self, newcomer: _Newcomer) -> None:
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(newcomer.sock)
        self._newcomers.pop(newcomer.sock.fileno(), None)

    def _on_data(self, newcomer: _Newcomer) -> None:
        try:
            data = newcomer.sock.recv(1024)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(newcomer)
            log.warning("DTU listener :%d: %s closed before registering (got %s)", self.port,
                        newcomer.peer, bytes(newcomer.buf).hex(" ").upper() or "nothing")
            newcomer.sock.close()
            return
        if newcomer.unknown:
            return  # held until the timeout, then closed
        newcomer.buf += data
        newcomer.quiet_at = time.monotonic() + self.settings.quiet_gap
        self._decide(newcomer, settled=False)

    def _decide(self, newcomer: _Newcomer, settled: bool) -> bool:
        """Register, or mark unknown, a newcomer whose registration is complete; True
        when it was handed to its DTU's slot."""
        buf = bytes(newcomer.buf)
        with self._lock:  # the index is kept sorted as drivers come and go
            found = identify(buf, self._ids, self.settings, settled=settled)
            slot = self._slots.get(found.dtu_id) if isinstance(found, Identified) else None
        if found is None:
            return False
        newcomer.quiet_at = math.inf
        if isinstance(found, Identified) and slot is not None:
            self._drop(newcomer)
            self._register(slot, newcomer.sock, newcomer.peer, buf[found.end:])
            return True
        newcomer.unknown = True
        self.stats["unknown"] += 1
        log.warning("DTU listener :%d: unknown DTU from %s (registration %s, %r); closing it "
                    "after the registration timeout", self.port, newcomer.peer,
                    buf.hex(" ").upper(), found)
        return False

    def _expire(self) -> None:
        now = time.monotonic()
        for newcomer in [n for n in self._newcomers.values() if n.quiet_at <= now]:
            newcomer.quiet_at = math.inf  # looked at again when the next byte comes
            self._decide(newcomer, settled=True)
        for newcomer in [n for n in self._newcomers.values() if n.deadline <= now]:
            if not newcomer.unknown and self._decide(newcomer, settled=True):
                continue  # registered: an exact match at the timeout
            self._drop(newcomer)
            if not newcomer.unknown:
                self.stats["silent"] += 1
                got = bytes(newcomer.buf).hex(" ").upper() or "nothing"
                log.warning("DTU listener :%d: %s did not register within %.3g s (got %s); "
                            "closed", self.port, newcomer.peer, self.settings.timeout, got)
            newcomer.sock.close()


class DtuRegistry:
    """One listener per listen port, refcounted by its DTU slots; one slot per DTU id,
    refcounted by the devices that name it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[tuple[str, int], DtuListener] = {}
        self._slots: dict[tuple[str, int, str], tuple[DtuSlot, int]] = {}

    def acquire(self, settings: PortSettings, endpoint: DtuEndpoint) -> DtuSlot:
        with self._lock:
            listener = self._listeners.get(settings.key)
            if listener is not None:
                diffs = listener.settings.differences(settings)
                if diffs:
                    raise ValueError(f"listenPort {settings.port}: devices on one listen port "
                                     "must agree; this device has " + "; ".join(diffs))
            key = (*settings.key, endpoint.dtu_id)
            entry = self._slots.get(key)
            if entry is not None:
                slot, users = entry
                if slot.endpoint != endpoint:
                    raise ValueError(f"dtuId {endpoint.dtu_id!r}: already open as "
                                     f"'{slot.endpoint.describe()}'; this device asks for "
                                     f"'{endpoint.describe()}': devices on one DTU must agree")
                self._slots[key] = (slot, users + 1)
                return slot
            if listener is None:
                listener = DtuListener(settings)
                self._listeners[settings.key] = listener
            elif settings.registration == "none" and listener.slot_count():
                raise ValueError(f"dtuId {endpoint.dtu_id!r}: port {settings.port} has no "
                                 "registration and already serves a DTU; without a "
                                 "registration packet a port serves one DTU")
            slot = DtuSlot(endpoint, settings)
            listener.add_slot(slot)
            self._slots[key] = (slot, 1)
            return slot

    def release(self, slot: DtuSlot) -> None:
        stop: DtuListener | None = None
        with self._lock:
            key = (*slot.port.key, slot.dtu_id)
            entry = self._slots.get(key)
            if entry is None or entry[0] is not slot:
                return
            if entry[1] > 1:
                self._slots[key] = (slot, entry[1] - 1)
                return
            del self._slots[key]
            listener = self._listeners[slot.port.key]
            listener.remove_slot(slot)
            if not listener.slot_count():
                del self._listeners[slot.port.key]
                stop = listener
        if stop is not None:
            stop.stop()

    def listener(self, host: str, port: int) -> DtuListener | None:
        with self._lock:
            return self._listeners.get((host, port))

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {f"{h}:{p}": dict(li.stats) for (h, p), li in self._listeners.items()}


registry = DtuRegistry()

__all__ = ["NOT_CONNECTED", "DtuListener", "DtuRegistry", "DtuSlot", "PortSettings",
           "registry"]
