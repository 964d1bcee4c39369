"""One DTU id's place at the listener (:class:`DtuSlot`): the connector of that DTU's line,
and the rule for a second connection that claims the id.

A DTU that re-dials behind a half-open socket must get its id back, and an impostor (or
a second DTU misconfigured with the same id) must not take it, nor make the id's values
alternate between two devices.  So, per port (``duplicateId``):

* ``replace``: the newcomer takes over and the old socket is shut down (the worker sees
  a link error and switches).  If the id changes hands more than ``idFlipLimit`` times
  within ``idFlipWindow``, it is *contested*: a WARNING names both peers, both
  connections are closed and the id is refused for one window.  Its line cannot connect
  meanwhile, so its items go Invalid with the reason: no value that may come from the
  other device is reported Ok.
* ``keep-existing``: the newcomer is held (not read) for the registration timeout while
  the old connection goes on being polled.  If the line got a reply in that time, the old
  connection still answers and the newcomer is refused; otherwise it takes over.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections import deque
from typing import Literal

from ..errors import ModbusConnectionError, ModbusError
from .admission import Networks
from .connect import open_socket_link
from .endpoint import DtuEndpoint
from .link import Link
from .registration import DtuAccess, PortSettings
from .worker import LineWorker

log = logging.getLogger("edgemodbus.dtu")

NOT_CONNECTED = "DTU not connected"

Offer = Literal["taken", "replaced", "challenge", "contested", "refused"]
"""What became of a connection offered to a slot: taken (the id was free), replaced
(it took over from a live one), challenge (keep-existing: hold it, then
:meth:`DtuSlot.settle`), contested (this offer made the id contested: refused) or refused
(the id is contested)."""


class DtuSlot:
    """The connector of one DTU's line: holds the socket the listener handed over until
    the line worker opens a link on it, and the socket in use (to replace it)."""

    def __init__(self, endpoint: DtuEndpoint, port: PortSettings,
                 access: DtuAccess | None = None) -> None:
        self.endpoint = endpoint
        self.port = port
        self.access = access or DtuAccess()
        self.allowed = Networks(self.access.allow_from, "dtuAllowFrom")
        self.line: LineWorker | None = None
        self.engine = "thread"  # or "loop": what serves its line (line/registry.py)
        self._lock = threading.Lock()
        self._pending: tuple[socket.socket, str, bytes] | None = None
        self._current: socket.socket | None = None
        self.peer: str | None = None
        self.connections = 0
        self.replaced = 0
        # when the id changed hands, in the window (made at the first change: 760 B)
        self._flips: deque[float] | None = None
        self.contested_until = 0.0  # monotonic time; refused before it
        self.contested_reason = ""

    @property
    def dtu_id(self) -> str:
        return self.endpoint.dtu_id

    def attach(self, line: LineWorker | None) -> None:
        """The line worker this slot feeds (None: detached)."""
        with self._lock:
            self.line = line

    def connected(self) -> bool:
        """Whether a connection holds the id (in use or handed over, not yet taken)."""
        with self._lock:
            return self._current is not None or self._pending is not None

    def answers(self) -> int:
        """Replies the line has received so far (any thread): proof that it answers."""
        line = self.line
        if line is None:
            return 0
        stats = line.stats
        return int(stats.responses + stats.native().responses)

    def offer(self, sock: socket.socket, peer: str, rest: bytes, now: float) -> Offer:
        """A new connection registered as this DTU (listener thread).  ``rest``: what it
        sent after its registration, for the link.  Unless taken or replaced, the caller
        keeps the socket (to hold or close it)."""
        with self._lock:
            if now < self.contested_until:
                return "refused"
            live = self._current is not None or self._pending is not None
            if live and self.port.duplicate_id == "keep-existing":
                return "challenge"
            if live and self._flipped(now):
                self.contested_until = now + self.port.flip_window
                self.contested_reason = (
                    f"DTU id {self.dtu_id!r} is contested: it changed hands "
                    f"{len(self._flips or ())} times within {self.port.flip_window:g} s, last "
                    f"between {self.peer} and {peer}; refused for {self.port.flip_window:g} s "
                    "(values could come from either device)")
                self._flips = None
                stale = self._drop_connections()
                line = self.line
                outcome: Offer = "contested"
            else:
                stale = self._hand_over(sock, peer, rest)
                line = self.line
                outcome = "replaced" if live else "taken"
        if stale is not None:
            stale.close()
        if outcome == "contested":
            log.warning("%s", self.contested_reason)
        elif outcome == "replaced":
            log.info("%s: reconnected from %s; replacing its previous connection",
                     self.endpoint.describe(), peer)
        if line is not None:
            line.connect_now()  # take the new socket, or see the contested refusal
        return outcome

    def settle(self, sock: socket.socket, peer: str, rest: bytes, answers_before: int,
               now: float) -> bool:
        """keep-existing: a challenger held since the line had ``answers_before`` replies.
        True: it took over (the old connection did not answer meanwhile)."""
        if self.connected() and self.answers() > answers_before:
            return False
        return self.offer_free(sock, peer, rest, now)

    def offer_free(self, sock: socket.socket, peer: str, rest: bytes, now: float) -> bool:
        """Hand ``sock`` over whatever holds the id (a settled challenge); False if the id
        became contested meanwhile."""
        with self._lock:
            if now < self.contested_until:
                return False
            live = self._current is not None or self._pending is not None
            if live:
                self._flipped(now)  # counted, never contested: the old one fell silent
            stale = self._hand_over(sock, peer, rest)
            line = self.line
        if stale is not None:
            stale.close()
        if live:
            log.info("%s: the connection from %s takes over: the previous one did not "
                     "answer", self.endpoint.describe(), peer)
        if line is not None:
            line.connect_now()
        return True

    def _flipped(self, now: float) -> bool:
        """Count a change of hands (lock held); True past idFlipLimit in the window."""
        flips = self._flips
        if flips is None:
            flips = self._flips = deque()
        flips.append(now)
        while flips[0] <= now - self.port.flip_window:
            flips.popleft()
        return len(flips) > self.port.flip_limit

    def _hand_over(self, sock: socket.socket, peer: str,
                   rest: bytes) -> socket.socket | None:
        """Make ``sock`` the pending connection (lock held); returns a pending one it
        displaced, to close."""
        stale = self._drop_connections()
        self._pending = (sock, peer, rest)
        self.connections += 1
        return stale

    def _drop_connections(self) -> socket.socket | None:
        """Shut the connection in use down (the worker sees a link error) and take the
        pending one out, returned to close (lock held)."""
        if self._current is not None or self._pending is not None:
            self.replaced += 1
        if self._current is not None:
            with contextlib.suppress(OSError):
                self._current.shutdown(socket.SHUT_RDWR)
        stale, self._pending = self._pending, None
        return stale[0] if stale is not None else None

    def open(self, line: LineWorker) -> Link:
        """The line worker takes the handed-over socket (Connector protocol)."""
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                if time.monotonic() < self.contested_until:
                    raise ModbusConnectionError(self.contested_reason)
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


__all__ = ["NOT_CONNECTED", "DtuSlot", "Offer"]
