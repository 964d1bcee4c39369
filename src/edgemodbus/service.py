"""The gateway service: poll every device file in a folder, publish to MQTT, serve metrics.

``python -m edgemodbus.service --config-dir DIR [--gateway FILE]`` (and
``edgemodbus run --config-dir DIR``) runs until SIGTERM or SIGINT:

* every ``*.json`` in DIR is a device file (the seed's format), except the gateway file;
  a device without ``organization.deviceCode`` is named after its file;
* the gateway file (``--gateway``, else ``DIR/gateway.json`` if present) holds
  ``gatewayId`` and the optional ``mqtt`` and ``metrics`` sections; without it the
  service only polls (and logs);
* SIGHUP re-reads DIR: a new file starts its device, a removed file stops it, a file whose
  address list alone changed is applied with ``update_addresses`` (the device keeps
  running), any other change restarts just that device; a file that no longer loads is
  reported and the running version kept;
* SIGTERM stops every device at once (each waits at most for the request in flight, so
  the whole stop takes about one response timeout), publishes the devices' last status
  and the gateway offline, and exits 0;
* the log has one line per device status change and per lifecycle event, never per value.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, ClassVar

from .config import (
    ConfigError,
    DeviceConfig,
    DriverModbusRtuParameter,
    Ms,
    Problem,
    _load,
    _Model,
    load_device_config,
)
from .driver import DriverModbusRtu
from .metrics import MetricsSettings
from .mqtt import MqttSettings, check_name

if TYPE_CHECKING:
    from .metrics import MetricsExporter
    from .mqtt import MqttPublisher

log = logging.getLogger("edgemodbus.service")

GATEWAY_FILE = "gateway.json"


class GatewayConfig(_Model):
    """The gateway file: who this gateway is and where its data goes."""

    _where: ClassVar[str] = "gateway"

    gateway_id: str | None = None  # default: the host name
    mqtt: MqttSettings | None = None
    metrics: MetricsSettings | None = None
    device_pattern: str = "*.json"
    status_check_interval: Ms = 500

    @property
    def effective_id(self) -> str:
        return self.gateway_id or socket.gethostname().split(".")[0] or "edgemodbus"


def load_gateway_config(path: str | os.PathLike[str] | dict[str, Any]) -> GatewayConfig:
    """Load and check a gateway file; ConfigError names the field, value and rule."""
    cfg = _load(GatewayConfig, path)
    if cfg.mqtt is not None and cfg.mqtt.enabled:
        try:
            check_name("gatewayId", cfg.effective_id)
        except ValueError as exc:
            raise ConfigError([Problem("gatewayId", cfg.effective_id, str(exc))]) from None
    return cfg


def line_label(params: DriverModbusRtuParameter) -> str:
    """A name for the line a device is on (metrics label): port or transport://host:port."""
    if params.transport == "rtu":
        return str(params.com_port)
    return f"{params.transport}://{params.tcp_host}:{params.tcp_port}"


@dataclass
class _Device:
    path: Path
    digest: str
    cfg: DeviceConfig  # as loaded from the file (reload compares these)
    code: str
    driver: DriverModbusRtu
    status: str


class Gateway:
    """The devices of one config folder with their MQTT publisher and metrics exporter."""

    def __init__(self, config_dir: Path, config: GatewayConfig,
                 gateway_file: Path | None = None) -> None:
        self.dir = config_dir
        self.config = config
        self.gateway_file = gateway_file.resolve() if gateway_file is not None else None
        self.gateway_id = config.effective_id
        self.devices: dict[Path, _Device] = {}
        self.publisher: MqttPublisher | None = None
        self.exporter: MetricsExporter | None = None
        self._gateway_digest = _digest(gateway_file) if gateway_file is not None else ""

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        mqtt, metrics = self.config.mqtt, self.config.metrics
        if mqtt is not None and mqtt.enabled:
            from .mqtt import MqttPublisher

            self.publisher = MqttPublisher(mqtt, gateway_id=self.gateway_id).start()
            log.info("MQTT: gateway %s publishing to %s:%d", self.gateway_id, mqtt.host,
                     mqtt.port)
        if metrics is not None and metrics.enabled:
            from .metrics import MetricsExporter

            self.exporter = MetricsExporter(metrics, gateway_id=self.gateway_id)
            try:
                self.exporter.start()
            except OSError as exc:
                self.exporter = None
                raise OSError(f"metrics: cannot listen on {metrics.host}:{metrics.port}: "
                              f"{exc.strerror or exc}") from None
            if self.publisher is not None:
                self.exporter.set_publisher(self.publisher)
        self.reload()

    def stop(self) -> None:
        """Stop every device in parallel, then the publisher and the exporter."""
        devices = list(self.devices.values())
        self.devices.clear()
        threads = [threading.Thread(target=self._stop_device, args=(dev,),
                                    name=f"stop {dev.code}") for dev in devices]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if self.publisher is not None:
            self.publisher.stop(timeout=0.5)
            self.publisher = None
        if self.exporter is not None:
            self.exporter.stop()
            self.exporter = None

    # -- devices ---------------------------------------------------------------------
    def device_files(self) -> list[Path]:
        files = []
        for path in sorted(self.dir.glob(self.config.device_pattern)):
            if not path.is_file() or path.name.startswith("."):
                continue
            if self.gateway_file is not None and path.resolve() == self.gateway_file:
                continue
            files.append(path)
        return files

    def reload(self) -> None:
        """Bring the running devices in line with the folder (see the module doc)."""
        if self.gateway_file is not None and self._gateway_digest != _digest(self.gateway_file):
            log.warning("%s changed: gateway settings apply after a restart of the service",
                        self.gateway_file)
        files = self.device_files()
        for path in [p for p in self.devices if p not in files]:
            dev = self.devices.pop(path)
            self._stop_device(dev)
            log.info("%s: stopped (%s removed)", dev.code, path.name)
        for path in files:
            try:
                digest = _digest(path)
            except OSError as exc:
                log.error("%s: cannot read: %s", path, exc)
                continue
            current = self.devices.get(path)
            if current is not None and current.digest == digest:
                continue
            try:
                cfg = load_device_config(path)
            except (ConfigError, ValueError, OSError) as exc:
                what = "keeping the running version" if current else "not started"
                log.error("%s: invalid, %s:\n%s", path, what, exc)
                continue
            if current is None:
                self._start_device(path, digest, cfg)
            else:
                self._change_device(current, digest, cfg)

    def _code(self, path: Path, cfg: DeviceConfig) -> str:
        return cfg.organization.device_code or path.stem

    def _start_device(self, path: Path, digest: str, cfg: DeviceConfig,
                      action: str = "started") -> None:
        code = self._code(path, cfg)
        taken = [d.path for d in self.devices.values() if d.code == code]
        if taken:
            log.error("%s: deviceCode %r is already used by %s; not started", path, code,
                      taken[0].name)
            return
        org = cfg.organization.model_copy(update={"device_code": code})
        comm = cfg.communication
        mqtt = self.config.mqtt
        if (mqtt is not None and mqtt.snapshot_interval
                and "snapshot_interval" not in comm.model_fields_set):
            comm = comm.model_copy(update={"snapshot_interval": mqtt.snapshot_interval})
        items = [it.model_copy(deep=True) for it in cfg.address_list]
        driver = DriverModbusRtu()
        try:
            if self.publisher is not None:
                self.publisher.check_item_names(code, [it.name for it in items])
                self.publisher.attach(driver, code)
            if self.exporter is not None:
                self.exporter.attach(driver, code, line_label(cfg.effective_parameters()))
            running = driver.start_device(org, comm, items)
        except (ValueError, OSError) as exc:
            self._detach(driver)
            log.error("%s: not started: %s", path, exc)
            return
        status = driver.device_driver_status.value
        self.devices[path] = _Device(path, digest, cfg, code, driver, status)
        if running:
            log.info("%s: %s from %s (%d items)", code, action, path.name, len(items))
        else:
            log.info("%s: %s (%s)", code, status, path.name)

    def _change_device(self, dev: _Device, digest: str, cfg: DeviceConfig) -> None:
        same_line = (cfg.organization.to_dict() == dev.cfg.organization.to_dict()
                     and cfg.communication.to_dict() == dev.cfg.communication.to_dict()
                     and cfg.driver_type == dev.cfg.driver_type)
        if same_line and dev.driver.device_driver_status.value != "Disabled":
            items = [it.model_copy(deep=True) for it in cfg.address_list]
            try:
                if self.publisher is not None:
                    self.publisher.check_item_names(dev.code, [it.name for it in items])
                dev.driver.update_addresses(items)
            except (ValueError, RuntimeError) as exc:
                log.error("%s: address list not applied, keeping the running one: %s",
                          dev.path, exc)
                return
            dev.digest, dev.cfg = digest, cfg
            log.info("%s: address list updated from %s (%d items)", dev.code, dev.path.name,
                     len(items))
            return
        del self.devices[dev.path]
        self._stop_device(dev)
        self._start_device(dev.path, digest, cfg, action="restarted")

    def _stop_device(self, dev: _Device) -> None:
        try:
            dev.driver.stop_device()
        except Exception:
            log.exception("%s: stop failed", dev.code)
        self._detach(dev.driver)

    def _detach(self, driver: DriverModbusRtu) -> None:
        if self.publisher is not None:
            self.publisher.detach(driver)
        if self.exporter is not None:
            self.exporter.detach(driver)

    def check_statuses(self) -> None:
        """Log each device status change, once."""
        for dev in self.devices.values():
            status = dev.driver.device_driver_status.value
            if status != dev.status:
                level = logging.WARNING if status in ("Offline", "Reconnecting") else logging.INFO
                log.log(level, "%s: %s -> %s", dev.code, dev.status, status)
                dev.status = status


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_service(config_dir: Path, gateway_config: Path | None = None) -> int:
    """Run the gateway until SIGTERM/SIGINT (SIGHUP reloads).  Returns the exit code:
    0 after a clean stop, 2 for a configuration error (printed on stderr)."""
    config_dir = Path(config_dir)
    if not config_dir.is_dir():
        print(f"edgemodbus service: --config-dir {str(config_dir)!r}: not a directory",
              file=sys.stderr)
        return 2
    if gateway_config is None and (config_dir / GATEWAY_FILE).is_file():
        gateway_config = config_dir / GATEWAY_FILE
    try:
        config = (load_gateway_config(gateway_config) if gateway_config is not None
                  else GatewayConfig())
    except (ConfigError, OSError) as exc:
        print(f"edgemodbus service: {gateway_config}: {exc}", file=sys.stderr)
        return 2
    wake = threading.Event()
    flags = {"stop": False, "reload": False}

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        flags["stop"] = True
        wake.set()

    def on_reload(signum: int, _frame: FrameType | None) -> None:
        flags["reload"] = True
        wake.set()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop),
                             (signal.SIGHUP, on_reload)):
            previous[sig] = signal.signal(sig, handler)
    gateway = Gateway(config_dir, config, gateway_config)
    try:
        try:
            gateway.start()
        except (OSError, ValueError) as exc:
            print(f"edgemodbus service: {exc}", file=sys.stderr)
            return 2
        log.info("gateway %s running: %d device files in %s", gateway.gateway_id,
                 len(gateway.devices), config_dir)
        interval = config.status_check_interval / 1000
        while not flags["stop"]:
            wake.wait(interval)
            wake.clear()
            if flags["reload"] and not flags["stop"]:
                flags["reload"] = False
                log.info("SIGHUP: reloading %s", config_dir)
                gateway.reload()
            gateway.check_statuses()
        log.info("stopping")
    finally:
        started = time.monotonic()
        gateway.stop()
        for sig, old in previous.items():
            signal.signal(sig, old)
    log.info("stopped in %.0f ms", (time.monotonic() - started) * 1000)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edgemodbus.service",
        description="Poll every device file in a folder; MQTT and metrics from a gateway "
                    "file; SIGHUP reloads, SIGTERM stops.")
    parser.add_argument("--config-dir", type=Path, required=True,
                        help="folder of device files (*.json)")
    parser.add_argument("--gateway", type=Path, default=None,
                        help=f"gateway file (default: DIR/{GATEWAY_FILE} if present)")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="-v: debug logs of edgemodbus")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    return run_service(args.config_dir, args.gateway)


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """INFO by default; no timestamps under systemd (the journal has them)."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt)


if __name__ == "__main__":
    sys.exit(main())
