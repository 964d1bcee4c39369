"""The Sparkplug B edge node: its lifecycle, the drivers it publishes (one Sparkplug device
each) and the thread that orders births, data and deaths.  The package's ``__init__.py``
describes the messages and threads."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from ...config import ConfigError
from ...datatypes import DeviceDriverStatus
from ...driver import DriverModbusRtu
from ..mqtt.holding import Holding
from ..mqtt.settings import MqttSettings, check_name
from .bdseq import RedisBdSeqStore
from .devices import DeviceListener, NodeDevice, is_good
from .inbox import CommandInbox, CommandLog, RebirthPacer
from .payloads import Sample, device_birth, device_data, device_death, node_birth, node_death
from .reads import ReadRunner
from .session import NodeSession
from .settings import check_id, node_id_for
from .state import HostState
from .writes import WriteRunner

if TYPE_CHECKING:
    from paho.mqtt.client import MQTTMessage

log = logging.getLogger("edgemodbus.sparkplug")

NAMESPACE = "spBv1.0"
_COUNTERS = ("connects", "disconnects", "connectFailures", "published", "publishErrors",
             "dropped", "nbirths", "dbirths", "ddata", "ddeaths", "rebirths", "commands",
             "commandErrors", "writes", "writesRefused", "rebirthsFolded", "reads",
             "readsRefused", "commandsNotHeld")


def _now() -> int:
    return time.time_ns() // 1_000_000


class SparkplugPublisher:
    """A Sparkplug B (v3.0) edge node on an MQTT broker: one device per attached driver.

    ``attach(driver, "dev1")`` (before or after ``start_device``), ``start()`` connects in
    the background and returns at once, ``stop()`` publishes NDEATH and disconnects.  The
    same methods as :class:`~edgemodbus.northbound.mqtt.MqttPublisher`, so the gateway
    uses either.  ``instance``: this instance's id in a dial-in fleet (docs/deploy.md):
    the node id names it (settings.py ``node_id_for``) and a device attached with
    ``held`` is born only while its DTU is connected here."""

    def __init__(self, settings: MqttSettings | Mapping[str, Any], *,
                 gateway_id: str = "edgemodbus", instance: str | None = None,
                 bd_seq_store: RedisBdSeqStore | None = None) -> None:
        try:
            import paho.mqtt.client as paho
        except ImportError:  # pragma: no cover - depends on the install
            raise ImportError("Sparkplug needs paho-mqtt and protobuf: "
                              "pip install 'edgemodbus[sparkplug]'") from None
        if not isinstance(settings, MqttSettings):
            settings = MqttSettings.load(settings)
        if settings.sparkplug is None:
            raise ValueError('mqtt.sparkplug: needed by a Sparkplug publisher, e.g. '
                             '"sparkplug": {"groupId": "plant1"}')
        self.settings = settings
        sp = settings.sparkplug
        self.gateway_id = check_name("gatewayId", gateway_id)
        self.group_id = sp.group_id
        self.instance = None if instance is None else check_name("instanceId", instance)
        self.node_id = node_id_for(sp.edge_node_id, self.gateway_id, self.instance,
                                   shared=bd_seq_store is not None)
        self.client_id = settings.client_id or f"edgemodbus-{self.gateway_id}" + (
            f"-{self.instance}" if self.instance else "")  # one per instance, as mqtt's
        self._paho = paho
        self._base = f"{NAMESPACE}/{self.group_id}"
        self._ncmd = f"{self._base}/NCMD/{self.node_id}"
        self._dcmd = f"{self._base}/DCMD/{self.node_id}/"
        self._host = HostState(sp.primary_host_id)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._events: deque[tuple[Any, ...]] = deque()  # control: connects, commands...
        # (device, its report's number, samples), bounded
        self._samples: deque[tuple[NodeDevice, int, list[Sample]]] = deque()
        self._queued = 0  # samples in self._samples
        self._devices: dict[str, NodeDevice] = {}
        self._counts = dict.fromkeys(_COUNTERS, 0)
        self._session = NodeSession(
            paho, settings, self.client_id, node_name=f"{self.group_id}/{self.node_id}",
            death_topic=self.topic("NDEATH"), death=lambda bd: node_death(bd, _now()),
            subscriptions=self._subscriptions, count=self._count, push=self._push,
            on_message=self._on_message, store=bd_seq_store)
        self.bd_seq: int | None = None  # the session's (the NBIRTH's and the will's)
        self._seq = 0
        self._born = False  # NBIRTH published in this session, no NDEATH since
        self._aliases: dict[tuple[str, str], int] = {}
        self._logs = CommandLog(log)
        self._writes = WriteRunner(self._count, self._logs)
        self._reads = ReadRunner(self._count, self._logs)
        self._inbox = CommandInbox(self._count, self._push, self._device_named,
                                   self._writes.command, self._logs, self._read_now)
        self._rebirths = RebirthPacer(sp.rebirth_interval / 1000)
        self._connected = self._session.connected
        self._thread: threading.Thread | None = None
        self._closed = False

    # -- topics --------------------------------------------------------------------------
    def topic(self, kind: str, device: str | None = None) -> str:
        """``spBv1.0/<group>/<kind>/<node>[/<device>]``."""
        node = f"{self._base}/{kind}/{self.node_id}"
        return node if device is None else f"{node}/{device}"

    def check_item_names(self, device_code: str, names: Iterable[str]) -> None:
        """Raise ValueError if the device code cannot be a Sparkplug device id (item names
        are metric names: any text)."""
        check_id("deviceCode", device_code)
        for name in names:
            if not name:
                raise ValueError(f"device {device_code!r}: an item has an empty name")

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> SparkplugPublisher:
        """Connect in the background; births follow the connection (and the primary
        host's STATE online, when one is configured)."""
        if self._thread is not None:
            return self
        if self._closed:
            raise RuntimeError("SparkplugPublisher cannot be restarted after stop()")
        problems = self.settings.tls.problems() if self.settings.tls is not None else []
        assert self.settings.sparkplug is not None
        problems += self.settings.sparkplug.problems()
        if problems:
            raise ConfigError(problems)
        self._writes.start()
        self._thread = threading.Thread(target=self._run, name="edgemodbus-sparkplug",
                                        daemon=True)
        self._thread.start()
        self._session.start()
        return self

    def stop(self, timeout: float = 1.0, reason: str = "shutdown") -> None:
        """Publish NDEATH (if connected), wait at most ``timeout`` s for it to go out,
        disconnect (the broker then drops the will) and join the threads.  Idempotent."""
        self._writes.stop()
        thread = self._thread
        if thread is not None:
            with self._lock:
                self._session.stopping = True
                self._events.append(("stop", timeout, reason))
                self._wake.notify()
            thread.join(timeout + 2.0)
            self._session.close()
            self._thread = None
        self._connected.clear()
        self._closed = True

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout: float) -> bool:
        return self._connected.wait(timeout)

    def lead(self, leader: bool) -> None:
        """A redundant pair's shared node (``bd_seq_store`` given): connect as the edge
        node while this instance leads, NDEATH and disconnect when it no longer does."""
        self._push(("lead", leader))

    def rebirth(self) -> None:
        """NBIRTH and every DBIRTH again (what NCMD ``Node Control/Rebirth`` does, paced
        by ``rebirthInterval`` as it is)."""
        self._push(("rebirth",))

    def stats(self) -> dict[str, Any]:
        """Counters (camelCase) as MqttPublisher's, plus the Sparkplug ones (births,
        ddata, ddeaths, rebirths, rebirthsFolded, writes, writesRefused, commandErrors,
        commandLogsSuppressed), bdSeq and seq."""
        with self._lock:
            result: dict[str, Any] = dict(self._counts)
            result["queued"] = self._queued
            result["queueSize"] = self.settings.queue_size
            result["devices"] = {d.code: {"published": d.published, "dropped": d.dropped,
                                          "born": d.born, "held": d.here()}
                                 for d in self._devices.values()}
            result["bdSeq"] = self.bd_seq
            result["seq"] = self._seq
            result["born"] = self._born
        result["pendingCommands"] = self._writes.pending
        result["commandLogsSuppressed"] = self._logs.suppressed
        result["connected"] = self.connected
        return result

    # -- drivers -------------------------------------------------------------------------
    def attach(self, driver: DriverModbusRtu, device_code: str | None = None, *,
               held: Callable[[], bool] | None = None) -> None:
        """Publish ``driver`` as Sparkplug device ``device_code`` (default the driver's):
        subscribes to it, leaving its other subscribers and callbacks as they are.  In a
        fleet, ``held`` says whether its DTU is connected here: DBIRTH when it arrives,
        DDEATH when it leaves, nothing (and no DCMD) in between (holding.py)."""
        code = device_code or str(driver.snapshot()["deviceCode"])
        self.check_item_names(code, [])
        dev = NodeDevice(driver, code)
        dev.fleet = Holding(held) if held is not None and self.instance else None
        with self._lock:
            if code in self._devices:
                raise ValueError(f"deviceCode {code!r} is already attached to this publisher")
            self._devices[code] = dev
        dev.listener = listener = DeviceListener(self._offer, dev)
        try:
            driver.subscribe(listener)
        except BaseException:
            with self._lock:
                del self._devices[code]
            raise
        self._push(("attach", dev))

    def detach(self, driver: DriverModbusRtu) -> None:
        """Stop publishing ``driver``: DDEATH (if it was born), our listener unsubscribed
        (only ours: the driver's other subscribers stay)."""
        with self._lock:
            devs = [d for d in self._devices.values() if d.driver is driver]
            for dev in devs:
                del self._devices[dev.code]
        for dev in devs:
            if dev.listener is not None:
                driver.unsubscribe(dev.listener)
            self._push(("detach", dev))

    def _offer(self, dev: NodeDevice, samples: list[Sample]) -> None:
        """From a line worker: queue, never block; past ``queueSize`` the oldest are
        dropped and their device is born again (its DBIRTH carries every value)."""
        with self._lock:
            dev.offered += 1
            self._samples.append((dev, dev.offered, samples))
            self._queued += len(samples)
            while self._queued > self.settings.queue_size and len(self._samples) > 1:
                old, _, lost = self._samples.popleft()
                self._queued -= len(lost)
                old.dropped += len(lost)
                self._counts["dropped"] += len(lost)
                self._events.append(("resync", old))
            self._wake.notify()

    def _push(self, event: tuple[Any, ...]) -> None:
        with self._lock:
            self._events.append(event)
            self._wake.notify()

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n

    # -- the paho client (its network thread calls these) ------------------------------
    def _subscriptions(self) -> list[tuple[str, int]]:
        """Commands, and the primary host's STATE (its retained one comes before any
        NBIRTH)."""
        topics = [(self._ncmd, 1), (self._dcmd + "+", 1)]
        if self._host.topic is not None:
            topics.append((self._host.topic, 1))
        return topics

    def _on_message(self, _client: Any, _userdata: Any, message: MQTTMessage) -> None:
        topic, payload = message.topic, bytes(message.payload)
        if topic == self._host.topic:
            self._push(("state", payload))
        elif topic == self._ncmd:
            self._inbox.node(payload)
        elif topic.startswith(self._dcmd):
            self._inbox.device_command(topic[len(self._dcmd):], payload)

    def _read_now(self, dev: NodeDevice | None, names: list[str] | None) -> None:
        """A read on demand of ``dev`` (``names``: these items), or of every attached
        device (paho's thread)."""
        if dev is None:
            with self._lock:
                devices = list(self._devices.values())
            for one in devices:
                self._reads.read(one)
        else:
            self._reads.read(dev, names)

    def _device_named(self, code: str) -> NodeDevice | None:
        with self._lock:
            return self._devices.get(code)

    # -- the Sparkplug thread ------------------------------------------------------------
    def _run(self) -> None:
        interval = self.settings.status_check_interval / 1000
        next_check = time.monotonic() + interval
        while True:
            with self._lock:
                while not self._events and not self._samples:
                    left = min(next_check, self._logs.next_due(),
                               self._rebirths.due or next_check) - time.monotonic()
                    if left <= 0:
                        break
                    self._wake.wait(left)
                events = list(self._events)
                self._events.clear()
                samples = list(self._samples)
                self._samples.clear()
                self._queued = 0
            try:
                for event in events:
                    if event[0] == "stop":
                        self._shutdown(event[1])
                        return
                    self._handle(event)
                for dev, number, batch in samples:
                    self._data(dev, number, batch)
                if self._rebirths.take_due():
                    self._rebirth()
                self._logs.flush()
                if time.monotonic() >= next_check:
                    next_check = time.monotonic() + interval
                    self._check_devices()
            except Exception:  # a bug must not end publishing
                log.exception("Sparkplug: publishing failed")

    def _handle(self, event: tuple[Any, ...]) -> None:
        kind = event[0]
        if kind == "connected":
            self.bd_seq, self._born = event[1], False
            self._host.reset()
            self._birth_all()
        elif kind == "disconnected":
            self._unborn()
        elif kind == "state":
            change = self._host.update(event[1])
            if change is True:
                self._birth_all()
            elif change is False:
                self._host_offline()
        elif kind == "rebirth":
            if self._rebirths.request():
                self._rebirth()
            else:
                self._count("rebirthsFolded")
        elif kind == "attach":
            self._device_birth(event[1])
        elif kind == "detach":
            dev = event[1]
            if dev.born and self._born:
                self._death(dev)
        elif kind == "lead":
            if not event[1] and self._born:
                self._session.goodbye(self._session_bd_seq(), 1.0)
            self._unborn()
            self._session.lead(event[1])
        elif kind == "resync" and event[1].born:
            self._device_birth(event[1])

    def _rebirth(self) -> None:
        log.info("Sparkplug: rebirth: NBIRTH and every DBIRTH again")
        self._count("rebirths")
        self._birth_all()

    def _session_bd_seq(self) -> int:
        return self.bd_seq if self.bd_seq is not None else 0

    def _host_offline(self) -> None:
        """The primary host went offline (Sparkplug 3.0, the edge node's behaviour on
        its STATE): NDEATH, disconnect, connect again (a new session, bdSeq + 1) and wait for
        the host's online STATE before NBIRTH."""
        log.warning("Sparkplug: primary host %s offline: NDEATH, reconnecting; births wait "
                    "for it to come back", self._host.host_id)
        if self._born:
            self._session.goodbye(self._session_bd_seq(), 1.0)
        self._unborn()
        self._session.restart()

    def _unborn(self) -> None:
        self._born = False
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            dev.born = False

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % 256
        return self._seq

    def _publish(self, topic: str, payload: bytes, qos: int = 0) -> bool:
        client = self._session.client
        if client is None or not self._connected.is_set():
            return False
        info = client.publish(topic, payload, qos=qos, retain=False)
        if info.rc != self._paho.MQTT_ERR_SUCCESS:
            self._count("publishErrors")
            return False
        self._count("published")
        return True

    def _birth_all(self) -> None:
        """NBIRTH (seq 0) then a DBIRTH per running device, once connected and (with a
        primary host) the host is online."""
        if not self._connected.is_set() or not self._host.online:
            return
        self._unborn()
        self._seq = 0
        if not self._publish(self.topic("NBIRTH"), node_birth(self._session_bd_seq(), _now())):
            return
        self._born = True
        self._count("nbirths")
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            self._device_birth(dev)

    def _alias(self, code: str, name: str) -> int:
        key = (code, name)
        alias = self._aliases.get(key)
        if alias is None:  # unique in the edge node and kept for the process' life
            alias = self._aliases[key] = len(self._aliases) + 1
        return alias

    def _device_birth(self, dev: NodeDevice) -> None:
        with self._lock:
            attached = self._devices.get(dev.code) is dev
        if not self._born or not attached:
            return
        if dev.driver.device_driver_status is not DeviceDriverStatus.RUNNING or not dev.here():
            if dev.born:
                self._death(dev)
            return
        if not dev.first_cycle_done():
            return  # born by the report that ends it, or by the next status check
        with self._lock:  # the reports queued so far: the birth's values include them
            dev.born_at = dev.offered
        payload = device_birth(self._next_seq(), _now(), dev.birth(self._alias))
        if self._publish(self.topic("DBIRTH", dev.code), payload):
            dev.born = True
            dev.published += 1
            self._count("dbirths")

    def _death(self, dev: NodeDevice) -> None:
        dev.born = False
        if self._publish(self.topic("DDEATH", dev.code), device_death(self._next_seq(),
                                                                      _now())):
            self._count("ddeaths")

    def _data(self, dev: NodeDevice, number: int, samples: list[Sample]) -> None:
        if not self._born:
            return  # the births after (re)connecting carry the current values
        if not dev.here():  # a fleet device whose DTU left: not ours to publish
            if dev.born:
                self._death(dev)
            return
        if dev.born and number <= dev.born_at:
            return  # queued before its DBIRTH, which carried these values already
        if not dev.born or any(s.name not in dev.metrics for s in samples):
            self._device_birth(dev)  # a new item, or a device that was not born yet
            return
        metrics = []
        bad = dev.bad
        for sample in samples:
            good = is_good(sample)
            recovered = good and sample.name in bad
            if good:
                bad.discard(sample.name)
            else:
                bad.add(sample.name)
            metrics.append((sample, dev.metrics[sample.name], recovered))
        if self._publish(self.topic("DDATA", dev.code),
                         device_data(self._next_seq(), _now(), metrics)):
            dev.published += 1
            self._count("ddata")

    def _check_devices(self) -> None:
        """A device that stopped running (or, in a fleet, whose DTU left) gets DDEATH;
        one running again (or whose items changed, or whose DTU arrived) a DBIRTH."""
        if not self._born:
            return
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            turned = dev.fleet.turn(time.time()) if dev.fleet is not None else None
            if turned is not None:
                log.info("Sparkplug: device %s: its DTU %s", dev.code, turned)
            running = dev.driver.device_driver_status is DeviceDriverStatus.RUNNING
            if dev.born and not (running and dev.here()):
                log.info("Sparkplug: device %s is %s: DDEATH", dev.code,
                         dev.driver.device_driver_status.value if dev.here() else "not here")
                self._death(dev)
            elif not dev.here():
                continue
            elif running and (not dev.born or dev.changed_items()):
                self._device_birth(dev)

    def _shutdown(self, timeout: float) -> None:
        """NDEATH on a clean stop (Sparkplug 3.0, 7.1.5), confirmed or ``timeout``."""
        if self._born:
            self._session.goodbye(self._session_bd_seq(), timeout)
        self._born = False
        self._logs.flush(force=True)  # the summaries of folded command log lines
