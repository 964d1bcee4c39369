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

A backlog is tracked by ids: ``tail[device]`` is the newest id appended unclaimed for a
device, ``handed`` the newest id the replay handed to paho; the device has a backlog
while ``tail > handed`` and the spool has pending messages (replay goes in id order).
"""

from __future__ import annotations

import logging

from .outbox import Message
from .settings import StoreAndForwardSettings
from .spool import Message as Row
from .spool import ReplayPacer, Spool, SpoolError, Stored

log = logging.getLogger("edgemodbus.mqtt")


class Forwarder:
    """The spool and its pacer as the sender uses them (MQTT thread only, except
    :meth:`stats`)."""

    def __init__(self, settings: StoreAndForwardSettings) -> None:
        self.spool = Spool(settings.path, max_bytes=settings.max_bytes,
                           max_age_s=settings.max_age_s, synchronous=settings.synchronous)
        self.pacer = ReplayPacer(settings.replay_rate_per_s,
                                 bytes_per_s=settings.replay_bytes_per_s)
        self.tail: dict[str, int] = self.spool.device_tails()  # kept from before: a backlog
        self.handed = 0
        self.done: list[int] = []  # completed ids, acked once per turn
        self.replayed = 0
        self.errors = 0
        self.credit = 0  # live messages appended behind a backlog, not yet replayed

    def backlogged(self, device: str | None) -> bool:
        """True while ``device`` has messages pending in the spool (its live ones must
        queue behind them)."""
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
        ids = self._append(messages, claimed=False)
        for message, i in zip(messages[len(messages) - len(ids):], ids, strict=True):
            self.tail[message.device or ""] = i
        return ids

    def claim(self, messages: list[Message]) -> list[int]:
        """Append claimed (live QoS 1, handed to paho right away): one id per message,
        0 for a message the spool dropped at once (sent anyway, never acked)."""
        ids = self._append(messages, claimed=True)
        return [0] * (len(messages) - len(ids)) + ids

    def _append(self, messages: list[Message], *, claimed: bool) -> list[int]:
        if not messages:
            return []
        try:
            return self.spool.append(
                [Row(m.device or "", m.topic, m.payload, m.qos, m.retain) for m in messages],
                claimed=claimed)
        except SpoolError as exc:  # the disk is full or failing: the messages are lost
            self.errors += len(messages)
            log.error("store-and-forward: %d messages not kept: %s", len(messages), exc)
            return []

    def keep_live(self, messages: list[Message]) -> None:
        """Live messages of devices with a backlog, while connected: appended unclaimed,
        and they add to the replay's budget (see the module docstring)."""
        self.credit += len(self.keep(messages))

    def replay_batch(self, room: int) -> list[Stored]:
        """The next messages to replay (claimed), at most ``room`` and the pacer's
        budget plus the live credit."""
        n = min(self.pacer.budget() + self.credit, room)
        if n <= 0 or self.spool.pending_count() == 0:
            return []
        try:
            batch = self.spool.next_batch(n)
        except SpoolError as exc:
            log.error("store-and-forward: replay failed: %s", exc)
            return []
        if batch:
            self.handed = max(self.handed, batch[-1].id)
        return batch

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
        if self.spool.pending_count() == 0:
            self.credit = 0
            return None
        return 0.0 if self.credit else self.pacer.delay()

    def settle(self) -> None:
        """Delete what completed this turn (one transaction)."""
        if self.done:
            done, self.done = self.done, []
            try:
                self.spool.ack(done)
            except SpoolError as exc:  # kept: replayed again later (a duplicate)
                log.error("store-and-forward: acknowledgements not recorded: %s", exc)

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
        return out

    def close(self) -> None:
        self.settle()
        self.spool.close()
