"""MQTT northbound: item changes, snapshots, device and gateway status, writes from MQTT.

Needs the extra ``edgemodbus[mqtt]`` (paho-mqtt); ``import edgemodbus`` never imports
this package, and paho is imported only when a :class:`MqttPublisher` is made.

Modules: settings.py (the ``mqtt`` section), publisher.py (lifecycle, attached drivers,
the MQTT thread), outbox.py and sender.py (the queues, and handing them to paho through
its public API: ``publish()``, ``loop_read/loop_write/loop_misc``), payload.py (every JSON
payload, through edgemodbus.codec's one value conversion), commands.py (writes from
MQTT), connection.py (failed connects in the log).

Threads and queues (why polling is never blocked):

* the publisher's listener on each driver (``driver.subscribe``: its batches and
  snapshots) runs on the line worker thread; it only copies the reported fields into a
  bounded queue (oldest updates are dropped and counted when it is full: ``queueSize``
  during an outage, ``queueSize`` plus one full report of every device while the broker
  is connected, so that the start-up burst of first reads is kept) or replaces the
  device's pending snapshot (latest wins);
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
    {prefix}/{deviceCode}/$batch          mode "batch": a device's changes of one cycle
                                          {"deviceCode","ts","values","status","errors"}
    /real/{deviceCode}                    periodic snapshot (the seed's topic), retained
    {prefix}/{deviceCode}/$status         device status, retained
    {prefix}/$gateway/{gatewayId}         gateway online/offline, retained; last will: offline
    {prefix}/{deviceCode}/set/{itemName}  write one item: a JSON value, or {"value", "id"}
    {prefix}/{deviceCode}/set             write several: {"name": value, ...} or {"items", "id"}
    {prefix}/{deviceCode}/$reply          result of a write: {"id","ok","error","items","ts"}
"""

from ...codec import jsonable
from .commands import parse_command, parse_read
from .payload import batch_payload, encode_item
from .publisher import MqttPublisher
from .settings import MqttSettings, TlsSettings, check_name

__all__ = [
    "MqttPublisher",
    "MqttSettings",
    "TlsSettings",
    "batch_payload",
    "check_name",
    "encode_item",
    "jsonable",
    "parse_command",
    "parse_read",
]
