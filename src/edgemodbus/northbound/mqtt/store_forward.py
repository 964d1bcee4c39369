"""Store-and-forward in the sender: when data messages go to the spool, and the replay.

Only when ``mqtt.storeAndForward`` is set (otherwise the sender never makes a
:class:`Forwarder` and nothing here runs).  Everything runs on the MQTT thread; the
spool's life cycle of an id is in ``spool/__init__.py``.  Only data messages (item
updates, batches) are spooled; statuses, the gateway's messages, replies and snapshots
are not (a stale status or reply replayed hours later would mislead).

The rules, per turn of the MQTT thread:

* not connected (an outage): every queued report becomes messages appended to the
  spool, unclaimed (one transaction), instead of waiting in the in-memory queue; so
  an outage is bounded by the spool's ``maxBytes`` and ``maxAgeS``, not by
  ``queueSize``;
* connected: a device with a *backlog* (messages of it still pending in the spool)
  appends its live messages to the spool too, unclaimed, behind its backlog: its order
  holds.  Devices without a backlog publish directly: at QoS 1 appended *claimed*
  first (kept until PUBACK), at QoS 0 not spooled at all;
* after the live messages, the replay: the oldest pending messages, as many as paho's
  window has room for and the :class:`ReplayPacer` allows, published with
  ``retain=False`` (a replayed retained value would replace a newer one).  Live
  messages that queued behind a backlog add to the pacer's budget (``credit``): they
  would have been sent anyway, so a device whose live rate exceeds ``replayRatePerS``
  still drains its backlog, at ``replayRatePerS`` beyond its live rate;
* a completion (PUBACK at QoS 1, written out at QoS 0) deletes the message, one
  transaction per turn; a message paho refused goes back to pending;
* a new connection: what the old one lost (QoS 0 not written) goes back to pending;
  QoS 1 messages in paho's window stay claimed, paho sends them again.

When the spool cannot be written (the disk full, an I/O error): what it should have kept
goes to a bounded queue in memory (``memoryQueueSize`` messages; beyond it the oldest
are dropped, counted as ``memoryDropped``), and the spool is tried again after a backoff
(1 s, doubling up to 30 s): the queue is then appended to it in one transaction.  Live
QoS 1 messages go out without a spool id meanwhile (not kept across a crash), and while
connected the queue is replayed after what the spool still holds, so data flows as soon
as the broker is back.  Acknowledgements that fail are kept and tried again with the
spool.  Errors are logged a few lines per 10 s (line/log_limit.py), then summed up.

A backlog is tracked by ids: ``tail[device]`` is the newest id appended unclaimed for a
device, ``handed`` the newest id the replay handed to paho; the device has a backlog
while ``tail > handed`` and the spool has pending messages (replay goes in id order).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Callable

from ...line.log_limit import LogLimiter
from .outbox import Message
from .settings import StoreAndForwardSettings
from .spool import Message as Row
from .spool import ReplayPacer, Spool, SpoolError, SpoolUnavailable, Stored

log = logging.getLogger("edgemodbus.mqtt")

RETRY_MIN = 1.0  # s: the first retry of a spool that refused a write
RETRY_MAX = 30.0


class NoSpool:
    """Stands in for a spool that could not be opened because its disk is full or
    failing: it keeps nothing, every append raises :class:`SpoolError` (so messages
    wait in memory), and :meth:`Forwarder.retry` opens the real one later."""

    def __init__(self, path: str, why: str) -> None:
        self.path, self.why = path, why

    def device_tails(self) -> dict[str, int]:
        return {}

    def pending_count(self) -> int:
        return 0

    def append(self, rows: list[Row], *, claimed: bool = False) -> list[int]:
        raise SpoolError(self.why)

    def next_batch(self, limit: int) -> list[Stored]:
        return []

    def ack(self, ids: list[int]) -> int:
        return 0

    def release(self, ids: list[int]) -> None:
        pass

    def stats(self) -> dict[str, int]:
        return dict.fromkeys(("appended", "acked", "released", "droppedSize", "droppedAge",
                              "stored", "pending", "inflight", "bytes", "fileBytes"), 0)

    def close(self) -> None:
        pass


class Forwarder:
    """The spool and its pacer as the sender uses them (MQTT thread only, except
    :meth:`stats`)."""

    def __init__(self, settings: StoreAndForwardSettings,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings
        self.clock = clock  # the backoff's (replaceable in tests)
        self.limiter = LogLimiter(log, interval=10.0, burst=3, clock=clock)
        # the spool refused a write: messages wait here (oldest first) until it takes
        # them again; while failing, retry_at is when to try next (a doubling backoff)
        self.memory: deque[Message] = deque()
        self.memory_limit = settings.memory_queue_size
        self._in_memory: Counter[str] = Counter()  # per device
        self.memory_dropped = 0
        self.retry_at = 0.0
        self.failing = False  # the spool refused the last write (or could not be opened)
        self._failures = 0
        self._ack_after = 0.0  # acknowledgements that failed wait until then
        self._backoff = RETRY_MIN
        self.spool: Spool | NoSpool
        try:
            self.spool = self._open()
        except SpoolUnavailable as exc:  # the disk full or failing: polling goes on
            self.spool = NoSpool(settings.path, str(exc))
            self._failed("the spool cannot be opened", exc)
        self.pacer = ReplayPacer(settings.replay_rate_per_s,
                                 bytes_per_s=settings.replay_bytes_per_s)
        self.tail: dict[str, int] = self.spool.device_tails()  # kept from before: a backlog
        self.handed = 0
        self.done: list[int] = []  # completed ids, acked once per turn
        self.replayed = 0
        self.errors = 0
        self.credit = 0  # live messages appended behind a backlog, not yet replayed

    def _open(self) -> Spool:
        s = self.settings
        return Spool(s.path, max_bytes=s.max_bytes, max_age_s=s.max_age_s,
                     synchronous=s.synchronous)

    def backlogged(self, device: str | None) -> bool:
        """True while ``device`` has messages pending in the spool (its live ones must
        queue behind them)."""
        if self._in_memory.get(device or ""):
            return True
        if not self.tail:
            return False
        tail = self.tail.get(device or "", 0)
        if tail <= self.handed:
            return False
        if self.spool.pending_count() == 0:  # acked or dropped meanwhile: nothing ahead
            self.tail.clear()
            self.credit = 0
            return False
        return True

    def keep(self, messages: list[Message]) -> list[int]:
        """Append unclaimed (an outage, or a backlogged device).  Their ids (the oldest
        of a batch larger than maxBytes get none: dropped, counted by the spool)."""
        if (self.memory or self.failing) and not self.retry():  # behind those in memory
            self._to_memory(messages)
            return []
        ids = self._append(messages, claimed=False)
        if ids is None:
            self._to_memory(messages)
            return []
        for message, i in zip(messages[len(messages) - len(ids):], ids, strict=True):
            self.tail[message.device or ""] = i
        return ids

    def claim(self, messages: list[Message]) -> list[int]:
        """Append claimed (live QoS 1, handed to paho right away): one id per message,
        0 for a message the spool dropped at once (sent anyway, never acked)."""
        ids = None if self.failing else self._append(messages, claimed=True)
        if ids is None:  # the spool is failing: sent all the same, not kept
            return [0] * len(messages)
        return [0] * (len(messages) - len(ids)) + ids

    def _append(self, messages: list[Message], *, claimed: bool) -> list[int] | None:
        """The spool's ids, or None when it refused the write (then failing: retried
        after the backoff)."""
        if not messages:
            return []
        try:
            ids = self.spool.append(
                [Row(m.device or "", m.topic, m.payload, m.qos, m.retain) for m in messages],
                claimed=claimed)
        except SpoolError as exc:  # the disk is full or failing
            self.errors += len(messages)
            self._failed("spool writes failed", exc)
            return None
        self._recovered()
        return ids

    def _failed(self, kind: str, exc: SpoolError) -> None:
        """A write refused: try again after the backoff (doubling to RETRY_MAX)."""
        if not self.failing:
            self._backoff = RETRY_MIN
        else:
            self._backoff = min(self._backoff * 2, RETRY_MAX)
        self.failing = True
        self._failures += 1
        self.retry_at = self.clock() + self._backoff
        self.limiter.event(logging.ERROR, f"store-and-forward {kind}", self.spool.path,
                           "store-and-forward: %s (%s); messages wait in memory (at "
                           "most %d), the spool is tried again in %.0f s", kind, exc,
                           self.memory_limit, self._backoff)

    def _recovered(self) -> None:
        if self.failing:
            self.failing = False
            self.retry_at = 0.0
            self.limiter.event(logging.WARNING, "store-and-forward spool recoveries",
                               self.spool.path, "store-and-forward: the spool %s takes "
                               "writes again", self.spool.path)

    def _to_memory(self, messages: list[Message]) -> None:
        """Keep ``messages`` in memory behind the others; beyond the bound the oldest
        are dropped (counted, logged a few lines per interval)."""
        memory = self.memory
        for message in messages:
            memory.append(message)
            self._in_memory[message.device or ""] += 1
        over = len(memory) - self.memory_limit
        if over > 0:
            for _ in range(over):
                self._forget(memory.popleft())
            self.memory_dropped += over
            self.limiter.event(logging.ERROR, "messages dropped from memory",
                               self.spool.path, "store-and-forward: %d oldest messages "
                               "dropped: the spool refuses writes and memoryQueueSize %d "
                               "is full", over, self.memory_limit)

    def _forget(self, message: Message) -> None:
        key = message.device or ""
        self._in_memory[key] -= 1
        if not self._in_memory[key]:
            del self._in_memory[key]

    def retry(self) -> bool:
        """Unless the backoff is still on: the acknowledgements kept, applied (they make
        room), then the messages waiting in memory appended to the spool (one
        transaction).  True when the spool took them (nothing waits in memory)."""
        if self.failing and self.clock() < self.retry_at:
            return False
        failures = self._failures
        if isinstance(self.spool, NoSpool):
            try:
                self.spool = self._open()
            except SpoolError as exc:
                self._failed("the spool cannot be opened", exc)
                return False
            self.tail = self.spool.device_tails()
        self._ack()
        if self.memory and self._failures == failures:
            waiting = list(self.memory)
            ids = self._append(waiting, claimed=False)
            if ids is None:
                return False
            self.memory.clear()
            self._in_memory.clear()
            for message, i in zip(waiting[len(waiting) - len(ids):], ids, strict=True):
                self.tail[message.device or ""] = i
        if self._failures != failures:
            return False
        self._recovered()
        return True

    def tick(self) -> None:
        """Once per turn of the MQTT thread: the retry when it is due, the log
        summaries."""
        if self.failing and self.clock() >= self.retry_at:
            self.retry()
        self.limiter.flush()

    def keep_live(self, messages: list[Message]) -> None:
        """Live messages of devices with a backlog, while connected: appended unclaimed,
        and they add to the replay's budget (see the module docstring)."""
        self.credit += len(self.keep(messages))

    def replay_batch(self, room: int) -> list[Stored]:
        """The next messages to replay, at most ``room`` and the pacer's budget plus the
        live credit: the spool's oldest (claimed), then those waiting in memory (id 0,
        taken off the queue: :meth:`unsent` puts back what paho refused)."""
        n = min(self.pacer.budget() + self.credit, room)
        if n <= 0:
            return []
        batch: list[Stored] = []
        readable = True
        if self.spool.pending_count():
            try:
                batch = self.spool.next_batch(n)
            except SpoolError as exc:
                readable = False
                self.limiter.event(logging.ERROR, "store-and-forward replays failed",
                                   self.spool.path, "store-and-forward: replay failed: %s",
                                   exc)
            if batch:
                self.handed = max(self.handed, batch[-1].id)
        memory = self.memory
        if memory and (not readable or self.spool.pending_count() == 0):
            while memory and len(batch) < n:
                message = memory.popleft()
                self._forget(message)
                batch.append(Stored(0, message.device or "", message.topic,
                                    message.payload, message.qos, message.retain, 0.0))
        return batch

    def unsent(self, batch: list[Stored]) -> None:
        """Replayed messages paho did not take: spooled ones pending again, the others
        back to the front of the memory queue."""
        self.release([(row.id, row.device or None) for row in batch])
        for row in reversed([row for row in batch if not row.id]):
            self.memory.appendleft(Message(row.device or None, row.topic, row.payload,
                                           row.qos, row.retain))
            self._in_memory[row.device] += 1

    def replayed_batch(self, messages: int, nbytes: int) -> None:
        """``messages`` of ``nbytes`` were replayed: the live credit first, the rest from
        the pacer."""
        free = min(self.credit, messages)
        self.credit -= free
        paced = messages - free
        if paced:
            self.pacer.spend(paced, nbytes * paced // messages)
        self.replayed += messages

    def delay(self) -> float | None:
        """How long the MQTT thread may sleep before the next replay step (None: no
        backlog)."""
        if self.spool.pending_count() == 0 and not self.memory:
            self.credit = 0
            return None
        return 0.0 if self.credit else self.pacer.delay()

    def settle(self) -> None:
        """Delete what completed this turn (one transaction; also while writes are
        refused: deletes make room), unless deletes failed and their backoff is on."""
        if self.done and self.clock() >= self._ack_after:
            self._ack()

    def _ack(self) -> None:
        if not self.done:
            return
        try:
            self.spool.ack(self.done)
        except SpoolError as exc:  # kept: tried again after the backoff
            self._failed("acknowledgements failed", exc)
            self._ack_after = self.retry_at
        else:
            self.done = []
            self._ack_after = 0.0

    def release(self, taken: list[tuple[int, str | None]]) -> None:
        """Messages paho did not take (or lost), by (id, device): pending again, so
        their devices have a backlog until the replay has handed them over."""
        taken = [(i, device) for i, device in taken if i]
        if not taken:
            return
        self.spool.release([i for i, _ in taken])
        for i, device in taken:
            key = device or ""
            self.tail[key] = max(self.tail.get(key, 0), i)
        self.handed = min(self.handed, min(i for i, _ in taken) - 1)

    def stats(self) -> dict[str, int]:
        out = self.spool.stats()
        out["replayed"] = self.replayed
        out["errors"] = self.errors
        out["memory"] = len(self.memory)  # read from another thread: a glance
        out["memoryDropped"] = self.memory_dropped
        return out

    def close(self) -> None:
        """Acknowledgements applied, what waits in memory appended (both tried once
        more, whatever the backoff: the last chance), then the spool closed."""
        self.retry_at = 0.0
        self.retry()
        if self.memory:
            log.error("store-and-forward: %d messages in memory lost at stop: the spool "
                      "%s refuses writes", len(self.memory), self.spool.path)
        self.limiter.flush(force=True)
        self.spool.close()
