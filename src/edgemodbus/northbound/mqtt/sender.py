"""The MQTT thread's side of the outbox: queued messages handed to the paho client while
its in-flight window has room, control messages first, then item updates (one message
per update, or in mode "batch" one per device and cycle), then snapshots.

Every message reaches paho in one place, :meth:`Sender.hand_over` (``client.publish``,
paho's public API), and its completion is observed in one place, :meth:`Sender.settle`
(the ``MQTTMessageInfo`` that publish() returned: QoS 0 once written to the socket,
QoS 1 and 2 once the broker confirmed).  Between the two, a :class:`Message` sits in the
window (outbox.Message: device, topic, payload, qos, retain) beside its spool id (0: not
spooled).  With ``mqtt.storeAndForward`` set, a :class:`~.store_forward.Forwarder`
decides which data messages go to the spool and replays it (store_forward.py says when);
without it nothing of that runs."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import TYPE_CHECKING, Any

from ...config import ConfigError, Problem
from .devices import AttachedDevice
from .outbox import Message, Outbox, Report
from .payload import batch_payload, dumps, encode_item, now
from .settings import MqttSettings
from .spool import SpoolError
from .store_forward import Forwarder

if TYPE_CHECKING:
    from paho.mqtt.client import Client, MQTTMessageInfo

log = logging.getLogger("edgemodbus.mqtt")

# paho numbers messages (QoS 0 too) with 16-bit ids: never hold more than half of them
_WINDOW_CAP = 32_768
# reports taken from the outbox per round: the lock is never held for long
_TAKE = 512


class Sender:
    """Moves messages from the outbox into the paho client (on the MQTT thread only) and
    keeps the window of messages paho has taken but not yet sent or confirmed."""

    def __init__(self, outbox: Outbox, settings: MqttSettings, paho: ModuleType,
                 gateway_id: str, item_topic: Callable[[str, str], str],
                 connected: threading.Event,
                 devices: Mapping[str, AttachedDevice] | None = None) -> None:
        self._outbox = outbox
        self._devices: Mapping[str, AttachedDevice] = {} if devices is None else devices
        self.settings = settings
        self._paho = paho
        self.gateway_id = gateway_id
        self.item_topic = item_topic
        self._connected = connected
        self._batch = settings.mode == "batch"
        self._size = min(settings.max_inflight * 4, _WINDOW_CAP)
        self.window: deque[tuple[MQTTMessageInfo, Message, int]] = deque()
        self.forwarder: Forwarder | None = None  # open_spool(): storeAndForward is set

    def open_spool(self) -> None:
        """Open the spool when ``mqtt.storeAndForward`` is set (at start(); the outbox no
        longer bounds an outage by queueSize: the spool's bounds do)."""
        spool = self.settings.store_and_forward
        if spool is not None and self.forwarder is None:
            try:
                self.forwarder = Forwarder(spool)
            except SpoolError as exc:  # in use by another process, not a spool file, ...
                raise ConfigError([Problem("mqtt.storeAndForward.path", spool.path,
                                           str(exc))]) from None
            with self._outbox.lock:
                self._outbox.spooling = True
                self._outbox.spool_memory = spool.memory_queue_size

    def close_spool(self) -> None:
        if self.forwarder is not None:
            self.forwarder.close()

    # -- the seam: to paho, and back -------------------------------------------------------
    def hand_over(self, client: Client, message: Message, spool_id: int = 0) -> bool:
        """Hand one message to paho (``client.publish``).  False: not taken (retry
        later); an invalid topic or payload is refused for good (logged, counted, True;
        a spooled one is deleted from the spool)."""
        try:
            info = client.publish(message.topic, message.payload, qos=message.qos,
                                  retain=message.retain)
        except ValueError as exc:  # an invalid topic, a payload over 256 MB: never retried
            self._outbox.count("publishErrors")
            log.error("MQTT publish to %r refused: %s", message.topic, exc)
            if spool_id and self.forwarder is not None:
                self.forwarder.done.append(spool_id)
            return True
        rc = info.rc
        if rc == 0 or (rc == self._paho.MQTT_ERR_NO_CONN and message.qos > 0):
            self.window.append((info, message, spool_id))  # qos>0 without connection: paho resends
            return True
        self._outbox.count("publishErrors")
        return False

    def settle(self) -> None:
        """Take the messages paho is done with off the window, oldest first: written
        (QoS 0), confirmed by the broker (QoS 1, 2), or failed for good."""
        window = self.window
        forwarder = self.forwarder
        acknowledged = 0
        while window:
            info, message, spool_id = window[0]
            try:
                done = info.is_published()
            except (ValueError, RuntimeError):  # paho gave up on it
                if spool_id and forwarder is not None:  # kept: sent again later
                    forwarder.release([(spool_id, message.device)])
            else:
                if not done:
                    break
                if message.qos > 0:
                    acknowledged += 1
                if spool_id and forwarder is not None:
                    forwarder.done.append(spool_id)
            window.popleft()
        if acknowledged:
            self._outbox.count("acknowledged", acknowledged)

    def reconnected(self) -> None:
        """A new connection: QoS 0 messages that had not been written are gone (paho
        empties its output queue on reconnect; counted as ``lostOnDisconnect``); QoS 1
        and 2 ones stay in the window, paho sends them again."""
        self.settle()
        kept: deque[tuple[MQTTMessageInfo, Message, int]] = deque()
        lost = 0
        back: list[tuple[int, str | None]] = []
        for info, message, spool_id in self.window:
            if message.qos > 0:
                kept.append((info, message, spool_id))
            elif not info.is_published():  # (written ones may wait behind a QoS 1 one)
                lost += 1
                if spool_id:
                    back.append((spool_id, message.device))
            elif spool_id and self.forwarder is not None:
                self.forwarder.done.append(spool_id)
        self.window = kept
        if back and self.forwarder is not None:
            self.forwarder.release(back)  # replayed: the spool still had them
        if lost:
            self._outbox.count("lostOnDisconnect", lost)

    # -- the queues ------------------------------------------------------------------------
    def busy(self) -> bool:
        """True while paho holds messages not yet sent (or, QoS > 0, not confirmed)."""
        self.settle()
        return bool(self.window)

    def room(self) -> int:
        self.settle()
        return self._size - len(self.window)

    def pump(self, client: Client) -> None:
        """Move queued messages into the client while the in-flight window has room:
        control messages first, then item updates, then snapshots.  A message paho does
        not take goes back to the front of its queue (or, spooled, to the spool).  Then,
        with store-and-forward, the replay with the room left."""
        self._pump_live(client)
        forwarder = self.forwarder
        if forwarder is not None:
            if self._connected.is_set():
                self._replay(client, forwarder)
            forwarder.settle()
            forwarder.tick()

    def _pump_live(self, client: Client) -> None:
        s, outbox = self.settings, self._outbox
        room = self.room()
        while room > 0 and self._connected.is_set():
            with outbox.lock:
                control = [outbox.control.popleft()
                           for _ in range(min(room, len(outbox.control)))]
                room -= len(control)
                reports = outbox.take_reports(min(room, _TAKE), split=not self._batch)
                room -= (len(reports) if self._batch
                         else sum(len(report.rows) for report in reports))
                snapshots: list[tuple[AttachedDevice, dict[str, Any]]] = []
                if room > 0 and outbox.snapshots:
                    snapshots = list(outbox.snapshots.values())[:room]
                    for dev, _ in snapshots:
                        del outbox.snapshots[dev.code]
                    room -= len(snapshots)
            if not control and not reports and not snapshots:
                return
            sent_control = 0
            for message in control:
                if not self.hand_over(client, message):
                    break
                sent_control += 1
            left = reports
            published: dict[AttachedDevice, int] = {}
            if sent_control == len(control):
                left = self._send_reports(client, reports, published)
            sent_snapshots: list[AttachedDevice] = []
            if not left and sent_control == len(control):
                for dev, snap in snapshots:
                    body = dict(snap)
                    body["gatewayId"] = self.gateway_id
                    body["ts"] = now()
                    message = Message(dev.code, dev.snapshot_topic, dumps(body),
                                      s.snapshot_qos, s.snapshot_retain)
                    if not self.hand_over(client, message):
                        break
                    sent_snapshots.append(dev)
            with outbox.lock:
                for dev, count in published.items():
                    dev.published += count
                    outbox.counts["published"] += count
                if self._batch and self.forwarder is None:  # else: _send_spooled counts
                    outbox.counts["batchesPublished"] += len(reports) - len(left)
                outbox.counts["snapshotsPublished"] += len(sent_snapshots)
                for dev in sent_snapshots:
                    dev.snapshots += 1
                # not taken: back to the front, oldest first, newer snapshots win
                outbox.control.extendleft(reversed(control[sent_control:]))
                outbox.put_back(left)
                for dev, snap in snapshots[len(sent_snapshots):]:
                    outbox.snapshots.setdefault(dev.code, (dev, snap))
            if sent_control < len(control) or left or len(sent_snapshots) < len(snapshots):
                return
            room = self.room()

    def _send_reports(self, client: Client, reports: list[Report],
                      published: dict[AttachedDevice, int]) -> list[Report]:
        """Item updates to paho: a message per report (batch) or per row (per-item);
        ``published`` counts what was taken per device.  Returns what was not taken."""
        if self.forwarder is not None:
            self._send_spooled(client, self.forwarder, reports, published)
            return []
        qos, retain = self.settings.qos, self.settings.retain
        for index, report in enumerate(reports):
            dev, rows = report.dev, report.rows
            if self._batch:
                message = Message(dev.code, dev.batch_topic, batch_payload(dev.code, rows),
                                  qos, retain)
                if not self.hand_over(client, message):
                    return reports[index:]
                published[dev] = published.get(dev, 0) + len(rows)
                continue
            topics = dev.item_topics
            for sent, (name, value, status, ts, error) in enumerate(rows):
                topic = topics.get(name)
                if topic is None:
                    topic = topics[name] = self.item_topic(dev.code, name)
                message = Message(dev.code, topic, encode_item(value, status, ts, error),
                                  qos, retain)
                if not self.hand_over(client, message):
                    published[dev] = published.get(dev, 0) + sent
                    return [Report(dev, rows[sent:]), *reports[index + 1:]]
            published[dev] = published.get(dev, 0) + len(rows)
        return []

    # -- store-and-forward (store_forward.py) -------------------------------------------
    def messages(self, reports: list[Report]) -> list[tuple[AttachedDevice, Message, int]]:
        """The messages of ``reports``: (device, message, item updates it carries)."""
        qos, retain = self.settings.qos, self.settings.retain
        out: list[tuple[AttachedDevice, Message, int]] = []
        for report in reports:
            dev, rows = report.dev, report.rows
            if self._batch:
                out.append((dev, Message(dev.code, dev.batch_topic,
                                         batch_payload(dev.code, rows), qos, retain),
                            len(rows)))
                continue
            topics = dev.item_topics
            for name, value, status, ts, error in rows:
                topic = topics.get(name)
                if topic is None:
                    topic = topics[name] = self.item_topic(dev.code, name)
                out.append((dev, Message(dev.code, topic,
                                         encode_item(value, status, ts, error), qos, retain),
                            1))
        return out

    def replay_delay(self) -> float | None:
        """With a backlog to replay and room in the window: how long the MQTT thread may
        sleep before the pacer allows the next message (None: no limit from here)."""
        forwarder = self.forwarder
        if forwarder is None or not self._connected.is_set() or self.room() <= 0:
            return None
        delay = forwarder.delay()
        return None if delay is None else max(delay, 0.002)

    def spool_outage(self) -> None:
        """Not connected: every queued report goes to the spool (one transaction)."""
        forwarder = self.forwarder
        if forwarder is None:
            return
        with self._outbox.lock:
            reports = self._outbox.take_reports(self._outbox.queued, split=False)
        if reports:
            forwarder.keep([message for _, message, _ in self.messages(reports)])
        forwarder.tick()

    def _send_spooled(self, client: Client, forwarder: Forwarder, reports: list[Report],
                      published: dict[AttachedDevice, int]) -> None:
        """Live messages with store-and-forward: a device with a backlog appends them to
        the spool behind it; the others publish directly (QoS 1: appended claimed
        first).  What paho refuses stays in (or goes to) the spool."""
        made = self.messages(reports)
        behind: dict[str, bool] = {}
        for dev, _, _ in made:
            if dev.code not in behind:
                behind[dev.code] = forwarder.backlogged(dev.code)
        kept = [message for dev, message, _ in made if behind[dev.code]]
        direct = [(dev, message, n) for dev, message, n in made if not behind[dev.code]]
        forwarder.keep_live(kept)
        claimed = [message for _, message, _ in direct if message.qos > 0]
        ids = iter(forwarder.claim(claimed))
        sids = [next(ids) if message.qos > 0 else 0 for _, message, _ in direct]
        handed = 0
        for index, (dev, message, n) in enumerate(direct):
            if not self.hand_over(client, message, sids[index]):
                rest = list(zip(direct[index:], sids[index:], strict=True))
                forwarder.release([(sid, message.device)
                                   for (_, message, _), sid in rest if sid])
                # not in the spool (QoS 0, or the spool refused them): kept now
                forwarder.keep([message for (_, message, _), sid in rest if not sid])
                break
            published[dev] = published.get(dev, 0) + n
            handed += 1
        if self._batch:  # live batches handed over; spooled ones count as replayed
            self._outbox.count("batchesPublished", handed)

    def _replay(self, client: Client, forwarder: Forwarder) -> None:
        """Spooled messages to paho with the window's room, at the pacer's rate, oldest
        first, with the retain flag they were kept with: a device's live messages queue
        behind its backlog (store_forward.py), so the last one replayed for a topic is
        its newest and the broker's retained value ends up the current one.  A fleet
        device whose DTU is not connected here now (it moved to another instance during
        the outage) is replayed with retain off: the retained value is its holder's."""
        batch = forwarder.replay_batch(self.room())
        sent = nbytes = 0
        away: dict[str, bool] = {}
        for stored in batch:
            retain = stored.retain and not self._away(stored.device, away)
            message = Message(stored.device or None, stored.topic, stored.payload,
                              stored.qos, retain)
            if not self.hand_over(client, message, stored.id):
                forwarder.unsent(batch[sent:])
                break
            sent += 1
            nbytes += len(stored.payload)
        if batch:
            forwarder.replayed_batch(sent, nbytes)

    def _away(self, code: str, seen: dict[str, bool]) -> bool:
        """Whether device ``code`` is a fleet device not held here now (looked at once
        per replay batch, in ``seen``)."""
        if code not in seen:
            dev = self._devices.get(code)
            seen[code] = dev is not None and dev.fleet is not None and dev.fleet.quiet()
        return seen[code]
