"""Prometheus families beside metrics.py's: the Sparkplug publisher's own counters and the
gateway's Modbus TCP server (serve/).  The exporter calls these at each scrape; like
metrics.py they read ``stats()`` and never raise into a scrape.

Sparkplug (from the publisher's ``stats()``, only when it is a Sparkplug one): births
(``edgemodbus_sparkplug_nbirths_total``, ``_dbirths_total``), ``_ddata_total``,
``_ddeaths_total``, ``_rebirths_total``, DCMD ``_writes_total`` and
``_writes_refused_total``, refused commands (``_command_errors_total``), rebirth requests
folded by ``rebirthInterval`` (``_rebirths_folded_total``) and command log lines folded
into summaries (``_command_logs_suppressed_total``); gauges
``edgemodbus_sparkplug_bd_seq`` (the session's bdSeq: it moves once per MQTT session) and
``edgemodbus_sparkplug_born`` (1 between NBIRTH and NDEATH).  ``seq`` is not exported: it
moves with every message and wraps at 256, so a scrape of it says nothing.

MQTT store-and-forward (from the publisher's ``stats()["spool"]``, only when
``mqtt.storeAndForward`` is set): ``edgemodbus_mqtt_spool_<counter>_total`` for
appended, acked, replayed, released, dropped by ``maxBytes`` (``_dropped_size_total``)
and by ``maxAgeS`` (``_dropped_age_total``), and ``_errors_total`` (messages the disk
refused); gauges ``edgemodbus_mqtt_spool_messages`` (stored), ``_pending`` (waiting for
the replay), ``_inflight`` and ``_bytes`` (what counts against ``maxBytes``).

Modbus TCP server (label ``listen``, ``host:port``): ``edgemodbus_serve_<counter>_total``
for its connection and request counters, ``edgemodbus_serve_exceptions_total`` by
exception ``code``, ``edgemodbus_serve_stale_replies_total`` by ``unit`` and ``reason``
(a served unit's reads answered 0B), and the gauge ``edgemodbus_serve_connections``
(the masters' connections open now).

The exporter's own HTTP server (metrics_http.py): ``edgemodbus_metrics_http_<counter>_total``
for connections accepted, requests answered, connections evicted, refused, timed out
(header deadline), too large, bad requests and accept failures.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from prometheus_client.metrics_core import Metric

log = logging.getLogger("edgemodbus.metrics")

NAMESPACE = "edgemodbus"

# stats() key -> (metric name without namespace and _total, help)
SPARKPLUG_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("nbirths", "sparkplug_nbirths", "NBIRTH messages published (one per session and rebirth)"),
    ("dbirths", "sparkplug_dbirths", "DBIRTH messages published"),
    ("ddata", "sparkplug_ddata", "DDATA messages published"),
    ("ddeaths", "sparkplug_ddeaths", "DDEATH messages published"),
    ("rebirths", "sparkplug_rebirths", "Rebirths requested (NCMD Node Control/Rebirth)"),
    ("writes", "sparkplug_writes", "DCMD writes the slave confirmed"),
    ("writesRefused", "sparkplug_writes_refused",
     "DCMD writes refused (over a cap, unknown metric, a value of another type or out of "
     "range, slave exception or timeout)"),
    ("commandErrors", "sparkplug_command_errors",
     "NCMD/DCMD messages refused whole (not Sparkplug, over a cap, unsupported NCMD "
     "metrics, DCMD for an unknown device)"),
    ("commandsNotHeld", "sparkplug_commands_not_held",
     "DCMD messages ignored: in a fleet, the device's DTU is not connected to this instance"),
    ("rebirthsFolded", "sparkplug_rebirths_folded",
     "Rebirth requests within rebirthInterval of the last rebirth, folded into the next"),
    ("commandLogsSuppressed", "sparkplug_command_logs_suppressed",
     "Log lines about commands folded into rate-limited summaries"),
)
SPOOL_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("appended", "mqtt_spool_appended", "Messages written to the store-and-forward spool"),
    ("acked", "mqtt_spool_acked", "Spooled messages the broker acknowledged (deleted)"),
    ("replayed", "mqtt_spool_replayed", "Spooled messages replayed to the broker"),
    ("released", "mqtt_spool_released",
     "Spooled messages in flight put back to pending (refused, or the connection lost)"),
    ("droppedSize", "mqtt_spool_dropped_size", "Oldest spooled messages dropped (maxBytes)"),
    ("droppedAge", "mqtt_spool_dropped_age", "Oldest spooled messages dropped (maxAgeS)"),
    ("errors", "mqtt_spool_errors",
     "Messages the spool refused (disk full or failing): kept in memory instead"),
    ("memoryDropped", "mqtt_spool_memory_dropped",
     "Messages dropped from the memory queue while the spool refused writes"),
)
SPOOL_GAUGES: tuple[tuple[str, str, str], ...] = (
    ("stored", "mqtt_spool_messages", "Messages in the store-and-forward spool"),
    ("pending", "mqtt_spool_pending", "Spooled messages waiting for the replay"),
    ("inflight", "mqtt_spool_inflight", "Spooled messages handed to the broker, not acked"),
    ("bytes", "mqtt_spool_bytes", "What the spooled messages count against maxBytes"),
    ("fileBytes", "mqtt_spool_file_bytes", "The spool's database and WAL on disk"),
    ("memory", "mqtt_spool_memory", "Messages waiting in memory while the spool refuses writes"),
)
SERVE_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("accepted", "serve_accepted", "Connections of Modbus TCP masters accepted"),
    ("refused", "serve_refused", "Connections refused (maxConnections reached)"),
    ("refusedSource", "serve_refused_source",
     "Connections reset at once: their source is outside the server's allowFrom"),
    ("refusedUnit", "serve_refused_unit",
     "Requests answered 0A: their source is outside the unit's allowFrom"),
    ("closedIdle", "serve_closed_idle", "Connections closed after the idle timeout"),
    ("closedBad", "serve_closed_bad",
     "Connections closed for a malformed MBAP header (protocol id, length) or a failed send"),
    ("closedByPeer", "serve_closed_by_peer", "Connections the master closed"),
    ("requests", "serve_requests", "Requests received"),
    ("cachedReplies", "serve_cached_replies", "Reads answered from the register image"),
    ("writes", "serve_writes", "Write requests to a served device"),
    ("writeErrors", "serve_write_errors", "Writes a device refused or failed"),
    ("forwarded", "serve_forwarded", "Requests forwarded to a device's line"),
    ("forwardExpired", "serve_forward_expired",
     "Forwarded requests answered 0B when their timeout ran out (counted from arrival)"),
    ("busy", "serve_busy", "Requests answered 06 (server busy): the line had too many waiting"),
    ("busyMaster", "serve_busy_master",
     "Requests answered 06 (server busy): their master had maxPendingPerMaster waiting"),
    ("acceptErrors", "serve_accept_errors",
     "accept() failures (EMFILE, ENFILE, ENOBUFS, ENOMEM): accepting paused, 50 ms doubling "
     "to 2 s"),
)


class ServerStats(Protocol):
    """What the exporter reads of the Modbus TCP server (ModbusTcpServer and the
    gateway's GatewayServer satisfy it): its counters, or None while there is none."""

    def stats(self) -> Mapping[str, Any] | None: ...


def sparkplug_metrics(stats: Mapping[str, Any]) -> list[Metric]:
    """The Sparkplug families from a publisher's ``stats()``; none for a publisher that
    is not a Sparkplug edge node (no ``nbirths`` counter)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    if "nbirths" not in stats:
        return []
    families: list[Metric] = [
        CounterMetricFamily(f"{NAMESPACE}_{name}", doc, value=float(stats.get(key, 0)))
        for key, name, doc in SPARKPLUG_COUNTERS]
    bd_seq = GaugeMetricFamily(f"{NAMESPACE}_sparkplug_bd_seq",
                               "bdSeq of the current Sparkplug session (0-255)")
    if isinstance(stats.get("bdSeq"), int):  # None before the first connection
        bd_seq.add_metric([], float(stats["bdSeq"]))
    families.append(bd_seq)
    families.append(GaugeMetricFamily(
        f"{NAMESPACE}_sparkplug_born", "1 while the edge node is born (NBIRTH published, "
        "no NDEATH since)", value=1.0 if stats.get("born") else 0.0))
    return families


def spool_metrics(stats: Mapping[str, Any]) -> list[Metric]:
    """The store-and-forward families from a publisher's ``stats()``; none without a
    spool."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    spool = stats.get("spool")
    if not isinstance(spool, Mapping):
        return []
    families: list[Metric] = [
        CounterMetricFamily(f"{NAMESPACE}_{name}", doc, value=float(spool.get(key, 0)))
        for key, name, doc in SPOOL_COUNTERS]
    families += [GaugeMetricFamily(f"{NAMESPACE}_{name}", doc, value=float(spool.get(key, 0)))
                 for key, name, doc in SPOOL_GAUGES]
    return families


def server_metrics(source: ServerStats) -> list[Metric]:
    """The Modbus TCP server's families; none while there is no server, or (logged) when
    its ``stats()`` fails."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    try:
        stats = source.stats()
    except Exception:  # a source must never break the scrape
        log.exception("Modbus TCP server stats() failed")
        return []
    if stats is None:
        return []
    listen = [str(stats.get("listen", ""))]
    families: list[Metric] = []
    for key, name, doc in SERVE_COUNTERS:
        family = CounterMetricFamily(f"{NAMESPACE}_{name}", doc, labels=["listen"])
        family.add_metric(listen, float(stats.get(key, 0)))
        families.append(family)
    exceptions = CounterMetricFamily(
        f"{NAMESPACE}_serve_exceptions", "Exception replies sent, by exception code",
        labels=["listen", "code"])
    for code, n in sorted(dict(stats.get("exceptions", {})).items()):
        exceptions.add_metric([*listen, str(code)], float(n))
    families.append(exceptions)
    stale = CounterMetricFamily(
        f"{NAMESPACE}_serve_stale_replies", "Reads of a served unit answered 0B, by unit and "
        "reason (pollingDelayed, deviceDown, old, invalid: docs/gateway.md)",
        labels=["listen", "unit", "reason"])
    for unit, counts in sorted(dict(stats.get("staleReplies", {})).items()):
        for reason, n in dict(counts).items():
            stale.add_metric([*listen, str(unit), str(reason)], float(n))
    families.append(stale)
    gauge = GaugeMetricFamily(f"{NAMESPACE}_serve_connections",
                              "Connections of Modbus TCP masters open now", labels=["listen"])
    gauge.add_metric(listen, float(stats.get("connections", 0)))
    families.append(gauge)
    return families


# the exporter's own HTTP server (metrics_http.py): its counts key -> (name, help)
EXPORTER_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("accepted", "metrics_http_accepted", "Scrape connections accepted"),
    ("answered", "metrics_http_answered", "Requests answered"),
    ("evicted", "metrics_http_evicted",
     "Connections closed to make room (the oldest still sending its request)"),
    ("refused", "metrics_http_refused", "Connections refused: the connection cap reached"),
    ("timedOut", "metrics_http_timed_out",
     "Connections closed for request headers not complete within the deadline"),
    ("tooLarge", "metrics_http_too_large", "Requests refused for headers over the size cap"),
    ("badRequests", "metrics_http_bad_requests", "Malformed or unsupported requests"),
    ("acceptErrors", "metrics_http_accept_errors",
     "accept() failures (EMFILE, ENFILE, ENOBUFS, ENOMEM): accepting paused"),
)


def exporter_metrics(counts: Mapping[str, int]) -> list[Metric]:
    """The exporter's own HTTP counters (so a slowloris or the fd limit shows)."""
    from prometheus_client.core import CounterMetricFamily

    return [CounterMetricFamily(f"{NAMESPACE}_{name}", doc, value=float(counts.get(key, 0)))
            for key, name, doc in EXPORTER_COUNTERS]


__all__ = ["ServerStats", "exporter_metrics", "server_metrics", "sparkplug_metrics",
           "spool_metrics"]
