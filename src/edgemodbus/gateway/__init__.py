"""The gateway service: poll every device file in a folder, publish to MQTT, serve metrics.

``python -m edgemodbus.gateway --config-dir DIR [--gateway FILE]`` (and
``edgemodbus run --config-dir DIR``) runs until SIGTERM or SIGINT:

* every ``*.json`` in DIR is a device file (the seed's format), except the gateway file;
  a device without ``organization.deviceCode`` is named after its file;
* the gateway file (``--gateway``, else ``DIR/gateway.json``) holds ``gatewayId`` and
  the optional ``mqtt`` and ``metrics`` sections; without it the service only polls (and
  logs); TLS files (``mqtt.tls.caFile`` ...) are checked before anything connects, a
  relative path is taken from the gateway file's folder;
* SIGHUP re-reads the gateway file first: one that no longer loads (or names a missing
  TLS file) is reported and the running settings kept; a changed one is applied live:
  a changed ``mqtt`` section or ``gatewayId`` (or changed TLS file contents) restarts the
  MQTT publisher (the old one says offline with reason ``reconfigure``), a changed
  ``metrics`` section moves the exporter, a changed ``mqtt.snapshotInterval`` restarts
  the devices that take theirs from it, ``devicePattern`` and ``statusCheckInterval``
  apply at once;
* then SIGHUP re-reads DIR: a new file starts its device, a removed file stops it, a file
  whose address list alone changed is applied with ``update_addresses`` (the device keeps
  running), any other change restarts just that device; a file that no longer loads is
  reported and the running version kept;
* ``--seconds N`` stops the service after N seconds as SIGTERM would (0: run until a
  signal);
* SIGTERM stops every device at once (each waits at most for the request in flight, so
  the whole stop takes about one response timeout), publishes the devices' last status
  and the gateway offline, and exits 0;
* the log has one line per device status change and per lifecycle event, never per value.
"""

from .config import GatewayConfig, load_gateway_config
from .run import main, run_service
from .service import Gateway

__all__ = ["Gateway", "GatewayConfig", "load_gateway_config", "main", "run_service"]
