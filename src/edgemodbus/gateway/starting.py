"""What the gateway starts northbound of its devices: the MQTT or Sparkplug publisher
and the Prometheus exporter (service.py starts and swaps them)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..config import NO_VALUE, ConfigError, Problem
from ..driver import DriverModbusRtu
from .config import GatewayConfig
from .serving import GatewayServer

if TYPE_CHECKING:
    from ..northbound.metrics import MetricsExporter
    from ..northbound.mqtt import MqttPublisher, MqttSettings
    from ..northbound.sparkplug.publisher import SparkplugPublisher
    from .pair import Pair

    Publisher = MqttPublisher | SparkplugPublisher


def make_publisher(mqtt: MqttSettings, gateway_id: str, instance: str | None,
                   pair: Pair | None = None) -> Publisher:
    """The publisher ``mqtt.mode`` asks for (not started): per-item MQTT or Sparkplug B;
    a Sparkplug edge node that the ``pair`` shares (``sharedByPair``) follows its lease.
    A missing optional package (paho-mqtt, protobuf) is a ConfigError naming ``mqtt``
    and the extra to install."""
    try:
        if mqtt.mode == "sparkplug":
            from ..northbound.sparkplug.publisher import SparkplugPublisher

            shared = mqtt.sparkplug is not None and mqtt.sparkplug.shared_by_pair
            pair = pair if shared else None
            node = SparkplugPublisher(mqtt, gateway_id=gateway_id, instance=instance,
                                      bd_seq_store=None if pair is None else pair.bd_seq_store())
            if pair is not None:
                pair.follow(node)
            return node
        from ..northbound.mqtt import MqttPublisher

        return MqttPublisher(mqtt, gateway_id=gateway_id, instance=instance)
    except ImportError as exc:
        raise missing_extra("mqtt", "sparkplug" if mqtt.mode == "sparkplug" else "mqtt",
                            exc) from None


def missing_extra(section: str, extra: str, exc: ImportError) -> ConfigError:
    """The gateway file's ``section`` needs a package that is not installed."""
    return ConfigError([Problem(section, NO_VALUE, f"needs the optional packages of "
                                f"edgemodbus[{extra}], not installed ({exc}): pip install "
                                f"'edgemodbus[{extra}]', or remove the {section} section")])


def start_exporter(config: GatewayConfig, serving: GatewayServer) -> MetricsExporter | None:
    """The exporter ``config`` asks for, listening, with the drivers' DTU listen ports
    as its listener source and ``serving`` (the Modbus TCP server); OSError names the
    address."""
    metrics = config.metrics
    if metrics is None or not metrics.enabled:
        return None
    try:
        from ..northbound.metrics import MetricsExporter

        exporter = MetricsExporter(metrics, gateway_id=config.effective_id)
    except ImportError as exc:
        raise missing_extra("metrics", "metrics", exc) from None
    exporter.set_listener_stats(DriverModbusRtu.dtu_registry)  # the DTU listen ports
    exporter.set_server_stats(serving)
    try:
        exporter.start()
    except OSError as exc:
        raise OSError(f"metrics: cannot listen on {metrics.host}:{metrics.port}: "
                      f"{exc.strerror or exc}") from None
    return exporter


__all__ = ["make_publisher", "missing_extra", "start_exporter"]
