"""The gateway service: every device file of a folder polled, published to MQTT, with
metrics; ``python -m edgemodbus.gateway`` and ``edgemodbus run --config-dir``."""

from .service import Gateway, GatewayConfig, load_gateway_config, main, run_service

__all__ = ["Gateway", "GatewayConfig", "load_gateway_config", "main", "run_service"]
