"""Leadership of a redundant pair (docs/deploy.md "Redundant pair"): a lease in Redis.

Two gateways run one config; only the holder of the lease polls the connect-mode devices
(a PLC over Modbus TCP, a serial device server: one master at a time).  Redis because
it is one small process on a gateway-class host and ``SET NX PX`` plus a compare-and-
extend script is the whole protocol (an etcd lease needs a 3-node cluster to be worth
it); the client is the maintained ``redis`` package (edgemodbus[fleet]).

- acquire: ``SET <prefix>leader <token> NX PX <leaseMs>``; on success ``INCR
  <prefix>fence`` (one script, atomic): the fencing token, higher at each new leader;
- renew every ``renewMs`` (default leaseMs/3): a script extends the key only if it still
  holds our token;
- the lease is valid until the *start* of the last successful renewal plus leaseMs, on
  the monotonic clock (a renewal's reply may come late; its start is the safe side);
- requests go out only before that less a margin (:meth:`Lease.deadline`): the line
  worker and the engine in C start none at or after it (line/worker.py ``lease``), so a
  leader paused past its lease sends nothing when it wakes, before its lease thread
  has even looked.

:class:`Lease` is the state machine (no thread, clock injected: unit-tested with a fake
clock); :class:`LeaseKeeper` runs it on a thread.  A paused process (``kill -STOP``, a
long GC) that wakes checks the time before anything else and gives up a lease whose
time passed, whatever Redis says.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any, Protocol

from ..errors import ModbusConnectionError
from ..line.log_limit import LogLimiter, short_text

log = logging.getLogger("edgemodbus.lease")

LOG_INTERVAL = 10.0
"""Seconds per line of a kind of failure to reach the lease engine (a standby retries
every renewMs/2, as often as 20 times a second: one line each flooded the log)."""

_ACQUIRE = """
if redis.call('SET', KEYS[1], ARGV[1], 'NX', 'PX', ARGV[2]) then
  return redis.call('INCR', KEYS[2])
end
return 0
"""
_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('PEXPIRE', KEYS[1], ARGV[2])
end
return 0
"""
_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('DEL', KEYS[1])
end
return 0
"""


class LeaseEngine(Protocol):
    """Where the lease lives (RedisEngine; a fake in unit tests)."""

    def acquire(self, token: str, ttl_ms: int) -> int | None:
        """Take the lease if free: the fencing token, else None."""
        ...

    def renew(self, token: str, ttl_ms: int) -> bool:
        """Extend the lease if ``token`` still holds it."""
        ...

    def release(self, token: str) -> None:
        """Give the lease up if ``token`` holds it."""
        ...


class RedisEngine:
    """The lease in Redis under ``prefix`` (keys ``<prefix>leader``, ``<prefix>fence``);
    every call times out after ``timeout`` seconds (a renewal must not hang past the
    lease)."""

    def __init__(self, url: str, prefix: str, timeout: float) -> None:
        import redis  # edgemodbus[fleet]

        self.client: Any = redis.Redis.from_url(url, socket_timeout=timeout,
                                                socket_connect_timeout=timeout)
        self.keys = [f"{prefix}leader", f"{prefix}fence"]
        self._acquire = self.client.register_script(_ACQUIRE)
        self._renew = self.client.register_script(_RENEW)
        self._release = self.client.register_script(_RELEASE)

    def acquire(self, token: str, ttl_ms: int) -> int | None:
        fence = int(self._acquire(keys=self.keys, args=[token, ttl_ms]))
        return fence or None

    def renew(self, token: str, ttl_ms: int) -> bool:
        return bool(int(self._renew(keys=self.keys[:1], args=[token, ttl_ms])))

    def release(self, token: str) -> None:
        self._release(keys=self.keys[:1], args=[token])

    def close(self) -> None:
        self.client.close()


class Lease:
    """One instance's view of the lease: held or not, until when, its fencing token.

    :meth:`step` makes one attempt (acquire or renew) and says when to make the next;
    ``on_gain(fence)`` and ``on_loss(reason)`` run on the caller's thread at each change.
    """

    def __init__(self, engine: LeaseEngine, ttl_ms: int, renew_ms: int, *,
                 token: str | None = None, clock: Callable[[], float] = time.monotonic,
                 on_gain: Callable[[int], None] = lambda fence: None,
                 on_loss: Callable[[str], None] = lambda reason: None,
                 margin_ms: int | None = None) -> None:
        if renew_ms * 3 > ttl_ms:
            raise ValueError(f"renewMs {renew_ms} must be at most a third of leaseMs "
                             f"{ttl_ms} (three renewals per lease)")
        margin_ms = default_margin_ms(ttl_ms) if margin_ms is None else margin_ms
        if not 0 <= margin_ms * 2 <= ttl_ms:
            raise ValueError(f"marginMs {margin_ms} must be 0..{ttl_ms // 2} (at most half "
                             f"of leaseMs {ttl_ms})")
        self.margin = margin_ms / 1000.0
        self.engine = engine
        self.ttl = ttl_ms / 1000.0
        self.ttl_ms = ttl_ms
        self.renew_period = renew_ms / 1000.0
        self.token = token or uuid.uuid4().hex
        self.clock = clock
        self.on_gain = on_gain
        self.on_loss = on_loss
        self.held = False
        self.fence: int | None = None
        self.expires = 0.0  # on self.clock; meaningful while held
        self._until = (False, 0.0)  # (held, expires - margin): what deadline() reads
        self._lock = threading.Lock()
        self._watchers: list[Callable[[], None]] = []  # told of a loss: watch()
        self._logs = LogLimiter(log, interval=LOG_INTERVAL, burst=1, clock=clock)
        self._failing = False  # the last attempt could not reach the engine
        self.counts = {"gained": 0, "lost": 0, "engineErrors": 0}
        """Leaderships gained and lost, attempts that could not reach the engine (its
        errors: refused, timed out, a reply that is not RESP or not the script's)."""

    def deadline(self) -> float:
        """The time (on the lease's clock, the monotonic one) before which a request to a
        gated device may start: the lease's known end less the margin; 0.0 when not held.
        Read by line workers before every request (no lock: one tuple read)."""
        held, until = self._until
        return until if held else 0.0

    def watch(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` (on the thread that saw it) whenever the lease is lost: a line
        gated by it reads the deadline again at once (LineWorker.lease_changed), not at
        the end of the engine's run that began while it held."""
        with self._lock:
            self._watchers = [*self._watchers, fn]

    def unwatch(self, fn: Callable[[], None]) -> None:
        """Stop calling ``fn`` (an equal bound method will do)."""
        with self._lock:
            self._watchers = [w for w in self._watchers if w != fn]

    def valid_for(self) -> float:
        """Seconds the lease is known to stay ours (0 when not held or expired)."""
        with self._lock:
            return max(0.0, self.expires - self.clock()) if self.held else 0.0

    def require(self, seconds: float, what: str = "write") -> None:
        """Raise :class:`NotLeaderError` unless the lease is held for at least
        ``seconds`` more (a write's timeout: it must not reach the PLC after the lease)."""
        if not self.check():
            raise NotLeaderError(f"{what} refused: not the leader of the pair (the other "
                                 "instance holds the lease, or none does)")
        left = self.valid_for()
        if left < seconds:
            raise NotLeaderError(f"{what} refused: not the leader for long enough (the "
                                 f"lease ends in {left:.3f} s, the {what} may take "
                                 f"{seconds:.3f} s)")

    def check(self) -> bool:
        """Whether the lease is held now; one whose time passed is given up here (the
        first thing a woken process does)."""
        with self._lock:
            expired = self.held and self.clock() >= self.expires
        if expired:
            self._lose("the lease time passed since the last renewal (paused?)")
        return self.held

    def step(self) -> float:
        """One acquire or renewal; the seconds until the next step."""
        self.check()
        self._logs.flush()
        start = self.clock()
        if self.held:
            try:
                ok = self.engine.renew(self.token, self.ttl_ms)
            except Exception as exc:
                self._unreachable(exc)
                self._lose(f"renewal failed: {short_text(str(exc), 200)}")
                return self.retry_period
            self._reachable()
            if not ok:
                self._lose("another instance holds the lease")
                return self.retry_period
            with self._lock:
                self.expires = start + self.ttl
                self._until = (self.held, self.expires - self.margin)
            self.check()  # a renewal that took longer than the lease
            return self.renew_period if self.held else self.retry_period
        try:
            fence = self.engine.acquire(self.token, self.ttl_ms)
        except Exception as exc:
            self._unreachable(exc)
            return self.retry_period
        self._reachable()
        if fence is None:
            return self.retry_period
        with self._lock:
            self.held, self.fence, self.expires = True, fence, start + self.ttl
            self._until = (True, self.expires - self.margin)
        if not self.check():
            return self.retry_period
        self.counts["gained"] += 1
        log.info("lease: leader (fencing token %d)", fence)
        self.on_gain(fence)
        return self.renew_period

    def _unreachable(self, exc: Exception) -> None:
        """One failed attempt: counted, one line per kind of error and interval (the
        error's words bounded: a fake server's garbage is quoted in them)."""
        self.counts["engineErrors"] += 1
        self._failing = True
        self._logs.event(logging.WARNING, "failed attempts to reach the lease engine",
                         type(exc).__name__, "lease: cannot reach the lease engine: %s",
                         short_text(str(exc), 200))

    def _reachable(self) -> None:
        """An attempt the engine answered: one line when it follows failures."""
        if self._failing:
            self._failing = False
            self._logs.flush(force=True)
            log.info("lease: the lease engine answers again")

    @property
    def retry_period(self) -> float:
        """A standby's period of acquire attempts: half the renew period (it takes over
        within the lease time plus this plus its devices' first cycle)."""
        return self.renew_period / 2

    def release(self) -> None:
        """Give the lease up (a clean stop): the standby takes over at its next try."""
        was = self.held
        self._lose("released")
        if was:
            try:
                self.engine.release(self.token)
            except Exception as exc:
                log.warning("lease: release failed (%s); it expires by itself", exc)

    def _lose(self, reason: str) -> None:
        with self._lock:
            was, self.held, self.fence = self.held, False, None
            self._until = (False, 0.0)
        if was:
            self.counts["lost"] += 1
            log.warning("lease: no longer the leader: %s", reason)
            for watcher in self._watchers:
                watcher()
            self.on_loss(reason)


def default_margin_ms(ttl_ms: int) -> int:
    """The margin when ``marginMs`` is left out: a tenth of the lease, at least 100 ms
    and at most half of it.  It covers a request's frame on its way to the slave (a
    256-byte RTU frame at 9600 Bd: 0.27 s) and the two clocks' rates."""
    return min(ttl_ms // 2, max(100, ttl_ms // 10))


class LeaseKeeper:
    """:meth:`Lease.step` on its own thread until :meth:`stop` (which releases)."""

    def __init__(self, lease: Lease) -> None:
        self.lease = lease
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lease", daemon=True)

    def start(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def _run(self) -> None:
        delay = 0.0
        while not self._stop.wait(delay):
            try:
                delay = self.lease.step()
            except Exception:  # a callback's bug: keep the lease honest regardless
                log.exception("lease: step failed")
                delay = self.lease.retry_period

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self.lease.release()


class NotLeaderError(ModbusConnectionError):
    """A write refused on the standby, or where the lease may end before it is done
    (a ModbusConnectionError: callers that handle a device not running handle it)."""


__all__ = ["Lease", "LeaseEngine", "LeaseKeeper", "NotLeaderError", "RedisEngine",
           "default_margin_ms"]
