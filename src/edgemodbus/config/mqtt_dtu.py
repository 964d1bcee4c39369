"""The keys of a DTU reached through an MQTT broker (transport ``mqtt-dtu``,
docs/links.md): the broker (host, port, credentials, TLS, as the northbound's ``mqtt``
section names them, with an ``mqtt`` prefix) and the DTU's topics (templates with
``{dtuId}``): it publishes what it reads from RS-485 to the uplink topic, writes to
RS-485 what it receives on the downlink topic, and its will (or its own status
messages) on the status topic says when it is offline.

:class:`MqttDtuFields` holds the fields (communication.py's model inherits them);
:func:`mqtt_dtu_problems` checks them with transport ``mqtt-dtu`` (elsewhere they are
ignored, each value's own form checked whatever the transport).
"""

from __future__ import annotations

from typing import Annotated, Protocol

from pydantic import Field, SecretStr, field_validator

from .base import Choice, Model, Range
from .limits import check_host
from .problems import Problem
from .secret import Secret
from .tls import tls_file_problems

TOPIC_FORBIDDEN = ("+", "#", "\0")  # MQTT wildcards and NUL: never in a topic we use
DEFAULT_UPLINK = "dtu/{dtuId}/up"
DEFAULT_DOWNLINK = "dtu/{dtuId}/down"
DEFAULT_STATUS = "dtu/{dtuId}/status"
_TLS_KEYS = ("mqttCaFile", "mqttCertFile", "mqttKeyFile")


class MqttDtuFields(Model):
    """The MQTT DTU keys (see the module docstring)."""

    mqtt_host: str = Field(
        default="127.0.0.1",
        description="mqtt-dtu: the broker's host name or address",
    )
    mqtt_port: Annotated[int, Range(1, 65535)] = Field(
        default=1883,
        description="mqtt-dtu: the broker's port (8883 is usual with TLS)",
    )
    mqtt_username: str = Field(
        default="",
        description="mqtt-dtu: user name at the broker (empty: none)",
    )
    mqtt_password: Secret = Field(
        default=SecretStr(""),
        description="mqtt-dtu: password at the broker; never shown nor logged",
    )
    mqtt_client_id: str = Field(
        default="",
        description="mqtt-dtu: client id of the gateway's connection to the broker (one "
        "connection per broker settings, shared by its DTUs); empty: "
        "edgemodbus-dtu-<host name>-<process id>",
    )
    mqtt_keepalive: Annotated[int, Range(5, 3600)] = Field(
        default=30,
        description="mqtt-dtu: MQTT keepalive (s)",
    )
    mqtt_qos: Annotated[int, Choice((0, 1, 2))] = Field(
        default=0,
        description="mqtt-dtu: QoS of the requests published and the topics subscribed",
    )
    mqtt_tls: bool = Field(
        default=False,
        description="mqtt-dtu: TLS to the broker (the CA file, else the system's CAs)",
    )
    mqtt_ca_file: str = Field(
        default="",
        description="mqtt-dtu with mqttTls: CA certificates (PEM); empty: the system's",
    )
    mqtt_cert_file: str = Field(
        default="",
        description="mqtt-dtu with mqttTls: client certificate (PEM), if the broker asks",
    )
    mqtt_key_file: str = Field(
        default="",
        description="mqtt-dtu with mqttTls: the client certificate's key (PEM)",
    )
    mqtt_tls_insecure: bool = Field(
        default=False,
        description="mqtt-dtu with mqttTls: skip the host name check (lab brokers only)",
    )
    uplink_topic: str = Field(
        default=DEFAULT_UPLINK,
        description="mqtt-dtu: where the DTU publishes what it reads from RS-485 (the "
        "replies); a template with {dtuId}",
    )
    downlink_topic: str = Field(
        default=DEFAULT_DOWNLINK,
        description="mqtt-dtu: where the gateway publishes the requests the DTU writes to "
        "RS-485; a template with {dtuId}",
    )
    status_topic: str = Field(
        default=DEFAULT_STATUS,
        description="mqtt-dtu: the DTU's online state (its will: offlinePayload); empty: "
        "the DTU counts as online while the broker is connected",
    )
    online_payload: str = Field(
        default="online",
        description="mqtt-dtu: the status message of a DTU that is online",
    )
    offline_payload: str = Field(
        default="offline",
        description="mqtt-dtu: the status message of a DTU that is offline (its will)",
    )

    @field_validator("mqtt_host")
    @classmethod
    def _mqtt_host(cls, value: str) -> str:
        return check_host(value)

    @field_validator("uplink_topic", "downlink_topic", "status_topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic(value)


def check_topic(template: str) -> str:
    """A topic template: no wildcards or NUL, the one placeholder ``{dtuId}``;
    ValueError says what is allowed."""
    if any(ch in template for ch in TOPIC_FORBIDDEN):
        raise ValueError("must not contain MQTT wildcards (+, #) or NUL")
    rest = template.replace("{dtuId}", "")
    if "{" in rest or "}" in rest:
        raise ValueError("the only placeholder is {dtuId} (no other braces)")
    return template


class MqttDtuParams(Protocol):
    """What the MQTT DTU checks read of DriverModbusRtuParameter."""

    @property
    def transport(self) -> str: ...
    @property
    def dtu_id(self) -> str: ...
    @property
    def mqtt_host(self) -> str: ...
    @property
    def mqtt_username(self) -> str: ...
    @property
    def mqtt_password(self) -> SecretStr: ...
    @property
    def mqtt_tls(self) -> bool: ...
    @property
    def mqtt_ca_file(self) -> str: ...
    @property
    def mqtt_cert_file(self) -> str: ...
    @property
    def mqtt_key_file(self) -> str: ...
    @property
    def uplink_topic(self) -> str: ...
    @property
    def downlink_topic(self) -> str: ...
    @property
    def status_topic(self) -> str: ...
    @property
    def online_payload(self) -> str: ...
    @property
    def offline_payload(self) -> str: ...


def mqtt_dtu_problems(p: MqttDtuParams) -> list[Problem]:
    """transport mqtt-dtu: the DTU's id, the topics, the credentials and TLS files."""
    if p.transport != "mqtt-dtu":
        return []
    problems: list[Problem] = []
    if not p.dtu_id:
        problems.append(Problem("dtuId", p.dtu_id, "required with transport mqtt-dtu: "
                                "the {dtuId} of its topics"))
    elif any(ch in p.dtu_id for ch in TOPIC_FORBIDDEN):
        problems.append(Problem("dtuId", p.dtu_id, "must not contain MQTT wildcards "
                                "(+, #) or NUL: it is part of the DTU's topics"))
    if not p.mqtt_host.strip():
        problems.append(Problem("mqttHost", p.mqtt_host, "a broker host is required"))
    for key, template in (("uplinkTopic", p.uplink_topic), ("downlinkTopic", p.downlink_topic)):
        if "{dtuId}" not in template:
            problems.append(Problem(key, template, "needs {dtuId}: each DTU has topics "
                                    f"of its own, e.g. {DEFAULT_UPLINK}"))
    if p.uplink_topic == p.downlink_topic:
        problems.append(Problem("downlinkTopic", p.downlink_topic, "must differ from "
                                "uplinkTopic: the gateway would read its own requests"))
    if p.status_topic:
        if "{dtuId}" not in p.status_topic:
            problems.append(Problem("statusTopic", p.status_topic, "needs {dtuId} (or "
                                    f"empty: no status), e.g. {DEFAULT_STATUS}"))
        if p.status_topic in (p.uplink_topic, p.downlink_topic):
            problems.append(Problem("statusTopic", p.status_topic, "must differ from the "
                                    "uplink and downlink topics"))
        if p.online_payload == p.offline_payload:
            problems.append(Problem("offlinePayload", p.offline_payload,
                                    "must differ from onlinePayload"))
    if p.mqtt_password.get_secret_value() and not p.mqtt_username:
        problems.append(Problem("mqttPassword", p.mqtt_password, "needs mqttUsername"))
    if p.mqtt_tls:  # the files' checks of the northbound's mqtt.tls (config/tls.py)
        problems += tls_file_problems(p.mqtt_ca_file or None, p.mqtt_cert_file or None,
                                      p.mqtt_key_file or None, keys=_TLS_KEYS)
    return problems


def topic_for(template: str, dtu_id: str) -> str:
    """A template with the DTU's id in place."""
    return template.replace("{dtuId}", dtu_id)


__all__ = ["MqttDtuFields", "MqttDtuParams", "check_topic", "mqtt_dtu_problems", "topic_for"]
