"""MQTT northbound: item changes, snapshots, device and gateway status, writes from MQTT.

Needs the extra ``edgemodbus[mqtt]`` (paho-mqtt); ``import edgemodbus`` never imports
this module, and paho is imported only when a :class:`MqttPublisher` is made.

Threads and queues (why polling is never blocked):

* the driver's batch callback and snapshot publisher run on the bus worker thread; here
  they only copy the reported fields into a bounded queue (oldest updates are dropped
  and counted when it is full) or replace the device's pending snapshot (latest wins);
* one ``edgemodbus-mqtt`` thread owns the paho client (external-loop mode: our own
  ``select``), connects and reconnects with exponential backoff and jitter, serialises
  to JSON and publishes; nothing else touches the client;
* a connection attempt fails when the TCP connect or TLS handshake fails, when the peer
  closes before CONNACK (a plain client on a TLS-only port), when no CONNACK comes within
  ``connectTimeout``, or when the broker refuses (CONNACK code); each failure is counted
  (``connectFailures``) and logged with its reason: the first at once, then at most one
  line per ``failureLogInterval`` with the number of attempts since (each one at debug);
* writes received on the command topics run on one ``edgemodbus-mqtt-cmd`` thread with an
  asyncio loop through ``write_addresses_async`` (many devices' writes in flight at once;
  per device in arrival order); the result goes to the reply topic.

Topic layout (every template configurable; placeholders ``{prefix}``, ``{deviceCode}``,
``{itemName}``, ``{gatewayId}``)::

    {prefix}/{deviceCode}/{itemName}      item change  {"value","status","updateTs","errorReason"}
    /real/{deviceCode}                    periodic snapshot (the seed's topic), retained
    {prefix}/{deviceCode}/$status         device status, retained
    {prefix}/$gateway/{gatewayId}         gateway online/offline, retained; last will: offline
    {prefix}/{deviceCode}/set/{itemName}  write one item: a JSON value, or {"value", "id"}
    {prefix}/{deviceCode}/set             write several: {"name": value, ...} or {"items", "id"}
    {prefix}/{deviceCode}/$reply          result of a write: {"id","ok","error","items","ts"}
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import random
import select
import socket
import ssl
import string
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, cast

from pydantic import ValidationError, field_validator, model_validator

from ...config import MAX_MS, Choice, ConfigError, Model, Ms, Problem, Range
from ...driver import DriverModbusRtu

if TYPE_CHECKING:
    from paho.mqtt.client import Client, MQTTMessage, MQTTMessageInfo

    from ...config import DeviceAddressItem

log = logging.getLogger("edgemodbus.mqtt")

PLACEHOLDERS = ("prefix", "deviceCode", "itemName", "gatewayId")
_FORBIDDEN = ("+", "#", "\0")
_MAX_COMMAND_BYTES = 65536
_MAX_PENDING_COMMANDS = 256
_CONTROL_LIMIT = 10_000


class TlsSettings(Model):
    """TLS to the broker: CA file (else the system's), optional client certificate.

    ``enabled: false`` keeps the section in the file without using it (the shipped
    example does so).  :meth:`problems` checks the files before any connection."""

    _where: ClassVar[str] = "mqtt.tls"

    enabled: bool = True
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    insecure: bool = False  # skip the host name check (self-signed lab brokers only)

    def files(self) -> dict[str, str]:
        """The file fields that are set, JSON key -> path."""
        named = {"caFile": self.ca_file, "certFile": self.cert_file, "keyFile": self.key_file}
        return {key: path for key, path in named.items() if path is not None}

    def resolved(self, base: str | os.PathLike[str]) -> TlsSettings:
        """A copy whose relative file paths are taken from folder ``base``."""
        update = {_SNAKE[key]: str(Path(base, path)) for key, path in self.files().items()
                  if not os.path.isabs(path)}
        return self.model_copy(update=update) if update else self

    def problems(self, where: str = "mqtt.tls") -> list[Problem]:
        """What is wrong with the files (missing, unreadable, not PEM, key without its
        certificate), each named by its field; [] when TLS can be set up from them."""
        if not self.enabled:
            return []
        found: list[Problem] = []
        for field, path in self.files().items():
            message = _file_problem(path)
            if message is None and field == "caFile":
                message = _ssl_problem(ssl.create_default_context, cafile=path)
            if message is not None:
                found.append(Problem(f"{where}.{field}", path, message))
        if self.key_file is not None and self.cert_file is None:
            found.append(Problem(f"{where}.keyFile", self.key_file,
                                 "needs certFile (the client certificate of this key)"))
        cert, key = self.cert_file, self.key_file
        if not found and cert is not None:
            found += _pem_problems(f"{where}.certFile", cert, "CERTIFICATE", "certificate")
            key_field, key_path = (("keyFile", key) if key is not None else
                                   ("certFile", cert))  # no keyFile: the key is in certFile
            found += _pem_problems(f"{where}.{key_field}", key_path, "PRIVATE KEY",
                                   "private key", "" if key is not None else
                                   " (keyFile is not set, so the key must be in certFile)")
        if not found and cert is not None:
            chain = ssl.create_default_context().load_cert_chain
            problem = _ssl_problem(chain, cert, key, password=_no_password)
            if problem is not None:
                found.append(Problem(f"{where}.certFile/keyFile", f"{cert}, {key}", problem))
        return found


_SNAKE = {"caFile": "ca_file", "certFile": "cert_file", "keyFile": "key_file"}


def _file_problem(path: str) -> str | None:
    """Why ``path`` cannot be read as a file by this process, or None."""
    try:
        with open(path, "rb") as file:
            file.read(1)
    except FileNotFoundError:
        return "no such file"
    except IsADirectoryError:
        return "is a directory, not a file"
    except PermissionError:
        return f"not readable by this process (uid {os.geteuid()}): permission denied"
    except OSError as exc:
        return f"cannot be read: {exc.strerror or exc}"
    return None


def _no_password() -> bytes:
    raise ValueError("the key is encrypted; give an unencrypted key file")


def _pem_problems(field: str, path: str, label: str, what: str,
                  hint: str = "") -> list[Problem]:
    """[] if the file holds a PEM block ``-----BEGIN ...{label}-----``."""
    with open(path, "rb") as file:
        text = file.read(1 << 20)
    if f"{label}-----".encode() in text and b"-----BEGIN " in text:
        return []
    return [Problem(field, path, f"no PEM {what} in it{hint}")]


_SSL_REASONS = {
    "NO_CERTIFICATE_OR_CRL_FOUND": "no PEM certificate in it",
    "KEY_VALUES_MISMATCH": "the key does not belong to the certificate",
}


def _ssl_problem(load: Callable[..., object], *args: Any, **kwargs: Any) -> str | None:
    """Why OpenSSL refuses the files ``load(*args, **kwargs)`` reads (not PEM, key and
    certificate do not match...), or None."""
    try:
        load(*args, **kwargs)
    except ssl.SSLError as exc:
        reason = str(exc.reason or exc)
        return _SSL_REASONS.get(reason, f"not usable for TLS: {reason}")
    except (ValueError, OSError) as exc:
        return f"not usable for TLS: {exc}"
    return None


def _template_fields(template: str) -> list[str]:
    return [f for _, f, _, _ in string.Formatter().parse(template) if f is not None]


def _check_template(template: str, allowed: tuple[str, ...], *, last: str | None = None) -> str:
    """A topic template uses only ``allowed`` placeholders, no wildcards; ``last`` (if
    given) must be its final placeholder (command topics are subscribed with ``#``)."""
    if not template:
        raise ValueError("must not be empty")
    try:
        fields = _template_fields(template)
    except ValueError as exc:
        raise ValueError(f"is not a valid template ({exc})") from None
    for name in fields:
        if name not in allowed:
            raise ValueError(
                f"unknown placeholder {{{name}}}; allowed: "
                + ", ".join(f"{{{a}}}" for a in allowed)
            )
    literal = "".join(text for text, _, _, _ in string.Formatter().parse(template))
    if any(ch in literal for ch in _FORBIDDEN):
        raise ValueError("must not contain MQTT wildcards (+, #) or NUL")
    if last is not None and (
        not template.endswith("/{" + last + "}") or fields.count(last) != 1
    ):
        raise ValueError(f"must end with /{{{last}}} (a topic level of its own, used once)")
    return template


class MqttSettings(Model):
    """The ``mqtt`` section of the gateway file.  Times in ms unless named otherwise."""

    _where: ClassVar[str] = "mqtt"

    enabled: bool = True
    host: str = "127.0.0.1"
    port: Annotated[int, Range(1, 65535)] = 1883
    client_id: str | None = None  # default: edgemodbus-{gatewayId}
    username: str | None = None
    password: str | None = None
    keepalive: Annotated[int, Range(5, 3600)] = 30  # seconds (MQTT's unit)
    connect_timeout: Annotated[int, Range(100, 60_000)] = 5000
    tls: TlsSettings | None = None
    topic_prefix: str = "edgemodbus"
    item_topic: str = "{prefix}/{deviceCode}/{itemName}"
    snapshot_topic: str = "/real/{deviceCode}"
    status_topic: str = "{prefix}/{deviceCode}/$status"
    gateway_topic: str = "{prefix}/$gateway/{gatewayId}"
    command_topic: str = "{prefix}/{deviceCode}/set/{itemName}"
    batch_command_topic: str = "{prefix}/{deviceCode}/set"
    reply_topic: str = "{prefix}/{deviceCode}/$reply"
    qos: Annotated[int, Choice((0, 1, 2))] = 0  # item updates: a stream, state is retained
    retain: bool = False
    snapshot_qos: Annotated[int, Choice((0, 1, 2))] = 1
    snapshot_retain: bool = True
    snapshot_interval: Annotated[int, Range(0, MAX_MS)] = 0
    writes: bool = True
    queue_size: Annotated[int, Range(1, 10_000_000)] = 10_000
    max_inflight: Annotated[int, Range(1, 65_535)] = 100
    reconnect_min: Ms = 500
    reconnect_max: Ms = 30_000
    failure_log_interval: Ms = 60_000  # failed connects: first logged, then one line per this
    status_check_interval: Ms = 500

    @field_validator("topic_prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        if any(ch in value for ch in _FORBIDDEN):
            raise ValueError("must not contain MQTT wildcards (+, #) or NUL")
        return value

    @field_validator("item_topic")
    @classmethod
    def _item_topic(cls, value: str) -> str:
        return _check_template(value, PLACEHOLDERS)

    @field_validator("command_topic")
    @classmethod
    def _command_topic(cls, value: str) -> str:
        return _check_template(value, PLACEHOLDERS, last="itemName")

    @field_validator(
        "snapshot_topic", "status_topic", "batch_command_topic", "reply_topic"
    )
    @classmethod
    def _device_topics(cls, value: str) -> str:
        return _check_template(value, ("prefix", "deviceCode", "gatewayId"))

    @field_validator("gateway_topic")
    @classmethod
    def _gateway_topic(cls, value: str) -> str:
        return _check_template(value, ("prefix", "gatewayId"))

    @classmethod
    def load(cls, data: Mapping[str, Any], where: str = "mqtt") -> MqttSettings:
        """Validate a mapping; ConfigError with paths under ``where`` (``mqtt.qos``)."""
        try:
            return cls.model_validate(dict(data))
        except ValidationError as exc:
            raise ConfigError.from_validation_error(exc, where) from None

    @model_validator(mode="after")
    def _backoff(self) -> MqttSettings:
        if self.reconnect_max < self.reconnect_min:
            raise ValueError(f"reconnectMax {self.reconnect_max} must be >= reconnectMin "
                             f"({self.reconnect_min})")
        return self


def check_name(kind: str, name: str) -> str:
    """A device code or gateway id must be usable as one topic level."""
    if not name:
        raise ValueError(f"{kind} must not be empty for MQTT topics")
    bad = [ch for ch in _FORBIDDEN if ch in name]
    if bad or "/" in name:
        raise ValueError(
            f"{kind} {name!r} cannot be used in MQTT topics: it contains "
            f"{' '.join(repr(c) for c in bad + (['/'] if '/' in name else []))}; "
            "use letters, digits, '-', '_' or '.'"
        )
    return name


def jsonable(value: Any) -> Any:
    """A value as JSON can carry it: datetimes as ISO 8601, bytes as hex, and non-finite
    floats (NaN, infinities) as null, since strict JSON has no such numbers."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    return value


def _deep_jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _deep_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_deep_jsonable(v) for v in obj]
    return jsonable(obj)


def _dumps(obj: Any) -> bytes:
    try:
        text = json.dumps(obj, ensure_ascii=False, separators=(",", ":"), allow_nan=False,
                          default=str)
    except ValueError:  # a NaN somewhere: the slow, careful path
        text = json.dumps(_deep_jsonable(obj), ensure_ascii=False, separators=(",", ":"),
                          default=str)
    return text.encode()


def _now() -> str:
    return datetime.now(timezone.utc).isoformat()


def _status_text(status: Any) -> str:
    return str(getattr(status, "value", status))


class _Device:
    """What the publisher keeps per attached driver."""

    __slots__ = (
        "batch_topic", "code", "command_prefix", "driver", "dropped", "item_heads", "item_topics",
        "prev_batch", "prev_snapshot", "published", "published_status", "reply_topic",
        "seen_status", "snapshot_topic", "snapshots", "snapshots_coalesced", "status_topic",
    )

    def __init__(self, publisher: MqttPublisher, driver: DriverModbusRtu, code: str) -> None:
        s = publisher.settings
        fmt = publisher.topic
        self.driver = driver
        self.code = code
        self.snapshot_topic = fmt(s.snapshot_topic, code)
        self.status_topic = fmt(s.status_topic, code)
        self.reply_topic = fmt(s.reply_topic, code)
        self.batch_topic = fmt(s.batch_command_topic, code)
        self.command_prefix = fmt(s.command_topic, code, "\0").removesuffix("\0")
        self.item_topics: dict[str, str] = {}
        self.item_heads: dict[str, bytes] = {}  # topic length + topic, for raw packets
        self.prev_batch: Callable[[list[DeviceAddressItem]], None] | None = None
        self.prev_snapshot: Callable[[str, dict[str, Any]], None] | None = None
        self.published = 0
        self.dropped = 0
        self.snapshots = 0
        self.snapshots_coalesced = 0
        self.published_status: str | None = None
        self.seen_status: Any = None

    def filters(self) -> list[str]:
        """Subscriptions for this device's commands, without overlaps (an overlap
        would deliver one command twice)."""
        filters = [self.command_prefix + "#"]
        if self.batch_topic + "/" != self.command_prefix:
            filters.append(self.batch_topic)
        return filters


_Row = tuple[_Device, str, Any, Any, Any, Any]  # device, name, value, status, ts, error
_Control = tuple[str, bytes, int, bool]  # topic, payload, qos, retain


class MqttPublisher:
    """Publishes what attached drivers report to an MQTT broker and accepts writes.

    ``publisher.attach(driver, "dev1")`` (before or after ``start_device``) hooks the
    driver's batch callback and snapshot publisher; ``start()`` connects in the
    background and returns at once; ``stop()`` publishes the gateway offline, flushes
    briefly and disconnects, never waiting for an unreachable broker.
    """

    def __init__(self, settings: MqttSettings | Mapping[str, Any] | None = None, *,
                 gateway_id: str = "edgemodbus") -> None:
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
        self._lock = threading.Lock()
        self._rows: deque[_Row] = deque()
        self._snapshots: dict[str, tuple[_Device, dict[str, Any]]] = {}
        self._control: deque[_Control] = deque()
        self._actions: deque[Callable[[], None]] = deque()
        self._devices: dict[str, _Device] = {}
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._wake_pending = False
        self._status_dirty = False
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._client: Client | None = None
        self._connected = threading.Event()
        self._attempt: float | None = None  # when the pending CONNECT went out
        self._tls = settings.tls is not None and settings.tls.enabled
        self._failures = _FailureLog(f"{settings.host}:{settings.port}",
                                     settings.failure_log_interval / 1000,
                                     settings.reconnect_max / 1000)
        self._window: deque[MQTTMessageInfo] = deque()
        self._flush_timeout = 1.0
        self._stop_reason = "shutdown"
        self.client_id = settings.client_id or f"edgemodbus-{self.gateway_id}"
        self._counts: dict[str, int] = dict.fromkeys(
            ("connects", "disconnects", "connectFailures", "published", "dropped",
             "publishErrors", "snapshotsPublished", "snapshotsCoalesced", "commands",
             "commandErrors", "controlDropped"), 0)
        self._raw_queue: Callable[..., Any] | None = None
        self._cmd_loop: asyncio.AbstractEventLoop | None = None
        self._cmd_thread: threading.Thread | None = None
        self._pending_commands = 0
        self._closed = False

    # -- topics --------------------------------------------------------------------------
    def topic(self, template: str, device_code: str = "", item_name: str = "") -> str:
        """A topic template filled in for this gateway."""
        return template.format(prefix=self.settings.topic_prefix, deviceCode=device_code,
                               itemName=item_name, gatewayId=self.gateway_id)

    def item_topic(self, device_code: str, item_name: str) -> str:
        return self.topic(self.settings.item_topic, device_code, item_name)

    def check_item_names(self, device_code: str, names: Iterable[str]) -> None:
        """Raise ValueError if an item's topic is also a command, status or reply topic
        of this device (a publish there would be read back as a command)."""
        check_name("deviceCode", device_code)
        s = self.settings
        matches = self._paho.topic_matches_sub
        reserved = {
            self.topic(s.status_topic, device_code): "status",
            self.topic(s.reply_topic, device_code): "reply",
            self.topic(s.snapshot_topic, device_code): "snapshot",
        }
        command = self.topic(s.command_topic, device_code, "\0").removesuffix("\0") + "#"
        batch = self.topic(s.batch_command_topic, device_code)
        for name in names:
            if any(ch in name for ch in _FORBIDDEN):
                raise ValueError(
                    f"item {name!r} of device {device_code!r}: MQTT topics cannot contain "
                    "'+', '#' or NUL; rename the item"
                )
            topic = self.item_topic(device_code, name)
            clash = reserved.get(topic)
            if clash is None and (topic == batch or (s.writes and matches(command, topic))):
                clash = "command"
            if clash is not None:
                raise ValueError(
                    f"item {name!r} of device {device_code!r}: its topic {topic!r} is the "
                    f"device's {clash} topic; rename the item or change mqtt.itemTopic"
                )

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
        self._client = self._make_client()
        if self.settings.writes:
            loop = asyncio.new_event_loop()
            self._cmd_loop = loop
            self._cmd_thread = threading.Thread(
                target=self._run_commands, args=(loop,), name="edgemodbus-mqtt-cmd",
                daemon=True)
            self._cmd_thread.start()
        self._thread = threading.Thread(target=self._run, name="edgemodbus-mqtt", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 1.0, reason: str = "shutdown") -> None:
        """Publish device statuses and the gateway offline with ``reason`` (if connected),
        flush for at most ``timeout`` seconds, disconnect and join the threads.
        Idempotent."""
        self._stop_commands()
        thread = self._thread
        if thread is not None:
            self._flush_timeout = max(0.0, timeout)
            self._stop_reason = reason
            self._stopping.set()
            self._wake()
            client = self._client
            # a connect() in progress can take up to connectTimeout; never longer
            connect = self.settings.connect_timeout / 1000 if client is not None else 0.0
            thread.join(timeout + connect + 1.0)
            if thread.is_alive():  # pragma: no cover - a wedged socket
                log.error("MQTT thread did not stop within %.1f s", timeout + connect + 1.0)
            self._thread = None
        if not self._closed:
            self._closed = True
            for sock in (self._wake_r, self._wake_w):
                sock.close()

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
        and per device ``published``, ``dropped``, ``snapshotsCoalesced``."""
        with self._lock:
            result: dict[str, Any] = dict(self._counts)
            result["queued"] = len(self._rows)
            result["queueSize"] = self.settings.queue_size
            result["pendingSnapshots"] = len(self._snapshots)
            result["devices"] = {
                d.code: {"published": d.published, "dropped": d.dropped,
                         "snapshotsPublished": d.snapshots,
                         "snapshotsCoalesced": d.snapshots_coalesced}
                for d in self._devices.values()
            }
            result["pendingCommands"] = self._pending_commands
        result["connected"] = self.connected
        return result

    # -- drivers -------------------------------------------------------------------------
    def attach(self, driver: DriverModbusRtu, device_code: str | None = None) -> None:
        """Publish what ``driver`` reports.  ``device_code`` defaults to the driver's
        (known once it was started).  Chains callbacks that were already set."""
        code = device_code or str(driver.snapshot()["deviceCode"])
        check_name("deviceCode", code)
        self.check_item_names(code, driver.snapshot()["items"].keys())
        dev = _Device(self, driver, code)
        with self._lock:
            if code in self._devices:
                raise ValueError(f"deviceCode {code!r} is already attached to this publisher")
            self._devices[code] = dev
        dev.prev_batch = driver.addresses_updated_callback
        dev.prev_snapshot = driver.snapshot_publisher
        prev_batch, prev_snapshot = dev.prev_batch, dev.prev_snapshot

        def on_batch(items: list[DeviceAddressItem]) -> None:
            self._offer_items(dev, items)
            if prev_batch is not None:
                prev_batch(items)

        def on_snapshot(topic: str, snapshot: dict[str, Any]) -> None:
            self._offer_snapshot(dev, snapshot)
            if prev_snapshot is not None:
                prev_snapshot(topic, snapshot)

        driver.addresses_updated_callback = on_batch
        driver.snapshot_publisher = on_snapshot
        self._act(lambda: self._subscribe(dev))

    def detach(self, driver: DriverModbusRtu) -> None:
        """Stop publishing ``driver``: its last status is published (retained), its
        command topics unsubscribed and its callbacks restored."""
        with self._lock:
            devs = [d for d in self._devices.values() if d.driver is driver]
            for dev in devs:
                del self._devices[dev.code]
        for dev in devs:
            driver.addresses_updated_callback = dev.prev_batch
            driver.snapshot_publisher = dev.prev_snapshot
            payload = self._status_payload(dev.code, _status_text(driver.device_driver_status))
            self._push_control(dev.status_topic, payload, 1, True)
            self._act(lambda dev=dev: self._unsubscribe(dev))  # type: ignore[misc]

    # -- producers (bus worker threads, paho never touched) ---------------------------------
    def _offer_items(self, dev: _Device, items: list[DeviceAddressItem]) -> None:
        rows = [(dev, it.name, it.value, it.status, it.update_ts, it.error_reason)
                for it in items]
        limit = self.settings.queue_size
        status = dev.driver.device_driver_status  # a cheap look: did the status change?
        with self._lock:
            if status is not dev.seen_status:
                dev.seen_status = status
                self._status_dirty = True
            queue = self._rows
            queue.extend(rows)
            over = len(queue) - limit
            if over > 0:  # drop the oldest: a newer update of an item supersedes it
                self._counts["dropped"] += over
                for _ in range(over):
                    queue.popleft()[0].dropped += 1
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self._wake()

    def _offer_snapshot(self, dev: _Device, snapshot: dict[str, Any]) -> None:
        with self._lock:
            if dev.code in self._snapshots:
                dev.snapshots_coalesced += 1
                self._counts["snapshotsCoalesced"] += 1
            self._snapshots[dev.code] = (dev, snapshot)
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self._wake()

    def _push_control(self, topic: str, payload: bytes, qos: int, retain: bool) -> None:
        with self._lock:
            if len(self._control) >= _CONTROL_LIMIT:
                self._counts["controlDropped"] += 1
                return
            self._control.append((topic, payload, qos, retain))
        self._wake()

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n

    def _act(self, action: Callable[[], None]) -> None:
        with self._lock:
            self._actions.append(action)
        self._wake()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # full (already woken) or closed
            self._wake_w.send(b"\0")

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
        client.will_set(self.topic(s.gateway_topic), self._gateway_payload(False, "lost"),
                        qos=1, retain=True)
        if s.username is not None:
            client.username_pw_set(s.username, s.password)
        if s.tls is not None and s.tls.enabled:
            client.tls_set(ca_certs=s.tls.ca_file, certfile=s.tls.cert_file,
                           keyfile=s.tls.key_file)
            client.tls_insecure_set(s.tls.insecure)
        self._raw_queue = _raw_packet_queue(client)
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
                        self._connect_failed(_error_text(exc, self._tls))
                    else:
                        self._attempt = time.monotonic()  # CONNECT sent, CONNACK due
            elif self._attempt is not None and now - self._attempt >= s.connect_timeout / 1000:
                self._connect_failed(f"no CONNACK within {s.connect_timeout} ms "
                                     "(connectTimeout); is this an MQTT broker?")
                _close_socket(client)
            if self._connected.is_set():
                delay = s.reconnect_min / 1000
                self._run_actions()
                if now >= next_status_check or self._status_dirty:
                    next_status_check = now + s.status_check_interval / 1000
                    self._status_dirty = False
                    self._check_statuses()
                self._pump(client)
            else:
                self._run_actions(connected=False)
            sock = client.socket()
            timeout = s.status_check_interval / 1000
            if sock is None:
                timeout = max(0.0, min(timeout, next_attempt - time.monotonic()))
            elif self._attempt is not None:
                timeout = max(0.0, min(timeout, self._attempt + s.connect_timeout / 1000
                                       - time.monotonic()))
            self._wait(client, sock, timeout)
        self._shutdown(client)

    def _connect_failed(self, reason: str) -> None:
        """One failed connection attempt: counted always, logged rate-limited."""
        self._attempt = None
        self._count("connectFailures")
        self._failures.failed(reason, time.monotonic())

    def _wait(self, client: Client, sock: Any, timeout: float) -> None:
        """Sleep in select() until the broker's socket or our wake-up socket is ready."""
        if sock is not None and hasattr(sock, "pending") and sock.pending():
            timeout = 0.0  # TLS has decrypted bytes buffered: read them now
        readers: list[Any] = [self._wake_r] if sock is None else [self._wake_r, sock]
        writers: list[Any] = [sock] if sock is not None and client.want_write() else []
        try:
            readable, writable, _ = select.select(readers, writers, [], timeout)
        except (OSError, ValueError):  # the socket was closed under us: reconnect
            return
        if self._wake_r in readable:
            with self._lock:
                self._wake_pending = False
            with contextlib.suppress(OSError):
                while self._wake_r.recv(4096):
                    pass
        try:
            if sock is not None and (sock in readable or timeout == 0.0):
                client.loop_read()
            if client.socket() is not None and (writable or client.want_write()):
                client.loop_write()
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
        self._count("connects")
        failed = self._failures.succeeded()
        log.info("MQTT connected to %s:%d as %s%s", self.settings.host, self.settings.port,
                 self.client_id, f" after {failed} failed attempts" if failed else "")
        self._connected.set()
        self._window.clear()  # qos>0 messages still pending are resent by paho
        s = self.settings
        client.publish(self.topic(s.gateway_topic), self._gateway_payload(True, None),
                       qos=1, retain=True)
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            dev.published_status = None  # republish every status (retained) below
            self._subscribe(dev)

    def _on_disconnect(self, _client: Client, _userdata: Any, _flags: Any, reason: Any,
                       _props: Any) -> None:
        if self._connected.is_set():
            self._count("disconnects")
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

    def _subscribe(self, dev: _Device) -> None:
        client = self._client
        if client is None or not self.settings.writes or not self._connected.is_set():
            return
        with self._lock:
            if self._devices.get(dev.code) is not dev:
                return
        for topic_filter in dev.filters():
            client.subscribe(topic_filter, qos=1)

    def _unsubscribe(self, dev: _Device) -> None:
        client = self._client
        if client is None or not self.settings.writes or not self._connected.is_set():
            return
        for topic_filter in dev.filters():
            client.unsubscribe(topic_filter)

    def _run_actions(self, connected: bool = True) -> None:
        with self._lock:
            actions = list(self._actions)
            self._actions.clear()
        if connected:
            for action in actions:
                try:
                    action()
                except Exception:
                    log.exception("MQTT action failed")
        # when not connected, subscriptions are made on (re)connect anyway

    def _check_statuses(self) -> None:
        with self._lock:
            devices = list(self._devices.values())
        for dev in devices:
            status = _status_text(dev.driver.device_driver_status)
            if status != dev.published_status:
                dev.published_status = status
                with self._lock:
                    self._control.append(
                        (dev.status_topic, self._status_payload(dev.code, status), 1, True))

    def _window_busy(self) -> bool:
        self._room()
        return bool(self._window)

    def _room(self) -> int:
        window = self._window
        while window and _done(window[0]):
            window.popleft()
        return self.settings.max_inflight * 4 - len(window)

    def _send(self, client: Client, topic: str, payload: bytes, qos: int, retain: bool) -> bool:
        """Hand one message to paho.  False: not taken (retry later)."""
        try:
            info = client.publish(topic, payload, qos=qos, retain=retain)
        except ValueError as exc:  # an invalid topic: never retried
            self._count("publishErrors")
            log.error("MQTT publish to %r refused: %s", topic, exc)
            return True
        rc = info.rc
        if rc == 0 or (rc == self._paho.MQTT_ERR_NO_CONN and qos > 0):
            self._window.append(info)  # qos>0 without connection: paho resends it later
            return True
        self._count("publishErrors")
        return False

    def _pump(self, client: Client) -> None:
        """Move queued messages into the client while the in-flight window has room:
        control messages first, then item updates, then snapshots.  A message paho does
        not take goes back to the front of its queue."""
        s = self.settings
        room = self._room()
        while room > 0 and self._connected.is_set():
            with self._lock:
                control = [self._control.popleft()
                           for _ in range(min(room, len(self._control)))]
                room -= len(control)
                rows = [self._rows.popleft() for _ in range(min(room, len(self._rows), 512))]
                room -= len(rows)
                snapshots: list[tuple[_Device, dict[str, Any]]] = []
                if room > 0 and self._snapshots:
                    snapshots = list(self._snapshots.values())[:room]
                    for dev, _ in snapshots:
                        del self._snapshots[dev.code]
                    room -= len(snapshots)
            if not control and not rows and not snapshots:
                return
            sent_control = 0
            for topic, payload, qos, retain in control:
                if not self._send(client, topic, payload, qos, retain):
                    break
                sent_control += 1
            sent_rows = 0
            if sent_control == len(control) and rows:
                if s.qos == 0 and self._raw_queue is not None:
                    sent_rows = self._send_raw(rows)
                else:
                    sent_rows = self._send_rows(client, rows)
            sent_snapshots: list[_Device] = []
            if sent_rows == len(rows) and sent_control == len(control):
                for dev, snap in snapshots:
                    body = dict(snap)
                    body["gatewayId"] = self.gateway_id
                    body["ts"] = _now()
                    if not self._send(client, dev.snapshot_topic, _dumps(body), s.snapshot_qos,
                                      s.snapshot_retain):
                        break
                    sent_snapshots.append(dev)
            with self._lock:
                self._counts["published"] += sent_rows
                self._counts["snapshotsPublished"] += len(sent_snapshots)
                for row in rows[:sent_rows]:
                    row[0].published += 1
                for dev in sent_snapshots:
                    dev.snapshots += 1
                # not taken: back to the front, oldest first, newer snapshots win
                self._control.extendleft(reversed(control[sent_control:]))
                self._rows.extendleft(reversed(rows[sent_rows:]))
                for dev, snap in snapshots[len(sent_snapshots):]:
                    self._snapshots.setdefault(dev.code, (dev, snap))
            if (sent_control < len(control) or sent_rows < len(rows)
                    or len(sent_snapshots) < len(snapshots)):
                return

    def _send_rows(self, client: Client, rows: list[_Row]) -> int:
        """Item updates through paho's publish(), one by one; how many it took."""
        qos, retain = self.settings.qos, self.settings.retain
        encode = _ItemEncoder()
        sent = 0
        for dev, name, value, status, ts, error in rows:
            item_topic = dev.item_topics.get(name)
            if item_topic is None:
                item_topic = dev.item_topics[name] = self.item_topic(dev.code, name)
            payload = encode(value, status, ts, error)
            if not self._send(client, item_topic, payload, qos, retain):
                break
            sent += 1
        return sent

    def _send_raw(self, rows: list[_Row]) -> int:
        """QoS 0 item updates as ready-made PUBLISH packets, queued as one write.

        paho's publish() costs about 9 us a message (a packet object, a send() each);
        building the bytes here and handing paho one buffer costs a fraction of that,
        which is what keeps MQTT within 1.5x of polling alone (bench/test_bench_mqtt.py).
        The buffer goes through paho's own output queue, so partial writes, keepalive
        and reconnects stay paho's business."""
        assert self._raw_queue is not None
        encode = _ItemEncoder()
        fixed = 0x31 if self.settings.retain else 0x30  # PUBLISH, QoS 0 (MQTT 3.1.1, 3.3)
        chunks: list[bytes] = []
        for dev, name, value, status, ts, error in rows:
            head = dev.item_heads.get(name)
            if head is None:
                topic = self.item_topic(dev.code, name).encode()
                head = dev.item_heads[name] = len(topic).to_bytes(2, "big") + topic
            payload = encode(value, status, ts, error)
            chunks.append(_fixed_header(fixed, len(head) + len(payload)) + head + payload)
        info = self._paho.MQTTMessageInfo(0)
        rc = self._raw_queue(self._paho.PUBLISH, b"".join(chunks), 0, 0, info)
        if rc not in (0, self._paho.MQTT_ERR_AGAIN):
            self._count("publishErrors")
            return 0
        self._window.append(info)
        return len(rows)

    def _shutdown(self, client: Client) -> None:
        """Last words on a clean stop: statuses, gateway offline, flush, disconnect."""
        try:
            if self._connected.is_set():
                self._check_statuses()
                s = self.settings
                with self._lock:
                    self._control.append((self.topic(s.gateway_topic),
                                          self._gateway_payload(False, self._stop_reason),
                                          1, True))
                started = time.monotonic()
                deadline = started + self._flush_timeout
                left = 0
                while time.monotonic() < deadline and self._connected.is_set():
                    self._pump(client)
                    with self._lock:
                        left = len(self._control) + len(self._rows) + len(self._snapshots)
                    if not left and not self._window_busy():
                        break
                    self._wait(client, client.socket(), 0.05)
                log.debug("MQTT flush on stop: %.0f ms, %d messages not sent, %d unconfirmed",
                          (time.monotonic() - started) * 1000, left, len(self._window))
                client.disconnect()
                if client.socket() is not None:
                    client.loop_write()
        except Exception:
            log.exception("MQTT shutdown failed")
        finally:
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
            if topic == dev.batch_topic:
                self._dispatch(dev, None, payload)
                return
            if topic.startswith(dev.command_prefix):
                self._dispatch(dev, topic[len(dev.command_prefix):], payload)
                return

    def _dispatch(self, dev: _Device, name: str | None, payload: bytes) -> None:
        loop = self._cmd_loop
        if loop is None or loop.is_closed():
            return
        with self._lock:
            self._counts["commands"] += 1
            busy = self._pending_commands >= _MAX_PENDING_COMMANDS
            if not busy:
                self._pending_commands += 1
        if busy:
            self._reply(dev, request_id_of(payload), False,
                        "too many writes pending; try again later", [])
            return
        try:
            loop.call_soon_threadsafe(self._spawn, dev, name, payload)
        except RuntimeError:  # the loop is closing: stop() is under way
            with self._lock:
                self._pending_commands -= 1

    def _spawn(self, dev: _Device, name: str | None, payload: bytes) -> None:
        asyncio.get_running_loop().create_task(self._command(dev, name, payload))

    async def _command(self, dev: _Device, name: str | None, payload: bytes) -> None:
        request_id: Any = None
        names: list[str] = []
        try:
            try:
                request_id, items = parse_command(name, payload)
            except ValueError as exc:
                self._reply(dev, request_id_of(payload), False, str(exc), [])
                return
            names = [n for n, _ in items]
            ok, error = await dev.driver.write_addresses_async(items)
            self._reply(dev, request_id, ok, error, names)
        except Exception as exc:  # never let a command kill the loop
            log.exception("%s: MQTT write failed", dev.code)
            self._reply(dev, request_id, False, f"internal error: {exc}", names)
        finally:
            with self._lock:
                self._pending_commands -= 1

    def _reply(self, dev: _Device, request_id: Any, ok: bool, error: str | None,
               names: list[str]) -> None:
        if not ok:
            self._count("commandErrors")
        body = {"id": request_id, "ok": ok, "error": error, "items": names, "ts": _now()}
        self._push_control(dev.reply_topic, _dumps(body), 1, False)

    def _run_commands(self, loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            tasks = asyncio.all_tasks(loop)
            for task in tasks:
                task.cancel()
            if tasks:
                loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            loop.close()

    def _stop_commands(self) -> None:
        loop, thread = self._cmd_loop, self._cmd_thread
        if loop is None or thread is None:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(loop.stop)
        thread.join(5.0)
        self._cmd_thread = None

    # -- payloads --------------------------------------------------------------------------
    def _status_payload(self, code: str, status: str) -> bytes:
        return _dumps({"deviceCode": code, "status": status, "gatewayId": self.gateway_id,
                       "ts": _now()})

    def _gateway_payload(self, online: bool, reason: str | None) -> bytes:
        body: dict[str, Any] = {"gatewayId": self.gateway_id,
                                "status": "online" if online else "offline"}
        if reason is not None:
            body["reason"] = reason
        if reason != "lost":  # the last will is fixed at connect time: no timestamp
            body["ts"] = _now()
        return _dumps(body)


class _FailureLog:
    """Failed connection attempts, logged without flooding: the first at once, then at
    most one line per ``interval`` seconds with the number of attempts it stands for;
    every attempt at debug level."""

    def __init__(self, where: str, interval: float, retry_max: float) -> None:
        self.where = where
        self.interval = interval
        self.retry_max = retry_max
        self.total = 0  # failures since the last success
        self.unreported = 0  # failures since the last warning line
        self.last_line = 0.0

    def failed(self, reason: str, now: float) -> None:
        self.total += 1
        self.unreported += 1
        log.debug("MQTT broker %s: connection attempt %d failed: %s", self.where, self.total,
                  reason)
        if self.total == 1:
            log.warning("MQTT broker %s: connection failed: %s; retrying with backoff up to "
                        "%g s (repeats logged at most every %g s)", self.where, reason,
                        self.retry_max, self.interval)
        elif now - self.last_line >= self.interval:
            log.warning("MQTT broker %s: still failing: %s (%d failed attempts since the "
                        "last report, %d in all)", self.where, reason, self.unreported,
                        self.total)
        else:
            return
        self.unreported = 0
        self.last_line = now

    def succeeded(self) -> int:
        """Forget the failures; how many there were."""
        total, self.total, self.unreported = self.total, 0, 0
        return total


def _error_text(exc: BaseException, tls: bool) -> str:
    """A connect error in words: ``connection refused``, ``timed out``, the TLS error;
    with ``tls``, a handshake cut short hints at a port that does not speak TLS."""
    if tls and isinstance(exc, (ConnectionResetError, BrokenPipeError, ssl.SSLError)) and (
            not isinstance(exc, ssl.CertificateError)):
        return f"{_error_text(exc, False)} (mqtt.tls is on: does this port speak TLS?)"
    if isinstance(exc, ssl.SSLCertVerificationError):
        return f"TLS certificate check failed: {exc.verify_message or exc}"
    if isinstance(exc, ssl.CertificateError):  # paho's own host name check
        return f"TLS certificate check failed: {exc}"
    if isinstance(exc, ssl.SSLError):
        return f"TLS handshake failed: {exc.reason or exc}"
    if isinstance(exc, socket.gaierror):
        return f"cannot resolve the host name: {exc.strerror or exc}"
    if isinstance(exc, TimeoutError) and not exc.strerror:
        return "timed out (connectTimeout)"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower() if exc.strerror[:1].isupper() else exc.strerror
    return str(exc) or type(exc).__name__


def _close_socket(client: Client) -> None:
    """Drop a connection that never got its CONNACK (paho has no public call for a
    connection that is not established; its reconnect() closes the old socket first)."""
    close = getattr(client, "_sock_close", None)
    if callable(close):
        close()
    else:  # pragma: no cover - a paho without it: DISCONNECT, closed once written
        client.disconnect()


def _raw_packet_queue(client: Client) -> Callable[..., Any] | None:
    """paho's internal ``_packet_queue(command, packet, mid, qos, info)`` if this paho
    has it with that shape (checked, since it is not public API), else None: then every
    message goes through publish()."""
    import inspect

    queue = getattr(client, "_packet_queue", None)
    if queue is None:
        return None
    try:
        params = list(inspect.signature(queue).parameters)
    except (TypeError, ValueError):
        return None
    if params[:5] != ["command", "packet", "mid", "qos", "info"]:
        return None
    return cast("Callable[..., Any]", queue)


def _fixed_header(first: int, remaining: int) -> bytes:
    """Packet type byte + remaining length (MQTT 3.1.1, 2.2.3: 7 bits a byte)."""
    out = bytearray((first,))
    while True:
        byte, remaining = remaining & 0x7F, remaining >> 7
        out.append(byte | 0x80 if remaining else byte)
        if not remaining:
            return bytes(out)


class _ItemEncoder:
    """JSON of one item update, {"value","status","updateTs","errorReason"}, without
    json.dumps for the common cases (ints, finite floats, bools, None; the timestamp
    shared by the items of one block is formatted once)."""

    __slots__ = ("iso", "ts")

    def __init__(self) -> None:
        self.ts: Any = None
        self.iso = "null"

    def __call__(self, value: Any, status: Any, ts: Any, error: Any) -> bytes:
        kind = type(value)
        if kind is int:
            text = str(value)
        elif kind is float:
            text = repr(value) if math.isfinite(value) else "null"
        elif value is None:
            text = "null"
        elif kind is bool:
            text = "true" if value else "false"
        else:
            text = json.dumps(jsonable(value), ensure_ascii=False, default=str)
        if ts is not self.ts:
            self.ts = ts
            self.iso = "null" if ts is None else f'"{ts.isoformat()}"'
        err = "null" if error is None else json.dumps(str(error), ensure_ascii=False)
        state = getattr(status, "value", status)
        return (f'{{"value":{text},"status":"{state}","updateTs":{self.iso},'
                f'"errorReason":{err}}}').encode()


def encode_item(value: Any, status: Any, ts: Any, error: Any) -> bytes:
    """The JSON payload of one item update (what the item topic carries)."""
    return _ItemEncoder()(value, status, ts, error)


def _done(info: MQTTMessageInfo) -> bool:
    """True once a message left the window: published, or failed for good."""
    try:
        return info.is_published()
    except (ValueError, RuntimeError):
        return True


def request_id_of(payload: bytes) -> Any:
    """The ``id`` of a JSON object payload, if there is one (for error replies)."""
    try:
        obj = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    return obj.get("id") if isinstance(obj, dict) else None


def parse_command(name: str | None, payload: bytes) -> tuple[Any, list[tuple[str, Any]]]:
    """(request id, [(item, value), ...]) from a command payload; ValueError says what
    is wrong.  ``name`` is the item of a single-item topic, None for the batch topic.

    Single item: a JSON value (``12.5``, ``true``, ``"text"``), or ``{"value": v, "id": x}``;
    text that is not JSON is taken as a string.  Batch: ``{"name": value, ...}``, or
    ``{"items": {...} | [{"name": n, "value": v}, ...] | [[n, v], ...], "id": x}``.
    """
    if len(payload) > _MAX_COMMAND_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes is too large "
                         f"(at most {_MAX_COMMAND_BYTES})")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("payload is not UTF-8 text") from None
    if name is not None:
        if not name:
            raise ValueError("no item name in the command topic")
        try:
            value = json.loads(text)
        except ValueError:
            return None, [(name, text)]
        if isinstance(value, dict):
            if "value" not in value:
                raise ValueError('an object payload needs a "value" key, e.g. {"value": 1}')
            return value.get("id"), [(name, value["value"])]
        return None, [(name, value)]
    try:
        body = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"batch payload is not JSON: {exc}") from None
    request_id: Any = None
    if isinstance(body, dict) and "items" in body:
        request_id = body.get("id")
        body = body["items"]
    items: list[tuple[str, Any]] = []
    if isinstance(body, dict):
        items = [(str(k), v) for k, v in body.items()]
    elif isinstance(body, list):
        for i, entry in enumerate(body):
            if isinstance(entry, dict) and isinstance(entry.get("name"), str) and (
                "value" in entry
            ):
                items.append((entry["name"], entry["value"]))
            elif isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str):
                items.append((entry[0], entry[1]))
            else:
                raise ValueError(f'items[{i}] {entry!r}: use {{"name": ..., "value": ...}} '
                                 "or [name, value]")
    else:
        raise ValueError(f"batch payload {body!r}: use an object of item names to values, "
                         'or {"items": ..., "id": ...}')
    if not items:
        raise ValueError("batch payload names no items")
    return request_id, items


__all__ = [
    "MqttPublisher",
    "MqttSettings",
    "TlsSettings",
    "check_name",
    "encode_item",
    "jsonable",
    "parse_command",
]
