"""Sparkplug B (v3.0) northbound: the gateway as an edge node, one Sparkplug device per
Modbus device (``mqtt.mode: "sparkplug"``).

Needs the extra ``edgemodbus[sparkplug]`` (paho-mqtt, protobuf).  This package's
``__init__`` imports only the settings; the publisher is
``edgemodbus.northbound.sparkplug.publisher.SparkplugPublisher`` (paho and protobuf are
imported with it).

Modules: settings.py (``mqtt.sparkplug``), publisher.py (lifecycle, births, data,
deaths, commands), session.py (the paho client, the will, connecting; a new session when
the primary host goes offline), client.py (the paho client's options), devices.py (per
device: metrics as born, aliases), payloads.py (our types and values as Sparkplug
metrics; sparkplug_b.proto is the specification's schema, sparkplug_b_pb2.py generated
from it by ``make proto``), commands.py (the metrics of NCMD/DCMD: caps, lossless
values), inbox.py (commands as untrusted input: refusals counted, logs rate-limited,
rebirths paced), state.py (the primary host's STATE), bdseq.py (bdSeq kept across
restarts in a file that is ours), writes.py (DCMD writes).

Messages (group ``G``, edge node ``N``: ``edgeNodeId``, default the gateway id; in a
dial-in fleet one node per instance, settings.py ``node_id_for``, and a listen-mode
device has DBIRTH/DDATA/DCMD only on the node holding its DTU, DDEATH when it leaves;
device ``D``: the device code)::

    spBv1.0/G/NBIRTH/N      on connect: bdSeq, Node Control/Rebirth; seq 0     QoS 0
    spBv1.0/G/NDEATH/N      the MQTT will (bdSeq of the session), and on stop  QoS 1
    spBv1.0/G/DBIRTH/N/D    after the device's first complete cycle: every    QoS 0
                            item, name + alias + type + timestamp
    spBv1.0/G/DDATA/N/D     what changed in a cycle, by alias (no type)       QoS 0
    spBv1.0/G/DDEATH/N/D    the device stopped running (Offline, link down) or was detached
    spBv1.0/G/NCMD/N        in: Node Control/Rebirth = true -> NBIRTH + every DBIRTH
                            (at most one per rebirthInterval; more are folded)
    spBv1.0/G/DCMD/N/D      in: writes (metrics by name or alias) -> write_addresses
    spBv1.0/STATE/<host>    in: the primary host's {"online", "timestamp"}, when configured

Every message but NDEATH has ``seq`` (0-255, wrapping, NBIRTH 0); timestamps are ms since
the epoch (a metric's is its item's updateTs).  Threads: paho's network thread (connect,
reconnect with backoff, callbacks that only queue events), ``edgemodbus-sparkplug`` (the
one that orders and publishes every message, so seq follows the publish order; it also
ends the session and starts paho's thread again when the primary host goes offline),
``edgemodbus-sparkplug-cmd`` (DCMD writes).  Line workers only copy their reports into a
bounded queue; past ``queueSize`` the oldest are dropped (counted) and the device gets a
DBIRTH that carries every current value.  While the broker is unreachable nothing is
kept: the births after reconnecting carry the current values.
"""

from .settings import SparkplugSettings, check_id

__all__ = ["SparkplugSettings", "check_id"]
