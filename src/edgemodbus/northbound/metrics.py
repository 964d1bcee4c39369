"""Prometheus metrics of drivers, lines and the MQTT publisher on an HTTP endpoint.

Needs the extra ``edgemodbus[metrics]`` (prometheus_client); ``import edgemodbus`` never
imports this module, and prometheus_client is imported only when a
:class:`MetricsExporter` is made.

Nothing is counted twice and nothing runs on the line workers: at each scrape a custom
collector reads ``stats()`` of every attached driver (and of the publisher) and turns
the counters into metric families.  Per device (labels ``device``, ``line``):
requests, responses, timeouts, CRC and protocol errors, exceptions by code, retries,
cycles, failed cycles, overruns, skipped blocks, callback errors, values changed,
writes; cycle time and round-trip time as histograms when ``stats()`` carries buckets
(``cycleTimeHistogram`` / ``roundTripHistogram``), else as summaries (count and sum,
exact).  Per line (label ``line``, once even when several devices share it): the
line's own counters, reconnects and forwarded requests (gateway) among them.  Per
publisher: connection state, published and dropped updates per device, queue depth,
commands (and a Sparkplug publisher's own counters: metrics_extra.py).  Per DTU listen port
(label ``port``, ``host:port``, from a listener source such as the drivers'
``DtuRegistry``): its events by kind (``edgemodbus_dtu_listener_events_total``, label
``event``: accepted, registered, refusals, ...) and its unregistered connections,
configured DTUs and connected DTUs as gauges.  The gateway's Modbus TCP server: see
metrics_extra.py.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Protocol

from pydantic import AfterValidator, ValidationError

from ..config import ConfigError, Model, Range
from ..config.limits import MAX_HOST, check_host
from ..datatypes import DeviceDriverStatus, enum_value
from .metrics_extra import (
    ServerStats,
    exporter_metrics,
    server_metrics,
    sparkplug_metrics,
    spool_metrics,
)
from .metrics_http import MetricsHttpServer

if TYPE_CHECKING:
    from prometheus_client.metrics_core import Metric

log = logging.getLogger("edgemodbus.metrics")

NAMESPACE = "edgemodbus"

# stats() key -> (metric name without namespace and _total, help)
DEVICE_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("requests", "requests", "Requests sent to the device (retries included)"),
    ("responses", "responses", "Good responses from the device"),
    ("timeouts", "timeouts", "Requests the device did not answer in time"),
    ("crcErrors", "crc_errors", "Responses with a bad CRC"),
    ("protocolErrors", "protocol_errors", "Malformed or unexpected responses"),
    ("retries", "retries", "Requests repeated after a timeout or CRC error"),
    ("cycles", "cycles", "Read cycles completed"),
    ("failedCycles", "failed_cycles", "Read cycles cut short because the device was silent"),
    ("overruns", "overruns", "Read cycles that took longer than readCycle"),
    ("skippedBlocks", "skipped_blocks", "Blocks not read because the device was silent"),
    ("callbackErrors", "callback_errors", "Exceptions raised by update callbacks"),
    ("valuesChanged", "values_changed", "Item updates reported (value or status changed)"),
    ("writes", "writes", "Write requests sent"),
    ("writeErrors", "write_errors", "Write requests that failed"),
)
LINE_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("requests", "line_requests", "Requests sent on the line"),
    ("responses", "line_responses", "Good responses on the line"),
    ("timeouts", "line_timeouts", "Timeouts on the line"),
    ("crcErrors", "line_crc_errors", "CRC errors on the line"),
    ("protocolErrors", "line_protocol_errors", "Protocol errors on the line"),
    ("linkErrors", "line_link_errors", "Link failures (connection lost, I/O errors)"),
    ("connects", "line_connects", "Successful connects of the line"),
    ("reconnects", "line_reconnects", "Reconnects after the line was lost"),
    ("discardedBytes", "line_discarded_bytes", "Stray bytes discarded before requests"),
    ("forwarded", "line_forwarded_requests", "Requests forwarded onto the line (gateway)"),
    ("forwardTimeouts", "line_forward_timeouts", "Forwarded requests that timed out"),
    ("forwardExceptions", "line_forward_exceptions",
     "Forwarded requests answered with an exception reply (passed through)"),
    ("forwardErrors", "line_forward_errors",
     "Forwarded requests that failed otherwise (bad reply, link lost)"),
    ("forwardCoalesced", "line_forward_coalesced",
     "Forwarded reads answered from a fresh polled block (no line traffic)"),
    ("forwardExpired", "line_forward_expired",
     "Forwarded requests whose timeout ran out while queued (not sent)"),
    ("jobs", "line_jobs", "Queued jobs run (writes, forwards, actions, commands)"),
    ("jobsAheadOfPolls", "line_jobs_ahead_of_polls", "Queued jobs run while polling was due"),
    ("pollsDelayed", "line_polls_delayed",
     "Queued jobs run while polling was late by more than its scan rate"),
    ("jobsRefused", "line_jobs_refused", "Jobs refused: too many waiting (exception 06)"),
    ("targetBackoffs", "line_target_backoffs",
     "Requests failed at once: their slave timed out recently (backoff)"),
    ("failovers", "line_failovers", "Moves to the next backup endpoint (alternates)"),
    ("failbacks", "line_failbacks", "Moves back to the primary endpoint after a probe"),
    ("workerErrors", "line_worker_errors", "Unexpected errors the line worker recovered from"),
)
MQTT_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("connects", "mqtt_connects", "Connections to the MQTT broker"),
    ("disconnects", "mqtt_disconnects", "Connections to the MQTT broker lost or closed"),
    ("connectFailures", "mqtt_connect_failures", "Failed attempts to connect to the broker"),
    ("publishErrors", "mqtt_publish_errors", "Messages the MQTT client refused"),
    ("commands", "mqtt_commands", "Write commands received over MQTT"),
    ("commandErrors", "mqtt_command_errors", "Write commands answered with an error"),
    ("controlDropped", "mqtt_control_dropped", "Status or reply messages dropped"),
)
MQTT_DEVICE_COUNTERS: tuple[tuple[str, str, str], ...] = (
    ("published", "mqtt_published", "Item updates published to MQTT"),
    ("dropped", "mqtt_dropped", "Item updates dropped because the MQTT queue was full"),
    ("snapshotsPublished", "mqtt_snapshots_published", "Snapshots published to MQTT"),
    ("snapshotsCoalesced", "mqtt_snapshots_coalesced",
     "Snapshots replaced by a newer one before they could be published"),
)

# DtuRegistry.stats() per port: the counters (label ``event``) and the gauges
DTU_LISTENER_EVENTS: tuple[str, ...] = (
    "accepted", "registered", "unknown", "silent", "oversize", "evicted", "refusedPortCap",
    "refusedSourceCap", "refusedNotAllowed", "refusedDtuNotAllowed", "badKey",
    "duplicateRefused", "replaced", "contested", "refusedContested", "acceptErrors",
    "acceptPauses", "proxyNotAllowed", "proxyMissing", "proxyMalformed", "proxyLocal",
    "logSuppressed",
)
DTU_LISTENER_GAUGES: tuple[tuple[str, str, str], ...] = (
    ("unregistered", "dtu_listener_unregistered",
     "Connections of the listen port waiting to register"),
    ("dtus", "dtu_listener_dtus", "DTU ids configured on the listen port"),
    ("connected", "dtu_listener_connected", "DTUs connected to the listen port"),
)


class MetricsSettings(Model):
    """The ``metrics`` section of the gateway file."""

    _where: ClassVar[str] = "metrics"
    _max_lengths: ClassVar[dict[str, int]] = {"host": MAX_HOST}

    enabled: bool = True
    host: Annotated[str, AfterValidator(check_host)] = "127.0.0.1"
    port: Annotated[int, Range(0, 65535)] = 9108  # 0: any free port (logged)

    @classmethod
    def load(cls, data: Mapping[str, Any], where: str = "metrics") -> MetricsSettings:
        """Validate a mapping; ConfigError with paths under ``where``."""
        try:
            return cls.model_validate(dict(data))
        except ValidationError as exc:
            raise ConfigError.from_validation_error(exc, where) from None


class StatsSource(Protocol):
    """What the exporter reads from a driver (DriverModbusRtu satisfies it)."""

    def stats(self) -> dict[str, Any]: ...

    @property
    def device_driver_status(self) -> DeviceDriverStatus: ...

    @property
    def data_item_count(self) -> int: ...


class PublisherStats(Protocol):
    def stats(self) -> dict[str, Any]: ...


class ListenerStats(Protocol):
    """What the exporter reads of the DTU listen ports (DtuRegistry satisfies it): per
    ``host:port``, counters and gauges by name."""

    def stats(self) -> dict[str, dict[str, int]]: ...


class MetricsExporter:
    """Serves ``/metrics`` for attached drivers (and an MQTT publisher).

    ``attach(driver, device_code, line)`` may be called before or after the driver
    starts; ``start()`` binds the HTTP server (``port`` 0 picks a free one, see
    :attr:`port`); ``stop()`` closes it.  ``render()`` gives the text without HTTP.
    """

    def __init__(self, settings: MetricsSettings | Mapping[str, Any] | None = None, *,
                 gateway_id: str | None = None) -> None:
        try:
            from prometheus_client import CollectorRegistry
        except ImportError:  # pragma: no cover - depends on the install
            raise ImportError(
                "metrics need prometheus_client: pip install 'edgemodbus[metrics]'"
            ) from None

        if settings is None:
            settings = MetricsSettings()
        elif not isinstance(settings, MetricsSettings):
            settings = MetricsSettings.load(settings)
        self.settings: MetricsSettings = settings
        self.gateway_id = gateway_id
        self.instance = gateway_id or "edgemodbus"  # edgemodbus_dtu_held label (fleet.py)
        self._lock = threading.Lock()
        self._drivers: dict[str, tuple[StatsSource, str, Callable[[], bool] | None]] = {}
        self._publisher: PublisherStats | None = None
        self._listeners: ListenerStats | None = None
        self._serve: ServerStats | None = None  # the Modbus TCP server (gateway)
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(self)  # we are the Collector (collect/describe)
        self._server: MetricsHttpServer | None = None
        self._thread: threading.Thread | None = None

    # -- sources -----------------------------------------------------------------------
    def attach(self, driver: StatsSource, device_code: str | None = None,
               line: str | None = None, held: Callable[[], bool] | None = None) -> None:
        """Export ``driver``'s counters under ``device_code`` (default: the driver's)
        and ``line`` (a name for its serial port or TCP endpoint; default "").  In a
        dial-in fleet ``held`` says whether the device's DTU is connected here: a device
        not held exports no series at all (the holder exports them; an instance's
        ``edgemodbus_dtu_held`` counts what it holds), so a scrape costs only what the
        instance holds (docs/deploy.md "What the fleet costs")."""
        if device_code is None:
            snapshot = getattr(driver, "snapshot", None)
            device_code = str(snapshot()["deviceCode"]) if snapshot is not None else "device"
        with self._lock:
            if device_code in self._drivers:
                raise ValueError(f"deviceCode {device_code!r} is already exported")
            self._drivers[device_code] = (driver, line or "", held)

    def detach(self, driver: StatsSource) -> None:
        with self._lock:
            for code in [c for c, (d, _, _) in self._drivers.items() if d is driver]:
                del self._drivers[code]

    def set_publisher(self, publisher: PublisherStats | None) -> None:
        """Export the MQTT publisher's counters (None: stop exporting them)."""
        with self._lock:
            self._publisher = publisher

    def set_listener_stats(self, source: ListenerStats | None) -> None:
        """Export the DTU listen ports' counters (None: stop exporting them)."""
        with self._lock:
            self._listeners = source

    def set_server_stats(self, source: ServerStats | None) -> None:
        """Export the Modbus TCP server's counters (None: stop exporting them)."""
        with self._lock:
            self._serve = source

    # -- HTTP ----------------------------------------------------------------------------
    def start(self) -> int:
        """Serve ``http://host:port/metrics`` (one thread, bounded: metrics_http.py);
        returns the port."""
        if self._server is not None:
            return self.port
        from prometheus_client import make_wsgi_app

        server = MetricsHttpServer(self.settings.host, self.settings.port,
                                   make_wsgi_app(self.registry))
        thread = threading.Thread(target=server.serve_forever,
                                  name="edgemodbus-metrics", daemon=True)
        thread.start()
        self._server, self._thread = server, thread
        log.info("metrics on http://%s:%d/metrics", self.settings.host, self.port)
        return self.port

    def stop(self) -> None:
        server, thread = self._server, self._thread
        if server is None:
            return
        server.shutdown()
        if thread is not None:
            thread.join(5.0)
        server.server_close()
        self._server = self._thread = None

    def __enter__(self) -> MetricsExporter:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("metrics server not started")
        return int(self._server.server_port)

    def render(self) -> bytes:
        """The exposition text, as a scrape would get it."""
        from prometheus_client import generate_latest

        return bytes(generate_latest(self.registry))

    # -- the Collector protocol ----------------------------------------------------------
    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
            SummaryMetricFamily,
        )

        with self._lock:
            drivers = list(self._drivers.items())
            publisher = self._publisher
            listeners = self._listeners
            serve = self._serve
        dev_labels = ["device", "line"]
        counters = {key: CounterMetricFamily(f"{NAMESPACE}_{name}", doc, labels=dev_labels)
                    for key, name, doc in DEVICE_COUNTERS}
        exceptions = CounterMetricFamily(
            f"{NAMESPACE}_exceptions", "Modbus exception responses by exception code",
            labels=[*dev_labels, "code"])
        callback_time = CounterMetricFamily(
            f"{NAMESPACE}_callback_seconds", "Time spent in update callbacks",
            labels=dev_labels)
        status = GaugeMetricFamily(
            f"{NAMESPACE}_device_status", "1 for the device's current driver status",
            labels=[*dev_labels, "status"])
        items = GaugeMetricFamily(f"{NAMESPACE}_items", "Items polled", labels=dev_labels)
        last_cycle = GaugeMetricFamily(
            f"{NAMESPACE}_cycle_last_seconds", "Duration of the last read cycle",
            labels=dev_labels)
        max_cycle = GaugeMetricFamily(
            f"{NAMESPACE}_cycle_max_seconds", "Longest read cycle", labels=dev_labels)
        cycle_hist = HistogramMetricFamily(
            f"{NAMESPACE}_cycle_seconds", "Read cycle duration", labels=dev_labels)
        cycle_sum = SummaryMetricFamily(
            f"{NAMESPACE}_cycle_seconds", "Read cycle duration", labels=dev_labels)
        rtt_hist = HistogramMetricFamily(
            f"{NAMESPACE}_round_trip_seconds", "Request to response time", labels=dev_labels)
        rtt_sum = SummaryMetricFamily(
            f"{NAMESPACE}_round_trip_seconds", "Request to response time", labels=dev_labels)
        line_counters = {key: CounterMetricFamily(f"{NAMESPACE}_{name}", doc, labels=["line"])
                         for key, name, doc in LINE_COUNTERS}
        line_exceptions = CounterMetricFamily(
            f"{NAMESPACE}_line_exceptions", "Exception responses on the line by code",
            labels=["line", "code"])
        line_rtt = SummaryMetricFamily(
            f"{NAMESPACE}_line_round_trip_seconds", "Request to response time on the line",
            labels=["line"])
        seen_lines: set[str] = set()
        statuses = [s.value for s in DeviceDriverStatus]
        for code, (driver, line, held) in drivers:
            if held is not None and not held():
                continue  # a fleet's device held by another instance: its series are there
            try:
                stats = driver.stats()
                current = driver.device_driver_status
                count = driver.data_item_count
            except Exception:  # a source must never break the scrape
                log.exception("%s: stats() failed", code)
                continue
            labels = [code, line]
            current_text = str(enum_value(current))
            for state in statuses:
                status.add_metric([*labels, state], 1.0 if state == current_text else 0.0)
            items.add_metric(labels, float(count))
            if "cycles" not in stats:  # never started: status only
                continue
            for key, family in counters.items():
                family.add_metric(labels, float(stats.get(key, 0)))
            for exc_code, n in sorted(stats.get("exceptions", {}).items()):
                exceptions.add_metric([*labels, str(exc_code)], float(n))
            callback_time.add_metric(labels, float(stats.get("callbackTime", 0.0)))
            last_cycle.add_metric(labels, float(stats.get("lastCycleTime", 0.0)))
            max_cycle.add_metric(labels, float(stats.get("maxCycleTime", 0.0)))
            _timing(stats, "cycleTimeHistogram", "avgCycleTime", "cycles", labels,
                    cycle_hist, cycle_sum)
            _timing(stats, "roundTripHistogram", "avgRoundTrip", "responses", labels,
                    rtt_hist, rtt_sum)
            line_stats = stats.get("line")
            if isinstance(line_stats, dict) and line not in seen_lines:
                seen_lines.add(line)
                for key, family in line_counters.items():
                    family.add_metric([line], float(line_stats.get(key, 0)))
                for exc_code, n in sorted(line_stats.get("exceptions", {}).items()):
                    line_exceptions.add_metric([line, str(exc_code)], float(n))
                responses = int(line_stats.get("responses", 0))
                line_rtt.add_metric([line], responses,
                                    float(line_stats.get("avgRoundTrip", 0.0)) * responses)
        yield from counters.values()
        yield from (exceptions, callback_time, status, items, last_cycle, max_cycle)
        for hist, summary in ((cycle_hist, cycle_sum), (rtt_hist, rtt_sum)):
            yield hist if hist.samples else summary
        yield from line_counters.values()
        yield from (line_exceptions, line_rtt)
        if publisher is not None:
            yield from self._mqtt_metrics(publisher)
        if listeners is not None:
            yield from _listener_metrics(listeners, self.instance)
        if serve is not None:
            yield from server_metrics(serve)
        server = self._server
        if server is not None:
            yield from exporter_metrics(dict(server.counts))

    def _mqtt_metrics(self, publisher: PublisherStats) -> Iterator[Metric]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        try:
            stats = publisher.stats()
        except Exception:
            log.exception("MQTT publisher stats() failed")
            return
        yield GaugeMetricFamily(f"{NAMESPACE}_mqtt_connected",
                                "1 while connected to the MQTT broker",
                                value=1.0 if stats.get("connected") else 0.0)
        yield GaugeMetricFamily(f"{NAMESPACE}_mqtt_queue_depth",
                                "Item updates waiting to be published",
                                value=float(stats.get("queued", 0)))
        yield GaugeMetricFamily(f"{NAMESPACE}_mqtt_queue_size",
                                "Capacity of the item update queue",
                                value=float(stats.get("queueSize", 0)))
        for key, name, doc in MQTT_COUNTERS:
            yield CounterMetricFamily(f"{NAMESPACE}_{name}", doc,
                                      value=float(stats.get(key, 0)))
        per_device = stats.get("devices", {})
        for key, name, doc in MQTT_DEVICE_COUNTERS:
            family = CounterMetricFamily(f"{NAMESPACE}_{name}", doc, labels=["device"])
            for code, dev in sorted(per_device.items()):
                if dev.get("held") is not False:  # False: a fleet's device held elsewhere
                    family.add_metric([code], float(dev.get(key, 0)))
            yield family
        yield from sparkplug_metrics(stats)
        yield from spool_metrics(stats)


def _listener_metrics(source: ListenerStats, instance: str) -> list[Metric]:
    """The DTU listen ports' families, and the DTUs connected here on all of them
    (``edgemodbus_dtu_held``, label ``instance``: a fleet's spread); none (logged) when
    the source fails, so that a scrape never does.  A counter or gauge a port's stats
    lack is not emitted."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    events = CounterMetricFamily(
        f"{NAMESPACE}_dtu_listener_events",
        "Events of a DTU listen port by kind (connections accepted, registered, refused "
        "and why, replaced, contested ids, accept errors, log lines folded)",
        labels=["port", "event"])
    gauges = {key: GaugeMetricFamily(f"{NAMESPACE}_{name}", doc, labels=["port"])
              for key, name, doc in DTU_LISTENER_GAUGES}
    try:
        ports = sorted(source.stats().items())
        for port, stats in ports:
            for event in DTU_LISTENER_EVENTS:
                if event in stats:
                    events.add_metric([port, event], float(stats[event]))
            for key, family in gauges.items():
                if key in stats:
                    family.add_metric([port], float(stats[key]))
        held = GaugeMetricFamily(f"{NAMESPACE}_dtu_held", "DTUs connected to this "
                                 "instance (held here), all listen ports", labels=["instance"])
        held.add_metric([instance], float(sum(s.get("connected", 0) for _, s in ports)))
    except Exception:  # a source must never break the scrape
        log.exception("DTU listener stats() failed")
        return []
    return [events, *gauges.values(), held]


def _timing(stats: Mapping[str, Any], hist_key: str, avg_key: str, count_key: str,
            labels: list[str], hist: Any, summary: Any) -> None:
    """A histogram from ``stats[hist_key]`` = {"buckets": [[le, cumulative], ...,
    ["+Inf", n]], "sum": s, "count": n} when present, else an exact summary from the
    average and the count."""
    data = stats.get(hist_key)
    if isinstance(data, Mapping) and data.get("buckets"):
        buckets = [(_le(le), float(n)) for le, n in data["buckets"]]
        if buckets[-1][0] != "+Inf":
            buckets.append(("+Inf", float(data.get("count", buckets[-1][1]))))
        hist.add_metric(labels, buckets, float(data.get("sum", 0.0)))
        return
    count = int(stats.get(count_key, 0))
    summary.add_metric(labels, count, float(stats.get(avg_key, 0.0)) * count)


def _le(bound: Any) -> str:
    if isinstance(bound, str):
        return bound
    return "+Inf" if bound == float("inf") else repr(float(bound))


__all__ = ["ListenerStats", "MetricsExporter", "MetricsSettings"]
