"""The ``mqtt`` section of the gateway file: broker, TLS files, topic templates, queues.

The templates are checked when loaded (placeholders, no wildcards); the TLS files are
checked by :meth:`TlsSettings.problems` before anything connects."""

from __future__ import annotations

import os
import string
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import ValidationError, field_validator, model_validator

from ...config import MAX_MS, Choice, ConfigError, Model, Ms, Problem, Range
from ...config.limits import MAX_HOST, MAX_NAME, check_host
from ...config.secret import Secret
from ...config.tls import tls_file_problems
from ..sparkplug.settings import SparkplugSettings
from .spool import MIN_FILE_BYTES, SYNCHRONOUS, path_problem

PLACEHOLDERS = ("prefix", "deviceCode", "itemName", "gatewayId")
# What goes on the wire: per-item, one message per item update on its item topic; batch,
# one message per device and cycle on its batch topic (payload.batch_payload); sparkplug,
# Sparkplug B (v3.0) with the ``sparkplug`` section (northbound/sparkplug/)
Mode = Literal["per-item", "batch", "sparkplug"]
FORBIDDEN = ("+", "#", "\0")  # never in a topic level: the wildcards and NUL


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
        certificate), each named by its field; [] when TLS can be set up from them
        (config/tls.py, shared with the mqtt-dtu keys)."""
        if not self.enabled:
            return []
        return tls_file_problems(self.ca_file, self.cert_file, self.key_file,
                                 where=f"{where}.")


_SNAKE = {"caFile": "ca_file", "certFile": "cert_file", "keyFile": "key_file"}


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
    if any(ch in literal for ch in FORBIDDEN):
        raise ValueError("must not contain MQTT wildcards (+, #) or NUL")
    if last is not None and (
        not template.endswith("/{" + last + "}") or fields.count(last) != 1
    ):
        raise ValueError(f"must end with /{{{last}}} (a topic level of its own, used once)")
    return template


class StoreAndForwardSettings(Model):
    """``mqtt.storeAndForward``: the SQLite file that keeps messages while the broker is
    away or has not acknowledged them (spool/__init__.py says how), and its bounds."""

    _where: ClassVar[str] = "mqtt.storeAndForward"

    path: str  # relative: from the gateway file's folder
    # the file (database + WAL); rows count topics + payloads (+32 a row) against it too
    max_bytes: Annotated[int, Range(MIN_FILE_BYTES)] = 100_000_000
    max_age_s: Annotated[int, Range(1)] = 7 * 86_400
    replay_rate_per_s: Annotated[float, Range(0.01)] = 500.0  # messages replayed per second
    replay_bytes_per_s: Annotated[int | None, Range(1)] = None  # no byte limit by default
    synchronous: Annotated[str, Choice(SYNCHRONOUS)] = "normal"  # "full": fsync each commit
    # messages kept in memory while the spool refuses writes (disk full, I/O error)
    memory_queue_size: Annotated[int, Range(0, 10_000_000)] = 10_000

    @field_validator("path")
    @classmethod
    def _path(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be empty (the spool file, e.g. /var/lib/edgemodbus/"
                             "spool.db)")
        return value

    def resolved(self, base: str | os.PathLike[str]) -> StoreAndForwardSettings:
        """A copy whose relative path is taken from folder ``base``."""
        if os.path.isabs(self.path):
            return self
        return self.model_copy(update={"path": str(Path(base, self.path))})

    def problems(self, where: str = "mqtt.storeAndForward") -> list[Problem]:
        """[] when the spool file can be kept at ``path`` (its folder exists and is
        writable), else the problem named by its field."""
        message = path_problem(self.path)
        return [] if message is None else [Problem(f"{where}.path", self.path, message)]


class MqttSettings(Model):
    """The ``mqtt`` section of the gateway file.  Times in ms unless named otherwise."""

    _where: ClassVar[str] = "mqtt"
    _max_lengths: ClassVar[dict[str, int]] = {
        "host": MAX_HOST, "clientId": MAX_NAME, "username": MAX_NAME}

    enabled: bool = True
    mode: Mode = "per-item"
    sparkplug: SparkplugSettings | None = None
    host: str = "127.0.0.1"
    port: Annotated[int, Range(1, 65535)] = 1883
    client_id: str | None = None  # default: edgemodbus-{gatewayId}
    username: str | None = None
    password: Secret | None = None  # never shown: masked in a dump, absent from a repr
    keepalive: Annotated[int, Range(5, 3600)] = 30  # seconds (MQTT's unit)
    connect_timeout: Annotated[int, Range(100, 60_000)] = 5000
    tls: TlsSettings | None = None
    topic_prefix: str = "edgemodbus"
    item_topic: str = "{prefix}/{deviceCode}/{itemName}"
    batch_topic: str = "{prefix}/{deviceCode}/$batch"  # mode "batch"
    snapshot_topic: str = "/real/{deviceCode}"
    status_topic: str = "{prefix}/{deviceCode}/$status"
    gateway_topic: str = "{prefix}/$gateway/{gatewayId}"
    command_topic: str = "{prefix}/{deviceCode}/set/{itemName}"
    batch_command_topic: str = "{prefix}/{deviceCode}/set"
    reply_topic: str = "{prefix}/{deviceCode}/$reply"
    action_topic: str = "{prefix}/{deviceCode}/$action"  # {"action": n, "parameters": {...}}
    read_topic: str = "{prefix}/{deviceCode}/$read"  # {"items": [...], "id": x}; {}: all
    qos: Annotated[int, Choice((0, 1, 2))] = 0  # item updates (either mode): a stream
    retain: bool = False
    snapshot_qos: Annotated[int, Choice((0, 1, 2))] = 1
    snapshot_retain: bool = True
    snapshot_interval: Annotated[int, Range(0, MAX_MS)] = 0
    writes: bool = True
    queue_size: Annotated[int, Range(1, 10_000_000)] = 10_000
    max_inflight: Annotated[int, Range(1, 65_535)] = 100
    # ms: a busy MQTT thread wakes at most about once per linger, sending all that came
    # meanwhile (a wake-up costs more CPU than a message); 0: each message at once
    linger: Annotated[int, Range(0, 1000)] = 10
    reconnect_min: Ms = 500
    reconnect_max: Ms = 30_000
    failure_log_interval: Ms = 60_000  # failed connects: first logged, then one line per this
    status_check_interval: Ms = 500
    store_and_forward: StoreAndForwardSettings | None = None  # off unless set

    @field_validator("host")
    @classmethod
    def _host(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be empty (the broker's host name or address)")
        return check_host(value)

    @field_validator("topic_prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        if any(ch in value for ch in FORBIDDEN):
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
        "snapshot_topic", "status_topic", "batch_command_topic", "reply_topic", "action_topic",
        "batch_topic", "read_topic",
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
    def _sparkplug(self) -> MqttSettings:
        if self.mode == "sparkplug" and self.sparkplug is None:
            raise ValueError('mode "sparkplug" needs the section mqtt.sparkplug with at '
                             'least its groupId, e.g. "sparkplug": {"groupId": "plant1"}')
        return self

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
    bad = [ch for ch in FORBIDDEN if ch in name]
    if bad or "/" in name:
        raise ValueError(
            f"{kind} {name!r} cannot be used in MQTT topics: it contains "
            f"{' '.join(repr(c) for c in bad + (['/'] if '/' in name else []))}; "
            "use letters, digits, '-', '_' or '.'"
        )
    return name
