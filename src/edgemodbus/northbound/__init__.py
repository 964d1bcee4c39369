"""Northbound: where polled data goes, MQTT (``northbound.mqtt``) and Prometheus metrics
(``northbound.metrics``).  Neither is imported by ``import edgemodbus``, and paho and
prometheus_client are imported only when a publisher or an exporter is made."""
