"""Listen mode (``rtu-over-tcp-server``): DTUs that dial in to us.

Most 4G/Ethernet DTUs are TCP clients: they connect to a server, optionally send a
registration packet (IMEI, ICCID, a serial number) and then pass RTU frames through
unchanged.  One :class:`DtuListener` thread serves each listen port (a ``selectors``
loop: accept, read registrations with a deadline, no busy loop); every identified
connection is handed to the :class:`DtuSlot` of its DTU id (:mod:`.dtu_slot`), the
connector of that DTU's line.  The registration rule is :func:`identify`.

The port faces the internet, so nothing a peer does before it registers may cost more
than a bound (:mod:`.admission`):

* at accept: the port's allow-list (``listenAllowFrom``), then the caps on connections
  waiting to register, per port and per source; a refused connection is reset at once.
  When the port is full, the oldest connection held as refused, or silent for the quiet
  gap, is evicted first, so that idle connections cannot keep DTUs out.
  Accept errors (EMFILE, ENFILE, ENOBUFS, ENOMEM) pause accepting, doubling up to
  2 s (line/accept_pause.py), instead of spinning;
* before registering: at most ``registrationMaxBytes`` bytes (then closed at once),
  read at ``registrationByteRate`` at most (reading pauses; TCP slows the sender), within
  the registration timeout;
* a peer that named an unknown id, a DTU it may not be (``dtuAllowFrom``) or a wrong
  ``registrationKey`` is held without being read until the registration timeout, then
  closed (a misconfigured DTU cannot reconnect in a tight loop);
* a second connection for a connected id follows the duplicate-id policy (dtu_slot.py);
* behind a load balancer (``fleet.loadBalancers``): a connection from a balancer must
  start with a PROXY v2 header (:mod:`.proxy_v2`), and every check above then sees the
  DTU's address from it; a header from any other address, a malformed or oversize one,
  or a balancer's connection without one is refused; a LOCAL header (the balancer's
  health check) is closed quietly.

Every refusal is counted in :attr:`DtuListener.stats`; log lines go through a
:class:`LogLimiter` (a few per kind and interval, the rest summarised) and show at most a
short hex prefix of untrusted bytes, and none of a registration that carries a key.
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import threading
import time
from typing import Any

from . import proxy_v2
from .accept_pause import ACCEPT_ERRORS, AcceptPause
from .admission import ByteBudget, Networks, Unregistered, key_matches
from .dtu_newcomer import ACCEPT_BATCH, BUDGET_BURST, COUNTERS, RESET, Newcomer, evictable
from .dtu_slot import DtuSlot
from .log_limit import LogLimiter, hex_prefix, short_text
from .registration import Identified, IdIndex, PortSettings, identify

log = logging.getLogger("edgemodbus.dtu")

class DtuListener:
    """One listen port and its thread: accepts DTUs, identifies them, hands them over."""

    def __init__(self, settings: PortSettings, balancers: Networks | None = None) -> None:
        self.settings = settings
        self.balancers = balancers or Networks((), "fleet.loadBalancers")
        self._slots: dict[str, DtuSlot] = {}
        self._ids = IdIndex(settings.registration)  # the slots' ids, for identify()
        self._lock = threading.Lock()
        self._allowed = Networks(settings.allow_from, "listenAllowFrom")
        self._waiting = Unregistered(settings.max_unregistered, settings.max_per_source)
        self._logs = LogLimiter(log)
        self._keyed = "(?P<key>" in settings.pattern  # registrations carry secrets
        self.counts: dict[str, int] = dict.fromkeys(COUNTERS, 0)
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
        self._newcomers: dict[Newcomer, None] = {}  # in accept order, oldest first
        self._challenged: set[str] = set()  # ids with a connection held as challenger
        self._paused = AcceptPause()  # accepting after an accept error (EMFILE...)
        self._stopping = False
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"edgemodbus-dtu-listener :{self.port}")
        self._thread.start()

    # -- slots and figures (any thread) -----------------------------------------------------
    def via_balancer(self, source: str) -> bool:
        """Whether a connection from ``source`` comes through a load balancer (replaced
        whole by the registry when the fleet section changes)."""
        balancers = self.balancers
        return bool(balancers.nets) and balancers.allows(source)

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

    def held(self) -> list[dict[str, Any]]:
        """The configured DTUs of this port: id, connected now, the last peer address,
        connections taken and replaced (the web console's DTU table)."""
        with self._lock:
            slots = list(self._slots.values())
        return [{"dtuId": s.dtu_id, "connected": s.connected(), "peer": s.peer,
                 "connections": s.connections, "replaced": s.replaced} for s in slots]

    @property
    def stats(self) -> dict[str, int]:
        """Counters of what the port accepted and refused, and gauges: connections
        waiting to register, configured DTUs, DTUs connected now."""
        with self._lock:
            slots = list(self._slots.values())
        return {**self.counts, "logSuppressed": self._logs.suppressed,
                "unregistered": self._waiting.total, "dtus": len(slots),
                "connected": sum(1 for s in slots if s.connected())}

    def stop(self) -> None:
        self._stopping = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")
        self._thread.join(10.0)
        for newcomer in self._newcomers:
            newcomer.sock.close()
        self._newcomers.clear()
        self._sel.close()
        self._sock.close()
        self._wake_r.close()
        self._wake_w.close()

    # -- the loop ----------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stopping:
            try:
                self._turn()
            except Exception:  # a bug must not stop the port: log it and go on
                log.exception("DTU listener on port %d: unexpected error", self.port)
                time.sleep(0.1)
        self._logs.flush(force=True)

    def _turn(self) -> None:
        """One turn of the loop: wait for sockets or the next timer, then serve them."""
        first = min((n.wake() for n in self._newcomers), default=math.inf)
        first = min(first, self._paused.until, self._logs.next_due())
        timeout = None if first == math.inf else max(0.0, first - time.monotonic())
        accept = False
        for key, _ in self._sel.select(timeout):
            if key.fileobj is self._sock:
                accept = True  # after the registrations: they free waiting places
            elif key.fileobj is self._wake_r:
                with contextlib.suppress(OSError):
                    self._wake_r.recv(64)
            else:
                self._on_data(key.data)
        if accept:
            self._accept()
        self._timers(time.monotonic())
        self._logs.flush()

    def _refuse(self, counter: str, source: str, conn: socket.socket, why: str) -> None:
        """Close a new connection at once (reset: no TIME_WAIT kept here), counted and
        logged through the limiter."""
        self.counts[counter] += 1
        self._logs.event(logging.WARNING, f"connections refused ({counter})", source,
                         "DTU listener :%d: %s refused: %s", self.port, source, why)
        with contextlib.suppress(OSError):
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, RESET)
        conn.close()

    def _accept(self) -> None:
        for _ in range(ACCEPT_BATCH):
            try:
                conn, addr = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in ACCEPT_ERRORS:
                    self._pause_accepting(exc)
                else:
                    log.warning("DTU listener :%d: accept failed: %s", self.port, exc)
                return
            self._paused.accepted()
            self.counts["accepted"] += 1
            self._admit(conn, str(addr[0]), f"{addr[0]}:{addr[1]}")

    def _pause_accepting(self, exc: OSError) -> None:
        """Out of fds or buffers: stop accepting for a while (the backlog waits)."""
        self.counts["acceptErrors"] += 1
        self.counts["acceptPauses"] += 1
        pause = self._paused.failed(time.monotonic())
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(self._sock)
        self._logs.event(logging.WARNING, "accept pauses", "accept",
                         "DTU listener :%d: accept failed (%s); pausing accepting for %.2g s",
                         self.port, exc.strerror or exc, pause)

    def _admit(self, conn: socket.socket, source: str, peer: str) -> None:
        proxied = self.via_balancer(source)  # the checks wait for the DTU's address
        if not proxied and not self._allowed.allows(source):
            self._refuse("refusedNotAllowed", source, conn, "not in listenAllowFrom")
            return
        with contextlib.suppress(OSError):
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        refusal = self._waiting.refusal(source, per_source=not proxied)
        if refusal is not None and refusal[0] == "refusedPortCap" and self._evict():
            refusal = self._waiting.refusal(source, per_source=not proxied)
        if refusal is not None:
            counter, why = refusal
            self._refuse(counter, source, conn, why)
            return
        conn.setblocking(False)
        now = time.monotonic()
        budget = ByteBudget(self.settings.byte_rate,
                            min(BUDGET_BURST, self.settings.max_bytes), now)
        newcomer = Newcomer(conn, peer, source, now + self.settings.timeout, budget, now,
                             proxied=proxied)
        self._newcomers[newcomer] = None
        self._waiting.add(source)
        if self.settings.registration == "none" and not proxied:
            self._hand_over_single(newcomer)
        else:
            self._sel.register(conn, selectors.EVENT_READ, newcomer)

    def _evict(self) -> bool:
        """The port is full: make room for a new connection by closing the oldest one
        that is either held as refused or has sent nothing for the quiet gap, so that
        idle connections cannot keep DTUs out.  False: none of the oldest qualifies."""
        newcomer = evictable(self._newcomers, time.monotonic() - self.settings.quiet_gap)
        if newcomer is None:
            return False
        self.counts["evicted"] += 1
        self._logs.event(logging.WARNING, "connections evicted", newcomer.source,
                         "DTU listener :%d: %s evicted: the port is full and it has not "
                         "registered", self.port, newcomer.peer)
        self._close(newcomer)
        return True

    def _hand_over_single(self, newcomer: Newcomer) -> None:
        """A port without registration: its one DTU takes every connection."""
        with self._lock:
            slots = list(self._slots.values())
        if len(slots) == 1:
            self._offer(slots[0], newcomer, bytes(newcomer.buf))  # after a PROXY header
            return
        self.counts["unknown"] += 1
        self._close(newcomer)
        self._logs.event(logging.WARNING, "connections refused (unknown)", newcomer.source,
                         "DTU listener :%d: %s refused: %d DTUs are configured on this port "
                         "without registration", self.port, newcomer.peer, len(slots))

    def _offer(self, slot: DtuSlot, newcomer: Newcomer, rest: bytes) -> None:
        """Hand an identified connection to its slot, under the duplicate-id policy:
        handed over, held as the id's one challenger, or held as refused."""
        conn, peer = newcomer.sock, newcomer.peer
        conn.setblocking(True)
        outcome = slot.offer(conn, peer, rest, time.monotonic())
        if outcome in ("taken", "replaced"):
            self._release(newcomer)
            self.counts["registered"] += 1
            if outcome == "replaced":
                self.counts["replaced"] += 1
            self._logs.event(logging.INFO, "DTUs registered", slot.dtu_id,
                             "DTU %r registered from %s on port %d", slot.dtu_id, peer,
                             self.port)
            return
        conn.setblocking(False)
        if outcome == "challenge" and slot.dtu_id not in self._challenged:
            self._challenged.add(slot.dtu_id)
            newcomer.challenge = (slot, rest, slot.answers())
            newcomer.deadline = time.monotonic() + self.settings.timeout
            self._hold(newcomer)
            return
        if outcome == "challenge":
            counter, why = "duplicateRefused", "already challenged by another connection"
        elif outcome == "contested":
            counter, why = "contested", "the id is contested"
        else:
            counter, why = "refusedContested", "the id is contested"
        self.counts[counter] += 1
        self._hold(newcomer)
        self._logs.event(logging.WARNING, f"connections held ({counter})", newcomer.source,
                         "DTU listener :%d: %s claims DTU id %r: %s; held until the "
                         "registration timeout", self.port, peer, slot.dtu_id, why)

    def _hold(self, newcomer: Newcomer) -> None:
        """Keep a refused (or challenging) newcomer without reading it until its
        deadline; it still counts against the caps."""
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(newcomer.sock)
        newcomer.held = True
        newcomer.quiet_at = newcomer.resume_at = math.inf

    def _close(self, newcomer: Newcomer) -> None:
        """Forget a newcomer and close its socket."""
        self._release(newcomer)
        newcomer.sock.close()

    def _release(self, newcomer: Newcomer) -> None:
        """Forget a newcomer whose socket is handed over or closed."""
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(newcomer.sock)
        self._newcomers.pop(newcomer, None)
        if newcomer.waiting:
            self._waiting.remove(newcomer.source)
            newcomer.waiting = False

    def _on_data(self, newcomer: Newcomer) -> None:
        limit = proxy_v2.MAX_HEADER if newcomer.proxied else self.settings.max_bytes
        room = limit - len(newcomer.buf)
        try:
            data = newcomer.sock.recv(max(1, min(room, 4096)))
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._logs.event(logging.WARNING, "peers closed before registering",
                             newcomer.source, "DTU listener :%d: %s closed before "
                             "registering (got %s)", self.port, newcomer.peer,
                             self._shown(newcomer.buf))
            self._close(newcomer)
            return
        newcomer.buf += data
        now = time.monotonic()
        if self._proxy(newcomer) or self._decide(newcomer, settled=False) or newcomer.held:
            return
        pause = newcomer.budget.spend(len(data), now)
        if pause:  # too fast: stop reading; the quiet gap counts from when reading resumes
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(newcomer.sock)
            newcomer.resume_at = now + pause
            newcomer.quiet_at = math.inf
        else:
            newcomer.quiet_at = now + self.settings.quiet_gap

    def _proxy(self, newcomer: Newcomer) -> bool:
        """Read a balancer's PROXY v2 header, then admit the connection as from the DTU's
        address; refuse a header from elsewhere.  True: it left the listener's reading,
        or waits for the rest of its header."""
        step = proxy_v2.step(bytes(newcomer.buf), newcomer.proxied)
        if isinstance(step, tuple):
            return self._drop(newcomer, *step)
        if step is None or isinstance(step, bool):
            return bool(step)
        if step.local:  # the balancer's health check
            self.counts["proxyLocal"] += 1
            self._close(newcomer)
            return True
        del newcomer.buf[:step.size]
        newcomer.proxied = False
        if step.source is not None:
            self._waiting.remove(newcomer.source)
            newcomer.waiting = False
            newcomer.source, newcomer.peer = step.source, f"{step.source}:{step.source_port}"
            if not self._allowed.allows(newcomer.source):
                return self._drop(newcomer, "refusedNotAllowed", "not in listenAllowFrom")
            refusal = self._waiting.refusal(newcomer.source)
            if refusal is not None:
                return self._drop(newcomer, *refusal)
            self._waiting.add(newcomer.source)
            newcomer.waiting = True
        if self.settings.registration == "none":
            self._hand_over_single(newcomer)
            return True
        return not newcomer.buf

    def _drop(self, newcomer: Newcomer, counter: str, why: str) -> bool:
        """Refuse a newcomer already waiting (see :meth:`_refuse`)."""
        self._release(newcomer)
        self._refuse(counter, newcomer.source, newcomer.sock, why)
        return True

    def _shown(self, buf: bytes | bytearray) -> str:
        """Untrusted registration bytes as a log line may show them."""
        if self._keyed:
            return f"{len(buf)} bytes, not shown: registrations carry a key"
        return hex_prefix(bytes(buf))

    def _decide(self, newcomer: Newcomer, settled: bool) -> bool:
        """Register, hold or close a newcomer whose registration is complete; True when
        it left the listener's reading (handed over or closed)."""
        if newcomer.proxied:
            return False  # its header is not complete
        buf = bytes(newcomer.buf)
        with self._lock:  # the index is kept sorted as drivers come and go
            found = identify(buf, self._ids, self.settings, settled=settled)
            slot = self._slots.get(found.dtu_id) if isinstance(found, Identified) else None
        if found is None:
            return False
        newcomer.quiet_at = math.inf
        if isinstance(found, Identified) and slot is not None:
            refusal = self._access_refusal(slot, newcomer, found)
            if refusal is None:
                self._offer(slot, newcomer, buf[found.end:])
                return True
            counter, why = refusal
        elif len(buf) >= self.settings.max_bytes:
            self.counts["oversize"] += 1
            self._logs.event(logging.WARNING, "connections closed (no registration in "
                             "registrationMaxBytes)", newcomer.source,
                             "DTU listener :%d: %s sent %d bytes without registering (%s); "
                             "closed", self.port, newcomer.peer, len(buf), self._shown(buf))
            self._close(newcomer)
            return True
        else:
            counter = "unknown"
            why = f"unknown DTU {short_text(str(found))}" if not self._keyed else \
                "unknown DTU"
        self.counts[counter] += 1
        self._hold(newcomer)
        self._logs.event(logging.WARNING, f"connections held ({counter})", newcomer.source,
                         "DTU listener :%d: %s: %s (registration %s); closing it after the "
                         "registration timeout", self.port, newcomer.peer, why,
                         self._shown(buf))
        return False

    def _access_refusal(self, slot: DtuSlot, newcomer: Newcomer,
                        found: Identified) -> tuple[str, str] | None:
        """Why the newcomer may not be this DTU: (counter, reason), or None."""
        if not slot.allowed.allows(newcomer.source):
            return "refusedDtuNotAllowed", f"DTU {slot.dtu_id!r} not allowed from " \
                f"{newcomer.source} (dtuAllowFrom)"
        key = slot.access.key
        if key and not key_matches(found.key, key):
            return "badKey", f"DTU {slot.dtu_id!r} with a missing or wrong registrationKey"
        return None

    def _timers(self, now: float) -> None:
        if self._paused.over(now):
            self._sel.register(self._sock, selectors.EVENT_READ, None)
        for newcomer in [n for n in self._newcomers if n.wake() <= now]:
            if newcomer.challenge is not None:
                self._settle(newcomer, now)
            elif newcomer.resume_at <= now and newcomer.deadline > now:
                newcomer.resume_at = math.inf
                newcomer.quiet_at = now + self.settings.quiet_gap
                self._sel.register(newcomer.sock, selectors.EVENT_READ, newcomer)
            elif newcomer.quiet_at <= now and newcomer.deadline > now:
                newcomer.quiet_at = math.inf  # looked at again when the next byte comes
                self._decide(newcomer, settled=True)
            elif newcomer.deadline <= now and newcomer.proxied and newcomer.buf:
                self._drop(newcomer, *proxy_v2.unfinished(bytes(newcomer.buf)))  # cut short
            elif newcomer.deadline <= now:
                self._expire(newcomer)

    def _expire(self, newcomer: Newcomer) -> None:
        """The registration timeout ran out."""
        if not newcomer.held and self._decide(newcomer, settled=True):
            return  # registered (an exact match at the timeout) or closed
        if not newcomer.held:
            self.counts["silent"] += 1
            self._logs.event(logging.WARNING, "connections closed (no registration in "
                             "registrationTimeout)", newcomer.source,
                             "DTU listener :%d: %s did not register within %.3g s (got %s); "
                             "closed", self.port, newcomer.peer, self.settings.timeout,
                             self._shown(newcomer.buf))
        self._close(newcomer)

    def _settle(self, newcomer: Newcomer, now: float) -> None:
        """keep-existing: the challenger's time is up."""
        assert newcomer.challenge is not None
        slot, rest, answers = newcomer.challenge
        self._challenged.discard(slot.dtu_id)
        self._release(newcomer)
        newcomer.sock.setblocking(True)
        if slot.settle(newcomer.sock, newcomer.peer, rest, answers, now):
            self.counts["registered"] += 1
            self.counts["replaced"] += 1
            return
        self.counts["duplicateRefused"] += 1
        self._logs.event(logging.WARNING, "connections refused (duplicate id)",
                         newcomer.source, "DTU listener :%d: %s claims DTU id %r, whose "
                         "connection from %s still answers; closed (duplicateId "
                         "keep-existing)", self.port, newcomer.peer, slot.dtu_id, slot.peer)
        newcomer.sock.close()


__all__ = ["COUNTERS", "DtuListener"]
