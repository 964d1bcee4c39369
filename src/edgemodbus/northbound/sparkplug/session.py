"""The edge node's MQTT sessions: the paho client, the NDEATH will with the next session's
bdSeq, connecting, and leaving a session on purpose (Sparkplug 3.0: an edge node whose
primary host goes offline publishes NDEATH, disconnects and connects again, a new
session with a new bdSeq).  paho's network thread calls the callbacks here; they only
count, log and hand events to the publisher's thread."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

from ..mqtt.connection import FailureLog
from ..mqtt.settings import MqttSettings
from .bdseq import BdSeqStore, RedisBdSeqStore
from .client import make_client

if TYPE_CHECKING:
    from paho.mqtt.client import Client, MQTTMessage

log = logging.getLogger("edgemodbus.sparkplug")


class NodeSession:
    """One paho client, connected again and again; each MQTT connection is a Sparkplug
    session whose bdSeq is the one its will (set before its CONNECT) carries.

    ``death`` makes an NDEATH payload for a bdSeq, ``subscriptions`` gives the topics to
    subscribe to on every connect, ``count`` bumps a publisher counter and ``push`` hands
    an event (``("connected", bdSeq)`` or ``("disconnected",)``) to the publisher's
    thread."""

    def __init__(self, paho: ModuleType, settings: MqttSettings, client_id: str, *,
                 node_name: str, death_topic: str, death: Callable[[int], bytes],
                 subscriptions: Callable[[], list[tuple[str, int]]],
                 count: Callable[[str], None], push: Callable[[tuple[Any, ...]], None],
                 on_message: Callable[[Any, Any, MQTTMessage], None],
                 store: RedisBdSeqStore | None = None) -> None:
        assert settings.sparkplug is not None
        self.settings = settings
        self.client_id = client_id
        self.node_name = node_name
        self._paho = paho
        self._death_topic = death_topic
        self._death = death
        self._subscriptions = subscriptions
        self._count = count
        self._push = push
        self._on_message = on_message
        self._store = store or BdSeqStore(settings.sparkplug.bd_seq_file)
        self.next_bd_seq = 0 if self._store.shared else self._store.load()
        # a pair's shared node (store given): connected only while this instance leads
        self.standby = self._store.shared
        self._leading = threading.Lock()  # start() and lead(): one connect at a time
        self._failures = FailureLog(f"{settings.host}:{settings.port}",
                                    settings.failure_log_interval / 1000,
                                    settings.reconnect_max / 1000)
        self.connected = threading.Event()
        self.stopping = False  # set by the publisher's stop(): no warning on disconnect
        self._leaving = False  # a disconnect we asked for (restart)
        self.client: Client | None = None

    def start(self) -> Client:
        """Make the client and connect in the background (paho's thread retries);
        a standby connects only when it leads (:meth:`lead`)."""
        self.client = client = make_client(self._paho, self.settings, self.client_id)
        client.on_connect = self._on_connect
        client.on_connect_fail = self._on_connect_fail
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        with self._leading:
            if not self.standby:
                self._connect(client)
        return client

    def lead(self, leader: bool) -> None:
        """A shared node's pair changed hands (publisher's thread): leading, connect (a
        new session, its bdSeq read from the shared store); no longer, disconnect (the
        publisher said NDEATH first) and stay away."""
        with self._leading:
            if leader != self.standby:
                return  # so already
            self.standby = not leader
            client = self.client
            if client is None:
                return  # start() connects if it leads
            if leader:
                self._connect(client)
                return
        self._disconnect(client)
        log.info("Sparkplug: edge node %s: standby, disconnected", self.node_name)

    def _disconnect(self, client: Client) -> None:
        """End the session on purpose (no will: not taken for a lost link) and wait for
        paho's thread."""
        self._leaving = True
        try:
            client.disconnect()
            client.loop_stop()
        finally:
            self._leaving = False
        self.connected.clear()

    def _connect(self, client: Client) -> None:
        if self._store.shared:  # the other instance may have used numbers since
            try:
                self.next_bd_seq = self._store.load()
            except Exception as exc:
                log.error("Sparkplug: bdSeq not read from the pair's store (%s); using "
                          "%d", exc, self.next_bd_seq)
        self._set_will(client)
        s = self.settings
        client.connect_async(s.host, s.port, s.keepalive)
        client.loop_start()

    def _set_will(self, client: Client) -> None:
        """The NDEATH of the next session as the MQTT will (QoS 1, not retained: 6.4.5)."""
        client.will_set(self._death_topic, self._death(self.next_bd_seq), qos=1,
                        retain=False)

    def goodbye(self, bd_seq: int, timeout: float) -> None:
        """Publish this session's NDEATH (QoS 1) and wait at most ``timeout`` s for the
        broker to take it (Sparkplug 3.0: an edge node that disconnects on purpose
        publishes NDEATH first; the broker drops the will on a clean disconnect)."""
        client = self.client
        if client is None or not self.connected.is_set():
            return
        info = client.publish(self._death_topic, self._death(bd_seq), qos=1, retain=False)
        try:
            info.wait_for_publish(timeout)
        except (RuntimeError, ValueError) as exc:
            log.debug("Sparkplug: NDEATH not confirmed: %s", exc)

    def restart(self) -> None:
        """End the session (a clean MQTT DISCONNECT) and connect again: a new session,
        whose will carries the next bdSeq.  Called from the publisher's thread, never
        from paho's (it joins paho's thread)."""
        client = self.client
        if client is None:
            return
        self._disconnect(client)
        log.info("Sparkplug: reconnecting to %s:%d for a new session (bdSeq %d)",
                 self.settings.host, self.settings.port, self.next_bd_seq)
        self._connect(client)

    def close(self) -> None:
        """Disconnect and stop paho's thread (the publisher's thread has ended), then
        close paho's wake-up socket pair: loop_start() opens it and only the client's
        __del__ or reinitialise() closes it, so a stopped publisher still referenced
        (a gateway's, until its reload is done) kept two sockets open."""
        client = self.client
        if client is not None:
            client.disconnect()
            client.loop_stop()
            client.reinitialise()
        self.connected.clear()

    # -- paho's network thread -----------------------------------------------------------
    def _on_connect(self, client: Client, _userdata: Any, _flags: Any, reason: Any,
                    _props: Any) -> None:
        if getattr(reason, "is_failure", False):
            self._count("connectFailures")
            self._failures.failed(f"the broker refused the connection: {reason}",
                                  time.monotonic())
            return
        if self._store.shared and not self._store.leading():
            # paho reconnected a leader paused past its lease (the broker had dropped
            # it): the node is the other instance's now; a clean DISCONNECT drops the will
            log.warning("Sparkplug: edge node %s: reconnected but no longer the pair's "
                        "leader: disconnecting", self.node_name)
            self.standby = True
            client.disconnect()
            return
        bd_seq = self.next_bd_seq  # the will the broker holds now carries it
        self.next_bd_seq = (bd_seq + 1) % 256
        self._store.save(self.next_bd_seq)
        self._set_will(client)  # for the next session, should paho reconnect by itself
        failed = self._failures.succeeded()
        log.info("Sparkplug: edge node %s connected to %s:%d (bdSeq %d)%s",
                 self.node_name, self.settings.host, self.settings.port, bd_seq,
                 f" after {failed} failed attempts" if failed else "")
        client.subscribe(self._subscriptions())
        self.connected.set()
        self._count("connects")
        self._push(("connected", bd_seq))

    def _on_connect_fail(self, _client: Client, _userdata: Any) -> None:
        self._count("connectFailures")
        self._failures.failed("cannot connect (TCP or TLS)", time.monotonic())

    def _on_disconnect(self, _client: Client, _userdata: Any, _flags: Any, reason: Any,
                       _props: Any) -> None:
        if self.connected.is_set():
            self._count("disconnects")
            if not self.stopping and not self._leaving:
                log.warning("Sparkplug: connection to %s:%d lost (%s); reconnecting",
                            self.settings.host, self.settings.port, reason)
        self.connected.clear()
        self._push(("disconnected",))
