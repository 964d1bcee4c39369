"""How fast the spool is replayed: a token bucket the sender asks before each batch, so
that a backlog of hours never crowds live data out of the connection."""

from __future__ import annotations

import math
import time
from collections.abc import Callable


class ReplayPacer:
    """A token bucket in messages per second and, optionally, bytes per second.

    Full at the start (``burst`` messages, by default one second's worth), refilled
    continuously.  The sender asks :meth:`budget` how many spooled messages it may take
    now, then reports what it sent with :meth:`spend`.  A message's bytes are only known
    once it was read, so the byte bucket may go into debt: the budget is 0 until the
    debt is paid off (an empty byte bucket, exactly 0, still lets one batch go).
    :meth:`delay` says how long until the budget is at least one (a select timeout).
    Pure: the clock is injected; not thread-safe (the MQTT thread owns it)."""

    def __init__(self, messages_per_s: float, *, bytes_per_s: float | None = None,
                 burst: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not messages_per_s > 0 or math.isinf(messages_per_s):
            raise ValueError(f"messages_per_s {messages_per_s!r} must be a finite number > 0")
        if bytes_per_s is not None and (not bytes_per_s > 0 or math.isinf(bytes_per_s)):
            raise ValueError(f"bytes_per_s {bytes_per_s!r} must be a finite number > 0 "
                             "or None")
        if burst is not None and not (burst >= 1 and math.isfinite(burst)):
            raise ValueError(f"burst {burst!r} must be a finite number >= 1 (messages)")
        self.rate = float(messages_per_s)
        self.byte_rate = None if bytes_per_s is None else float(bytes_per_s)
        self.burst = max(1.0, self.rate if burst is None else float(burst))
        # the byte bucket holds as many seconds of bytes as the message bucket of messages
        self.byte_burst = (None if self.byte_rate is None
                           else self.byte_rate * self.burst / self.rate)
        self._clock = clock
        self._tokens = self.burst
        self._byte_tokens = self.byte_burst
        self._at = clock()

    def _refill(self) -> None:
        now = self._clock()
        elapsed = max(0.0, now - self._at)  # a clock that goes back refills nothing
        self._at = now
        self._tokens = min(self.burst, self._tokens + elapsed * self.rate)
        if self.byte_rate is not None and self._byte_tokens is not None:
            assert self.byte_burst is not None
            self._byte_tokens = min(self.byte_burst,
                                    self._byte_tokens + elapsed * self.byte_rate)

    def budget(self) -> int:
        """How many messages may be replayed now (0 while either bucket is empty)."""
        self._refill()
        if self._byte_tokens is not None and self._byte_tokens < 0:
            return 0
        return int(self._tokens + 1e-9)  # 0.3 + 0.7 tokens is a whole one

    def spend(self, messages: int, nbytes: int = 0) -> None:
        """``messages`` messages of ``nbytes`` bytes in all were replayed."""
        if messages < 0 or nbytes < 0:
            raise ValueError(f"messages ({messages}) and nbytes ({nbytes}) must be >= 0")
        self._refill()
        self._tokens -= messages
        if self._byte_tokens is not None:
            self._byte_tokens -= nbytes

    def delay(self) -> float:
        """Seconds until :meth:`budget` is at least 1 (0.0: now)."""
        self._refill()
        wait = max(0.0, (1.0 - self._tokens) / self.rate)
        if self._byte_tokens is not None and self.byte_rate is not None:
            wait = max(wait, -self._byte_tokens / self.byte_rate)  # the debt paid off
        return wait
