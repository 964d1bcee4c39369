"""The paho client of the edge node, made from the ``mqtt`` section: credentials, TLS,
connect timeout and reconnect backoff (paho's network thread reconnects by itself)."""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING

from ..mqtt.connection import authenticate
from ..mqtt.settings import MqttSettings

if TYPE_CHECKING:
    from paho.mqtt.client import Client


def make_client(paho: ModuleType, s: MqttSettings, client_id: str) -> Client:
    """A clean-session MQTT 3.1.1 client (Sparkplug 3.0 asks for a clean session, so no
    stale command is delivered after an outage); its will and callbacks are the caller's.
    paho's backoff counts whole seconds: reconnectMin/Max are rounded, at least 1 s."""
    client: Client = paho.Client(callback_api_version=paho.CallbackAPIVersion.VERSION2,
                                 client_id=client_id, clean_session=True,
                                 protocol=paho.MQTTv311)
    client.connect_timeout = s.connect_timeout / 1000
    client.reconnect_delay_set(max(1, round(s.reconnect_min / 1000)),
                               max(1, round(s.reconnect_max / 1000)))
    client.max_queued_messages_set(max(s.queue_size, 1000))
    authenticate(client, s)
    return client
