"""DTUs on an MQTT broker (transport ``mqtt-dtu``, docs/links.md): a DTU publishes
what it reads from RS-485 to its uplink topic and writes to RS-485 what it receives on
its downlink topic.

The line engine reads and writes an fd, so an MQTT DTU's link is one end of a
``socket.socketpair()``: the engine polls it exactly like a TCP DTU stream (framing,
heartbeats, wrapped reports, timeouts, settling and the fault policy unchanged,
csrc/emb_stream.c).  The other end belongs to the broker's :class:`MqttDtuHub`: one
paho client (one MQTT connection per broker settings, shared by its DTUs) writes each
uplink message into the DTU's end (paho's network thread), and the hub's pump thread
publishes what it reads from that end to the downlink topic.

A DTU is online while the broker is connected and its status topic did not say
``offline`` (its will: the broker publishes it when the DTU drops off); an unknown
status counts as online, so DTUs without a status message are polled too.  Offline, its
end is closed: the engine's read fails as on a dropped TCP DTU, the line's connects fail
with the reason (devices Reconnecting), and the status ``online`` reconnects at once.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..config.tls import connect_error_text
from ..errors import ModbusConnectionError
from .connect import open_socket_link
from .endpoint import MqttBroker, MqttDtuEndpoint
from .link import Link
from .log_limit import LogLimiter, hex_prefix

if TYPE_CHECKING:
    from paho.mqtt.client import Client, MQTTMessage

    from .worker import LineWorker

log = logging.getLogger("edgemodbus.line")

_READ = 65536  # bytes read from a DTU's end at once (one request is at most 256)
_HUB_IDS = itertools.count(1)
_TICK = 1.0  # the longest select(): paho's keepalive is checked at least this often
_CONNECT_TIMEOUT = 5.0


class MqttDtuSlot:
    """One DTU on a hub: the connector of its line (worker thread), its online state
    (paho's thread) and the hub's end of its socketpair."""

    def __init__(self, hub: MqttDtuHub, endpoint: MqttDtuEndpoint) -> None:
        self.hub = hub
        self.endpoint = endpoint
        self.line: LineWorker | None = None
        self.online = False
        self.reason = f"waiting for the broker {endpoint.broker.describe()}"
        self.status: bytes | None = None  # the last status message (None: none yet)
        self._lock = threading.Lock()  # the end, the link, the state
        self._end: socket.socket | None = None
        self._link: Link | None = None

    # -- the connector (the line's worker) -----------------------------------------------
    def open(self, line: LineWorker) -> Link:
        """A link on a fresh socketpair whose other end the hub pumps; a connection
        error naming why while the DTU is offline."""
        with self._lock:
            if not self.online:
                raise ModbusConnectionError(f"{self.endpoint.describe()}: {self.reason}")
            ours, theirs = socket.socketpair()
            theirs.setblocking(False)
            self._close_end()
            self._end = theirs
        self.hub.pump(theirs, self)  # the pump closes it once it reads its end
        try:
            link = open_socket_link(ours, self.endpoint, line.timing, line.stats,
                                    on_close=lambda: self._closed(theirs),
                                    on_report=line.dispatch_report)
        except BaseException:
            ours.close()
            self._closed(theirs)
            raise
        with self._lock:
            self._link = link
        return link

    def _closed(self, end: socket.socket) -> None:
        """The link closed (worker thread): its end is forgotten (the pump reads the
        end of the stream from it and closes it)."""
        with self._lock:
            if self._end is end:
                self._end = None
                self._link = None

    def _close_end(self) -> None:
        """Shut the hub's end down (the lock is held): the engine's read of the link's
        end sees the end of the stream, the pump its own and closes it."""
        end, self._end = self._end, None
        if end is not None:
            with contextlib.suppress(OSError):  # closed by the pump meanwhile
                end.shutdown(socket.SHUT_RDWR)

    # -- from the broker (paho's thread) ------------------------------------------------------
    def uplink(self, payload: bytes) -> None:
        """What the DTU read from RS-485: into the link's stream (the hub's thread)."""
        with self._lock:
            end = self._end
            sent = 0
            if end is not None:
                try:
                    sent = end.send(payload)
                except OSError:  # full (a flood: the engine reads at its pace), shut down
                    sent = 0
            line = self.line
        if line is not None:  # (the line's counters; only this thread writes these)
            line.stats.uplink_messages += 1
            line.stats.uplink_dropped_bytes += len(payload) - sent
        if sent < len(payload):
            self.hub.limiter.event(
                logging.WARNING, "uplink messages dropped", self.endpoint.dtu_id,
                "%s: %d of %d bytes of an uplink message dropped (%s): %s",
                self.endpoint.describe(), len(payload) - sent, len(payload),
                "no link" if end is None else "the link's stream is full",
                hex_prefix(payload))

    def retained(self, payload: bytes) -> None:
        """A retained message on the uplink topic (the broker hands it over at every
        subscribe, before any request): never a reply, so dropped, counted, logged."""
        line = self.line
        if line is not None:
            line.stats.uplink_messages += 1
            line.stats.uplink_dropped_bytes += len(payload)
        self.hub.limiter.event(
            logging.WARNING, "retained uplink messages dropped", self.endpoint.dtu_id,
            "%s: a retained message on the uplink topic %r dropped (%d bytes: %s): a "
            "reply is never retained; clear it (publish an empty retained message there)",
            self.endpoint.describe(), self.endpoint.uplink, len(payload),
            hex_prefix(payload))

    def set_online(self, online: bool, reason: str) -> None:
        """The DTU (or the broker) came or went: close its end when it went, reconnect
        its line at once when it came."""
        with self._lock:
            was, self.online = self.online, online
            self.reason = reason
            if not online:
                link = self._link
                if link is not None:
                    link.close_reason = reason
                self._close_end()
            line = self.line
        if online != was:
            log.info("%s: %s", self.endpoint.describe(), "online" if online else reason)
        if online and not was and line is not None:
            line.connect_now()

    def on_status(self, payload: bytes) -> None:
        """A message on the status topic: ``offline`` takes the DTU down, ``online``
        brings it back; anything else changes nothing (logged, bounded: untrusted)."""
        if payload == self.endpoint.offline:
            self.status = self.endpoint.offline
            self.set_online(False, f"the DTU is offline (its status topic "
                                   f"{self.endpoint.status!r} says {payload[:32]!r})")
        elif payload == self.endpoint.online:
            self.status = self.endpoint.online
            if self.hub.connected:
                self.set_online(True, "online")
        else:  # (not kept: only the two known texts are, so a huge one costs nothing)
            self.hub.limiter.event(
                logging.WARNING, "unknown status messages", self.endpoint.dtu_id,
                "%s: a message on the status topic %r that is neither %r nor %r (%d "
                "bytes: %s); the DTU's state is unchanged", self.endpoint.describe(),
                self.endpoint.status, self.endpoint.online, self.endpoint.offline,
                len(payload), hex_prefix(payload))


class MqttDtuHub:
    """One broker's MQTT connection for all its DTUs and the one thread that runs it:
    paho's socket, the DTUs' ends and a wake-up socket in one selector (paho's own loop
    thread is not used: one thread per broker, and nothing of paho's left open after
    :meth:`stop`).  See the module docstring."""

    def __init__(self, broker: MqttBroker) -> None:
        try:
            import paho.mqtt.client as paho
            from paho.mqtt.enums import CallbackAPIVersion
        except ImportError:  # pragma: no cover - depends on the install
            raise ImportError("transport mqtt-dtu needs paho-mqtt: pip install "
                              "'edgemodbus[mqtt]'") from None

        self.broker = broker
        self.connected = False
        self._lock = threading.Lock()  # the tables
        self._slots: dict[str, MqttDtuSlot] = {}  # by dtu id
        self._topics: dict[str, tuple[MqttDtuSlot, bool]] = {}  # topic -> (slot, status?)
        # for the hub's thread: new ends to read, (un)subscriptions
        self._actions: queue.SimpleQueue[Callable[[selectors.BaseSelector], object]] = \
            queue.SimpleQueue()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._stop = threading.Event()
        self._failures = 0  # failed connects in a row (the backoff, the log)
        self.limiter = LogLimiter(log)  # untrusted uplink traffic: bounded log lines
        client_id = broker.client_id or \
            f"edgemodbus-dtu-{socket.gethostname()}-{os.getpid()}-{next(_HUB_IDS)}"
        client: Client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                                     client_id=client_id, clean_session=True,
                                     protocol=paho.MQTTv311)
        client.connect_timeout = _CONNECT_TIMEOUT
        if broker.username:
            client.username_pw_set(broker.username, broker.password or None)
        if broker.tls:
            client.tls_set(ca_certs=broker.ca_file or None, certfile=broker.cert_file or None,
                           keyfile=broker.key_file or None)
            client.tls_insecure_set(broker.tls_insecure)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        self.client = client
        self._thread = threading.Thread(
            target=self._run, name=f"edgemodbus-mqtt-dtu {broker.describe()}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Disconnect, end the thread, close every socket."""
        self._stop.set()
        self._wake()
        self._thread.join()
        self._wake_r.close()
        self._wake_w.close()

    # -- DTUs (any thread) ------------------------------------------------------------------
    def add(self, endpoint: MqttDtuEndpoint) -> MqttDtuSlot:
        """The slot of a new DTU on this broker; its topics subscribed."""
        slot = MqttDtuSlot(self, endpoint)
        topics = [endpoint.uplink] + ([endpoint.status] if endpoint.status else [])
        with self._lock:
            for topic in topics:
                if topic in self._topics:
                    raise ValueError(f"{endpoint.describe()}: topic {topic!r} is already "
                                     f"{self._topics[topic][0].endpoint.describe()}'s")
            self._slots[endpoint.dtu_id] = slot
            self._topics[endpoint.uplink] = (slot, False)
            if endpoint.status:
                self._topics[endpoint.status] = (slot, True)
        self._post(lambda _sel: self._subscribe(topics, slot))
        return slot

    def remove(self, slot: MqttDtuSlot) -> None:
        with self._lock:
            self._slots.pop(slot.endpoint.dtu_id, None)
            gone = [t for t, (s, _) in self._topics.items() if s is slot]
            for topic in gone:
                del self._topics[topic]
        slot.set_online(False, "removed")
        if gone:
            self._post(lambda _sel: self._unsubscribe(gone))

    @property
    def empty(self) -> bool:
        with self._lock:
            return not self._slots

    def pump(self, end: socket.socket, slot: MqttDtuSlot) -> None:
        """Have the hub's thread read ``end`` (a new link of ``slot``) and publish it;
        the thread closes it at the end of its stream."""
        self._post(lambda sel: sel.register(end, selectors.EVENT_READ, slot))

    def _post(self, action: Callable[[selectors.BaseSelector], object]) -> None:
        self._actions.put(action)
        self._wake()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # full (a wake-up is pending anyway), closed
            self._wake_w.send(b"\0")

    # -- the hub's thread: paho's callbacks ---------------------------------------------------
    def _subscribe(self, topics: list[str], slot: MqttDtuSlot | None = None) -> None:
        if self.connected and topics:
            self.client.subscribe([(topic, self.broker.qos) for topic in topics])
            if slot is not None and slot.status != slot.endpoint.offline:
                slot.set_online(True, "online")

    def _unsubscribe(self, topics: list[str]) -> None:
        if self.connected:
            self.client.unsubscribe(topics)

    def _on_connect(self, _client: Any, _userdata: Any, _flags: Any, reason: Any,
                    _props: Any) -> None:
        if reason.is_failure:
            log.warning("MQTT DTUs: broker %s refused the connection: %s",
                        self.broker.describe(), reason)
            return
        self.connected = True
        self._failures = 0
        with self._lock:
            topics = list(self._topics)
            slots = list(self._slots.values())
        log.info("MQTT DTUs: connected to %s (%d DTUs)", self.broker.describe(), len(slots))
        self._subscribe(topics)
        for slot in slots:
            if slot.status != slot.endpoint.offline:
                slot.set_online(True, "online")

    def _on_disconnect(self, _client: Any, _userdata: Any, _flags: Any, reason: Any,
                       _props: Any) -> None:
        was, self.connected = self.connected, False
        if was and not self._stop.is_set():
            log.warning("MQTT DTUs: lost the broker %s: %s", self.broker.describe(), reason)
        with self._lock:
            slots = list(self._slots.values())
        for slot in slots:
            slot.status = None  # what it says after a reconnect is news
            slot.set_online(False, f"lost the broker {self.broker.describe()}")

    def _on_message(self, _client: Any, _userdata: Any, msg: MQTTMessage) -> None:
        with self._lock:
            entry = self._topics.get(msg.topic)
        if entry is None:
            return
        slot, status = entry
        if status:
            slot.on_status(bytes(msg.payload))
        elif msg.retain:  # from the broker's store at subscribe time, not from the DTU now
            slot.retained(bytes(msg.payload))
        else:
            slot.uplink(bytes(msg.payload))

    # -- the hub's thread: the loop ------------------------------------------------------------
    def _run(self) -> None:
        selector = selectors.DefaultSelector()
        selector.register(self._wake_r, selectors.EVENT_READ)
        next_connect = 0.0
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if self.client.socket() is None and now >= next_connect:
                    next_connect = now + self._connect()
                self._select(selector, max(0.0, min(_TICK, next_connect - now))
                             if self.client.socket() is None else _TICK)
                if self.client.socket() is not None:
                    self.client.loop_misc()  # keepalive pings, a silent broker
                self.limiter.flush()
        except Exception:
            log.exception("MQTT DTUs: the hub of %s failed", self.broker.describe())
        finally:
            self._close(selector)

    def _connect(self) -> float:
        """Connect (blocking, at most the connect timeout); the wait before the next
        try (1 s doubling to 10 s) when it failed."""
        try:
            self.client.connect(self.broker.host, self.broker.port, self.broker.keepalive)
            return 0.0
        except (OSError, ValueError) as exc:
            self._failures += 1
            level = logging.WARNING if self._failures == 1 else logging.DEBUG
            why = connect_error_text(exc, "mqttTls" if self.broker.tls else None,
                                     f"{_CONNECT_TIMEOUT:.0f} s")
            log.log(level, "MQTT DTUs: cannot connect to %s: %s", self.broker.describe(), why)
            with self._lock:
                slots = list(self._slots.values())
            for slot in slots:
                slot.set_online(False, f"cannot connect to the broker "
                                       f"{self.broker.describe()}: {why}")
            return min(10.0, 2.0 ** min(self._failures - 1, 4))

    def _select(self, selector: selectors.BaseSelector, timeout: float) -> None:
        sock = self.client.socket()
        mqtt: socket.socket | None = sock if isinstance(sock, socket.socket) else None
        if mqtt is not None:
            events = selectors.EVENT_READ | (
                selectors.EVENT_WRITE if self.client.want_write() else 0)
            selector.register(mqtt, events, None)
        try:
            ready = selector.select(timeout)
        finally:
            if mqtt is not None:
                selector.unregister(mqtt)
        for key, mask in ready:
            if key.fileobj is self._wake_r:
                self._take_actions(selector)
            elif key.fileobj is mqtt:
                if mask & selectors.EVENT_READ:
                    self.client.loop_read()  # (one packet)
                    # TLS: packets decrypted with that one wait in the TLS layer, unseen
                    # by select(): read them now (a coalescing broker's replies)
                    pending = getattr(mqtt, "pending", None)
                    while pending is not None and self.client.socket() is mqtt and \
                            pending() > 0:
                        self.client.loop_read()
                if mask & selectors.EVENT_WRITE and self.client.socket() is not None:
                    self.client.loop_write()
            else:
                self._forward(selector, key.fileobj, key.data)  # type: ignore[arg-type]
        if self.client.socket() is not None and self.client.want_write():
            self.client.loop_write()  # what the DTUs' lines wrote, published at once

    def _take_actions(self, selector: selectors.BaseSelector) -> None:
        with contextlib.suppress(OSError):  # BlockingIOError: no more wake-ups
            while self._wake_r.recv(4096):
                pass
        while True:
            try:
                action = self._actions.get_nowait()
            except queue.Empty:
                return
            action(selector)

    def _forward(self, selector: selectors.BaseSelector, end: socket.socket,
                 slot: MqttDtuSlot) -> None:
        """What a DTU's line wrote: to its downlink topic."""
        try:
            data = end.recv(_READ)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the link closed its end, or the slot shut this one down
            selector.unregister(end)
            end.close()
            return
        self.client.publish(slot.endpoint.downlink, data, qos=self.broker.qos)

    def _close(self, selector: selectors.BaseSelector) -> None:
        """Stopping: a clean DISCONNECT, then every socket closed."""
        if self.client.socket() is not None:
            with contextlib.suppress(Exception):
                self.client.disconnect()  # queued; paho closes its socket once written
                self.client.loop_write()
        sock = self.client.socket()
        if isinstance(sock, socket.socket):  # (the DISCONNECT could not be written)
            sock.close()
        self._on_disconnect(None, None, None, "stopped", None)
        ends = [k.fileobj for k in selector.get_map().values() if k.fileobj is not self._wake_r]
        selector.close()
        while True:  # ends handed over after the last turn
            try:
                action = self._actions.get_nowait()
            except queue.Empty:
                break
            collect = selectors.DefaultSelector()
            with contextlib.suppress(Exception):
                action(collect)
            ends += [k.fileobj for k in collect.get_map().values()]
            collect.close()
        for end in ends:
            end.close()  # type: ignore[union-attr]


class MqttDtuHubs:
    """One hub per broker settings, shared by the DTU lines on it (refcounted by the
    line registry: a slot per line)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._hubs: dict[MqttBroker, MqttDtuHub] = {}

    def acquire(self, endpoint: MqttDtuEndpoint) -> MqttDtuSlot:
        with self._lock:
            hub = self._hubs.get(endpoint.broker)
            if hub is None:
                hub = MqttDtuHub(endpoint.broker)
                hub.start()
                self._hubs[endpoint.broker] = hub
            try:
                return hub.add(endpoint)
            except BaseException:
                if hub.empty:
                    del self._hubs[endpoint.broker]
                    hub.stop()
                raise

    def release(self, slot: MqttDtuSlot) -> None:
        hub = slot.hub
        hub.remove(slot)
        with self._lock:
            if not hub.empty or self._hubs.get(hub.broker) is not hub:
                return
            del self._hubs[hub.broker]
        hub.stop()


hubs = MqttDtuHubs()
