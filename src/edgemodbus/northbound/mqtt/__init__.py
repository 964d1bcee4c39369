"""MQTT northbound (see publisher.py for threads, queues and the topic layout)."""

from .publisher import (
    MqttPublisher,
    MqttSettings,
    TlsSettings,
    check_name,
    encode_item,
    jsonable,
    parse_command,
)

__all__ = [
    "MqttPublisher",
    "MqttSettings",
    "TlsSettings",
    "check_name",
    "encode_item",
    "jsonable",
    "parse_command",
]
