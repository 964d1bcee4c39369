"""The MQTT thread's side of the outbox: queued messages handed to the paho client while
its in-flight window has room, control messages first, then item updates (one message
per update, or in mode "batch" one per device and cycle), then snapshots.

Every message reaches paho in one place, :meth:`Sender.hand_over` (``client.publish``,
paho's public API), and its completion is observed in one place, :meth:`Sender.settle`
(the ``MQTTMessageInfo`` that publish() returned: QoS 0 once written to the socket,
QoS 1 and 2 once the broker confirmed).  Between the two, a :class:`Message` sits in the
window (outbox.Message: device, topic, payload, qos, retain); that is where a
store-and-forward spool would hook in."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

from .devices import AttachedDevice
from .outbox import Message, Outbox, Report
from .payload import batch_payload, dumps, encode_item, now
from .settings import MqttSettings

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
                 connected: threading.Event) -> None:
        self._outbox = outbox
        self.settings = settings
        self._paho = paho
        self.gateway_id = gateway_id
        self.item_topic = item_topic
        self._connected = connected
        self._batch = settings.mode == "batch"
        self._size = min(settings.max_inflight * 4, _WINDOW_CAP)
        self.window: deque[tuple[MQTTMessageInfo, Message]] = deque()

    # -- the seam: to paho, and back -------------------------------------------------------
    def hand_over(self, client: Client, message: Message) -> bool:
        """Hand one message to paho (``client.publish``).  False: not taken (retry
        later); an invalid topic or payload is refused for good (logged, counted, True)."""
        try:
            info = client.publish(message.topic, message.payload, qos=message.qos,
                                  retain=message.retain)
        except ValueError as exc:  # an invalid topic, a payload over 256 MB: never retried
            self._outbox.count("publishErrors")
            log.error("MQTT publish to %r refused: %s", message.topic, exc)
            return True
        rc = info.rc
        if rc == 0 or (rc == self._paho.MQTT_ERR_NO_CONN and message.qos > 0):
            self.window.append((info, message))  # qos>0 without connection: paho resends
            return True
        self._outbox.count("publishErrors")
        return False

    def settle(self) -> None:
        """Take the messages paho is done with off the window, oldest first: written
        (QoS 0), confirmed by the broker (QoS 1, 2), or failed for good."""
        window = self.window
        acknowledged = 0
        while window:
            info, message = window[0]
            try:
                done = info.is_published()
            except (ValueError, RuntimeError):  # paho gave up on it
                done = True
            else:
                if not done:
                    break
                if message.qos > 0:
                    acknowledged += 1
            window.popleft()
        if acknowledged:
            self._outbox.count("acknowledged", acknowledged)

    def reconnected(self) -> None:
        """A new connection: QoS 0 messages that had not been written are gone (paho
        empties its output queue on reconnect; counted as ``lostOnDisconnect``); QoS 1
        and 2 ones stay in the window, paho sends them again."""
        self.settle()
        kept: deque[tuple[MQTTMessageInfo, Message]] = deque()
        lost = 0
        for info, message in self.window:
            if message.qos > 0:
                kept.append((info, message))
            elif not info.is_published():  # (written ones may wait behind a QoS 1 one)
                lost += 1
        self.window = kept
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
        not take goes back to the front of its queue."""
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
                if self._batch:
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
