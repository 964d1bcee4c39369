"""The MQTT publisher: its lifecycle, the drivers it publishes and the MQTT thread.

Needs the extra ``edgemodbus[mqtt]`` (paho-mqtt); paho is imported only when a
:class:`MqttPublisher` is made.  The package's ``__init__.py`` describes the threads,
queues and topics."""

from __future__ import annotations

import contextlib
import logging
import random
import select
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from ...config import ConfigError
from ...driver import DriverModbusRtu
from .commands import CommandRunner
from .connection import FailureLog, abandon, authenticate, error_text, write, write_wanted
from .devices import AttachedDevice, check_topics
from .holding import NOT_HERE, Holding
from .listener import DeviceListener
from .outbox import Message, Outbox
from .payload import gateway_payload, status_payload, status_text
from .sender import Sender
from .settings import MqttSettings, check_name

if TYPE_CHECKING:
    from paho.mqtt.client import Client, MQTTMessage


log = logging.getLogger("edgemodbus.mqtt")


class MqttPublisher:
    """Publishes what attached drivers report to an MQTT broker and accepts writes.

    ``publisher.attach(driver, "dev1")`` (before or after ``start_device``) subscribes
    to the driver (its batches and snapshots); ``start()`` connects in the
    background and returns at once; ``stop()`` publishes the gateway offline, flushes
    briefly and disconnects, never waiting for an unreachable broker.
    """

    def __init__(self, settings: MqttSettings | Mapping[str, Any] | None = None, *,
                 gateway_id: str = "edgemodbus", instance: str | None = None) -> None:
        """``instance``: this instance's id in a dial-in fleet (holding.py), else None."""
        try:
            import paho.mqtt.client as paho
        except ImportError:  # pragma: no cover - depends on the install
            raise ImportError(
                "MQTT needs paho-mqtt: pip install 'edgemodbus[mqtt]'"
            ) from None
        if settings is None:
            settings = MqttSettings()
        elif not isinstance(settings, MqttSettings):
            settings = MqttSettings.load(settings)
        self.settings: MqttSettings = settings
        self.gateway_id = check_name("gatewayId", gateway_id)
        self._paho = paho
        self._outbox = Outbox(settings.queue_size)
        self._lock = self._outbox.lock  # one lock: the devices, the queues, the counters
        self._devices: dict[str, AttachedDevice] = {}
        self._held: dict[str, AttachedDevice] = {}  # fleet devices held here (MQTT thread)
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._client: Client | None = None
        self._connected = threading.Event()
        self._attempt: float | None = None  # when the pending CONNECT went out
        self._tls = settings.tls is not None and settings.tls.enabled
        self._failures = FailureLog(f"{settings.host}:{settings.port}",
                                    settings.failure_log_interval / 1000,
                                    settings.reconnect_max / 1000)
        self._sender = Sender(self._outbox, settings, paho, self.gateway_id, self.item_topic,
                              self._connected, self._devices)
        self._commands = CommandRunner(self._outbox)
        self._linger = settings.linger / 1000
        self._linger_until = 0.0  # no blocking wait before this: let messages gather
        self._flush_timeout, self._stop_reason = 1.0, "shutdown"
        self.instance = instance
        self.client_id = settings.client_id or f"edgemodbus-{self.gateway_id}" + (
            f"-{instance}" if instance else "")
        self._closed = False

    # -- topics --------------------------------------------------------------------------
    def topic(self, template: str, device_code: str = "", item_name: str = "") -> str:
        """A topic template filled in for this gateway."""
        return template.format(prefix=self.settings.topic_prefix, deviceCode=device_code,
                               itemName=item_name, gatewayId=self.gateway_id)

    def gateway_topic(self) -> str:
        """The gateway's online/offline topic; in a fleet one per instance below it."""
        topic = self.topic(self.settings.gateway_topic)
        return f"{topic}/{self.instance}" if self.instance else topic

    def item_topic(self, device_code: str, item_name: str) -> str:
        return self.topic(self.settings.item_topic, device_code, item_name)

    def check_item_names(self, device_code: str, names: Iterable[str]) -> None:
        """Raise ValueError if an item's topic is also a command, status or reply topic
        of this device (a publish there would be read back as a command)."""
        check_topics(self.settings, self.topic, self._paho.topic_matches_sub, device_code,
                     names)

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> MqttPublisher:
        """Start the MQTT thread (and the command thread when writes are on)."""
        if self._thread is not None:
            return self
        if self._closed:
            raise RuntimeError("MqttPublisher cannot be restarted after stop(); make a new one")
        if self.settings.tls is not None:
            problems = self.settings.tls.problems()
            if problems:
                raise ConfigError(problems)
        self._sender.open_spool()  # ConfigError naming the path if it cannot be used
        self._client = self._make_client()
        if self.settings.writes:
            self._commands.start()
        self._thread = threading.Thread(target=self._run, name="edgemodbus-mqtt", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 1.0, reason: str = "shutdown") -> None:
        """Publish device statuses and the gateway offline with ``reason`` (if connected),
        flush for at most ``timeout`` seconds, disconnect and join the threads.
        Idempotent."""
        self._commands.stop()
        thread = self._thread
        if thread is not None:
            self._flush_timeout = max(0.0, timeout)
            self._stop_reason = reason
            self._stopping.set()
            self._outbox.wake()
            client = self._client
            # a connect() in progress can take up to connectTimeout; never longer
            connect = self.settings.connect_timeout / 1000 if client is not None else 0.0
            thread.join(timeout + connect + 1.0)
            if thread.is_alive():  # pragma: no cover - a wedged socket
                log.error("MQTT thread did not stop within %.1f s", timeout + connect + 1.0)
            self._thread = None
        if not self._closed:
            self._closed = True
            self._outbox.close()
            self._sender.close_spool()

    def __enter__(self) -> MqttPublisher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout: float) -> bool:
        return self._connected.wait(timeout)

    def stats(self) -> dict[str, Any]:
        """Counters (camelCase): connection, published, dropped, queue depth, commands,
        and per device those of devices.AttachedDevice.stats."""
        with self._lock:
            result: dict[str, Any] = dict(self._outbox.counts)
            result.update(queued=self._outbox.queued, queueLimit=self._outbox.limit(),
                          queueSize=self.settings.queue_size,
                          pendingSnapshots=len(self._outbox.snapshots))
            result["devices"] = {d.code: d.stats() for d in self._devices.values()}
            result["pendingCommands"] = self._commands.pending
        if self._sender.forwarder is not None:
            result["spool"] = self._sender.forwarder.stats()
        result["connected"] = self.connected
        return result

    # -- drivers -------------------------------------------------------------------------
    def attach(self, driver: DriverModbusRtu, device_code: str | None = None,
               held: Callable[[], bool] | None = None) -> None:
        """Publish what ``driver`` reports.  ``device_code`` defaults to the driver's
        (known once it was started).  Subscribes to it: other subscribers and the
        driver's callbacks are left as they are.  In a fleet, ``held`` says whether its
        DTU is connected here: only then is it published (holding.py)."""
        code = device_code or str(driver.snapshot()["deviceCode"])
        check_name("deviceCode", code)
        self.check_item_names(code, driver.snapshot()["items"].keys())
        dev = AttachedDevice(self.settings, self.topic, driver, code)
        dev.fleet = Holding(held) if held is not None and self.instance else None
        with self._lock:
            if code in self._devices:
                raise ValueError(f"deviceCode {code!r} is already attached to this publisher")
            self._devices[code] = dev
        dev.listener = listener = DeviceListener(self._outbox, dev)
        try:
            driver.subscribe(listener)
        except BaseException:
            with self._lock:
                del self._devices[code]
            raise
        self._outbox.act(lambda: self._subscribe(dev))
        self._outbox.look_at((dev,))  # its first status

    def held_changed(self, driver: DriverModbusRtu) -> None:
        """In a fleet: ``driver``'s DTU may have come or gone; look now (any thread)."""
        self._outbox.look_at([d for d in list(self._devices.values()) if d.driver is driver])

    def detach(self, driver: DriverModbusRtu) -> None:
        """Stop publishing ``driver``: its last status is published (retained), its
        command topics unsubscribed and its listener unsubscribed (only ours: other
        subscribers of the driver stay)."""
        with self._lock:
            devs = [d for d in self._devices.values() if d.driver is driver]
            for dev in devs:
                del self._devices[dev.code]
                self._outbox.forget(dev)
        for dev in devs:
            if dev.listener is not None:
                driver.unsubscribe(dev.listener)
            fleet = dev.fleet  # in a fleet: "NotHere", and only if ours to say (holding.py)
            if fleet is None or (fleet.holding and fleet.may_say_left(str(self.instance))):
                status = NOT_HERE if fleet else status_text(driver.device_driver_status)
                self._outbox.push_control(Message(dev.code, dev.status_topic,
                                                  self._status(dev, status), 1, True))
            self._outbox.act(lambda dev=dev: self._unsubscribe(dev))  # type: ignore[misc]

    # -- the MQTT thread -------------------------------------------------------------------
    def _make_client(self) -> Client:
        paho = self._paho
        s = self.settings
        client: Client = paho.Client(
            callback_api_version=paho.CallbackAPIVersion.VERSION2,
            client_id=self.client_id,
            clean_session=True,  # no stale writes delivered after a long outage
            protocol=paho.MQTTv311,
        )
        client.max_inflight_messages_set(s.max_inflight)
        client.max_queued_messages_set(max(4 * s.max_inflight, 1000))
        client.connect_timeout = s.connect_timeout / 1000
        client.will_set(self.gateway_topic(),
                        gateway_payload(self.gateway_id, False, "lost"), qos=1, retain=True)
        authenticate(client, s)
        # paho's external-loop mode: with this callback set, publish() queues a message
        # instead of writing it at once, and one loop_write() (our select loop) sends what
        # a pump handed over; our select() asks want_write() itself
        client.on_socket_register_write = write_wanted
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        return client

    def _run(self) -> None:
        client = self._client
        assert client is not None
        s = self.settings
        delay = s.reconnect_min / 1000
        next_attempt = 0.0
        client.connect_async(s.host, s.port, s.keepalive)  # only stores where to connect
        next_status_check = 0.0
        while not self._stopping.is_set():
            now = time.monotonic()
            if client.socket() is None:
                self._connected.clear()
                if self._attempt is not None:  # closed without a callback saying why
                    self._connect_failed("the connection was closed before CONNACK")
                if now >= next_attempt:
                    next_attempt = now + delay * (1 + 0.2 * random.random())
                    delay = min(delay * 2, s.reconnect_max / 1000)
                    try:
                        client.reconnect()
                    except (OSError, ValueError) as exc:  # refused, timeout, TLS handshake
                        self._connect_failed(error_text(exc, self._tls))
                    else:
                        self._attempt = time.monotonic()  # CONNECT sent, CONNACK due
            elif self._attempt is not None and now - self._attempt >= s.connect_timeout / 1000:
                self._connect_failed(f"no CONNACK within {s.connect_timeout} ms "
                                     "(connectTimeout); is this an MQTT broker?")
                abandon(client)
            if self._connected.is_set():
                delay = s.reconnect_min / 1000
                self._run_actions()
                if now >= next_status_check or self._outbox.status_due:
                    next_status_check = now + s.status_check_interval / 1000
                    self._check_statuses(self._outbox.take_status_due(self._held))
                self._sender.pump(client)
            else:
                self._run_actions(connected=False)
                self._sender.spool_outage()
            sock = client.socket()
            timeout = s.status_check_interval / 1000
            replay = self._sender.replay_delay()
            if replay is not None:
                timeout = min(timeout, replay)
            if sock is None:
                timeout = max(0.0, min(timeout, next_attempt - time.monotonic()))
            elif self._attempt is not None:
                timeout = max(0.0, min(timeout, self._attempt + s.connect_timeout / 1000
                                       - time.monotonic()))
            self._wait(client, sock, timeout)
        self._shutdown(client)

    def _connect_failed(self, reason: str) -> None:  # counted always, logged rate-limited
        self._attempt = None
        self._outbox.set_outage(True)
        self._outbox.count("connectFailures")
        self._failures.failed(reason, time.monotonic())

    def _wait(self, client: Client, sock: Any, timeout: float) -> None:
        """Sleep in select() until the broker's socket or our wake-up socket is ready."""
        if sock is not None and hasattr(sock, "pending") and sock.pending():
            timeout = 0.0  # TLS has decrypted bytes buffered: read them now
        wake_r = self._outbox.wake_r
        readers: list[Any] = [wake_r] if sock is None else [wake_r, sock]
        writers: list[Any] = [sock] if sock is not None and client.want_write() else []
        linger = self._linger_until - time.monotonic()
        if linger > 0 and timeout > 0 and not writers and not self._stopping.is_set():
            # woken less than `linger` ago: sleep that out first, so that what arrives
            # meanwhile (reports, acknowledgements) costs one wake-up, not one each
            self._stopping.wait(min(linger, timeout))
            timeout = max(0.0, timeout - linger)
        try:
            readable, writable, _ = select.select(readers, writers, [], timeout)
        except (OSError, ValueError):  # the socket was closed under us: reconnect
            return
        if readable:
            self._linger_until = time.monotonic() + self._linger
        if wake_r in readable:
            self._outbox.woken()
        try:
            if sock is not None and (sock in readable or timeout == 0.0):
                client.loop_read()
            if client.socket() is not None and (writable or client.want_write()):
                write(client)
            if client.socket() is not None:
                client.loop_misc()
        except Exception:  # a bug in a callback must not kill the MQTT thread
            log.exception("MQTT client loop failed")

    def _on_connect(self, client: Client, _userdata: Any, _flags: Any, reason: Any,
                    _props: Any) -> None:
        if getattr(reason, "is_failure", False):
            self._connect_failed(f"the broker refused the connection: {reason}")
            return  # paho closes the socket; the loop retries with backoff
        self._attempt = None
        self._outbox.count("connects")
        failed = self._failures.succeeded()
        log.info("MQTT connected to %s:%d as %s%s", self.settings.host, self.settings.port,
                 self.client_id, f" after {failed} failed attempts" if failed else "")
        self._connected.set()
        self._outbox.set_outage(False)
        self._sender.reconnected()  # qos>0 messages still pending are resent by paho
        client.publish(self.gateway_topic(),
                       gateway_payload(self.gateway_id, True, None), qos=1, retain=True)
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            dev.published_status = None  # republish every status (retained) below
            self._subscribe(dev)
        self._outbox.look_at(devices)

    def _on_disconnect(self, _client: Client, _userdata: Any, _flags: Any, reason: Any,
                       _props: Any) -> None:
        if self._connected.is_set():
            self._outbox.set_outage(True)
            self._outbox.count("disconnects")
            if not self._stopping.is_set():
                log.warning("MQTT connection to %s:%d lost (%s); reconnecting",
                            self.settings.host, self.settings.port, reason)
        elif self._attempt is not None and not self._stopping.is_set():
            why = "" if str(reason) == "Unspecified error" else f" ({reason})"
            hint = ("; is the port TLS-only (set mqtt.tls)?" if not self._tls else
                    "; was our TLS client certificate refused?")
            self._connect_failed(f"the connection was closed before the broker answered "
                                 f"CONNECT{why}{hint}")
        self._connected.clear()

    def _subscribe(self, dev: AttachedDevice) -> None:
        client = self._client
        if client is None or not self._connected.is_set() or not (
                self.settings.writes or dev.fleet is not None):
            return
        with self._lock:
            if self._devices.get(dev.code) is not dev or (
                    dev.fleet is not None and not dev.fleet.holding):
                return
        for topic_filter in dev.filters(self.settings.writes):
            client.subscribe(topic_filter, qos=1)

    def _unsubscribe(self, dev: AttachedDevice) -> None:
        self._held.pop(dev.code, None)  # on the MQTT thread, as ever (detach: an action)
        client = self._client
        if client is None or not self._connected.is_set() or not (
                self.settings.writes or dev.fleet is not None):
            return
        for topic_filter in dev.filters(self.settings.writes):
            client.unsubscribe(topic_filter)

    def _run_actions(self, connected: bool = True) -> None:
        actions = self._outbox.take_actions()
        if connected:
            for action in actions:
                try:
                    action()
                except Exception:
                    log.exception("MQTT action failed")
        # when not connected, subscriptions are made on (re)connect anyway

    def _check_statuses(self, devices: list[AttachedDevice] | None = None) -> None:
        """Publish the statuses that changed, of ``devices`` (None: every device)."""
        if devices is None:
            with self._lock:
                devices = list(self._devices.values())
        for dev in devices:
            status = status_text(dev.driver.device_driver_status)
            if dev.fleet is not None and not self._fleet_turn(dev):
                continue
            if status != dev.published_status:
                dev.published_status = status
                payload = self._status(dev, status)
                with self._lock:
                    self._outbox.control.append(Message(dev.code, dev.status_topic, payload,
                                                        1, True))

    def _status(self, dev: AttachedDevice, status: str) -> bytes:
        return status_payload(self.gateway_id, dev.code, status, (str(self.instance),
                              dev.fleet.since) if dev.fleet is not None else None)

    def _fleet_turn(self, dev: AttachedDevice) -> bool:
        """A fleet device's arrival or departure (holding.py); whether it is held."""
        fleet = dev.fleet
        assert fleet is not None
        turn = fleet.turn(time.time())
        if turn == "arrived":
            dev.published_status, self._held[dev.code] = None, dev
            self._subscribe(dev)
        elif turn == "left":
            self._unsubscribe(dev)
            if fleet.may_say_left(str(self.instance)):
                with self._lock:
                    self._outbox.control.append(Message(
                        dev.code, dev.status_topic, self._status(dev, NOT_HERE), 1, True))
        return fleet.holding

    def _shutdown(self, client: Client) -> None:
        """Last words on a clean stop: statuses, gateway offline, flush, disconnect."""
        try:
            if self._connected.is_set():
                self._check_statuses()
                offline = gateway_payload(self.gateway_id, False, self._stop_reason)
                with self._lock:
                    self._outbox.control.append(Message(None, self.gateway_topic(),
                                                        offline, 1, True))
                started = time.monotonic()
                deadline = started + self._flush_timeout
                left = 0
                while time.monotonic() < deadline and self._connected.is_set():
                    self._sender.pump(client)
                    outbox = self._outbox
                    with self._lock:
                        left = len(outbox.control) + outbox.queued + len(outbox.snapshots)
                    if not left and not self._sender.busy():
                        break
                    self._wait(client, client.socket(), 0.05)
                log.debug("MQTT flush on stop: %.0f ms, %d messages not sent, %d unconfirmed",
                          (time.monotonic() - started) * 1000, left, len(self._sender.window))
                client.disconnect()
                if client.socket() is not None:
                    client.loop_write()
        except Exception:
            log.exception("MQTT shutdown failed")
        finally:
            self._sender.spool_outage()  # what was not sent is kept for the next start
            with contextlib.suppress(Exception):
                sock = client.socket()
                if sock is not None:
                    sock.close()
            self._connected.clear()

    # -- commands ------------------------------------------------------------------------
    def _on_message(self, _client: Client, _userdata: Any, message: MQTTMessage) -> None:
        topic = message.topic
        payload = bytes(message.payload)
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            if dev.fleet is not None and topic == dev.status_topic:
                if dev.fleet.read_back(payload, str(self.instance)):
                    dev.published_status = None  # publish ours again (holding.py)
                    self._outbox.status_changed(dev)
                return
            if topic == dev.action_topic:
                self._commands.dispatch(dev, None, payload, action=True)
                return
            if topic == dev.read_topic:
                self._commands.dispatch(dev, None, payload, read=True)
                return
            if topic == dev.batch_command_topic:
                self._commands.dispatch(dev, None, payload)
                return
            if topic.startswith(dev.command_prefix):
                self._commands.dispatch(dev, topic[len(dev.command_prefix):], payload)
                return
