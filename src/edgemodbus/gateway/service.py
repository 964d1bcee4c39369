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

from __future__ import annotations

import argparse
import hashlib
import logging
import math
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

from ..config import (
    ConfigError,
    DeviceConfig,
    DriverModbusRtuParameter,
    Model,
    Ms,
    Problem,
    load_device_config,
    load_model,
)
from ..driver import DriverModbusRtu
from ..northbound.metrics import MetricsSettings
from ..northbound.mqtt import MqttSettings, check_name

if TYPE_CHECKING:
    from ..northbound.metrics import MetricsExporter
    from ..northbound.mqtt import MqttPublisher

log = logging.getLogger("edgemodbus.service")

GATEWAY_FILE = "gateway.json"


class GatewayConfig(Model):
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
    """Load and check a gateway file; ConfigError names the field, value and rule.

    The TLS files of an enabled ``mqtt.tls`` must exist and hold PEM data (checked here,
    so a bad path is reported before anything connects); relative paths are taken from
    the gateway file's folder."""
    cfg = load_model(GatewayConfig, path)
    mqtt = cfg.mqtt
    if mqtt is None or not mqtt.enabled:
        return cfg
    problems: list[Problem] = []
    try:
        check_name("gatewayId", cfg.effective_id)
    except ValueError as exc:
        problems.append(Problem("gatewayId", cfg.effective_id, str(exc)))
    if mqtt.tls is not None and mqtt.tls.enabled:
        tls = mqtt.tls
        if isinstance(path, os.PathLike) or (
                isinstance(path, str)
                and not path.lstrip("\ufeff \t\r\n").startswith(("{", "["))):
            tls = tls.resolved(Path(path).absolute().parent)
            cfg = cfg.model_copy(update={"mqtt": mqtt.model_copy(update={"tls": tls})})
        problems += tls.problems()
    if problems:
        raise ConfigError(problems)
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
        # watched even when absent: one that appears later is applied on SIGHUP
        self.gateway_file = (gateway_file or config_dir / GATEWAY_FILE).resolve()
        self.gateway_id = config.effective_id
        self.devices: dict[Path, _Device] = {}
        self.publisher: MqttPublisher | None = None
        self.exporter: MetricsExporter | None = None
        self._gateway_digest = _gateway_digest(self.gateway_file, config)

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        mqtt = self.config.mqtt
        if mqtt is not None and mqtt.enabled:
            from ..northbound.mqtt import MqttPublisher

            self.publisher = MqttPublisher(mqtt, gateway_id=self.gateway_id).start()
            log.info("MQTT: gateway %s publishing to %s:%d", self.gateway_id, mqtt.host,
                     mqtt.port)
        self.exporter = _start_exporter(self.config)
        if self.exporter is not None and self.publisher is not None:
            self.exporter.set_publisher(self.publisher)
        self.reload_devices()

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

    def reload(self) -> None:
        """SIGHUP: the gateway file, then the device files (see the module doc)."""
        self.reload_gateway()
        self.reload_devices()

    # -- the gateway file ------------------------------------------------------------
    def reload_gateway(self) -> None:
        """Apply a changed gateway file; a broken one is reported, the running kept."""
        path = self.gateway_file
        keep = "keeping the running gateway settings"
        try:
            digest = _gateway_digest(path, self.config)
        except OSError as exc:
            log.error("%s: cannot read: %s; %s", path, exc.strerror or exc, keep)
            return
        if digest == self._gateway_digest:
            return
        if digest is None:
            log.warning("%s: removed; %s (without the file a restart runs with none)",
                        path, keep)
            return
        try:
            new = load_gateway_config(path)
        except (ConfigError, OSError) as exc:
            log.error("%s: invalid, %s:\n%s", path, keep, exc)
            return
        try:
            applied = self.apply_gateway(new)
        except (ValueError, OSError, ImportError) as exc:
            log.error("%s: not applied, %s: %s", path, keep, exc)
            return
        self._gateway_digest = _gateway_digest(path, new)
        log.info("%s: gateway settings applied: %s", path,
                 "; ".join(applied) if applied else "no effective change")

    def apply_gateway(self, new: GatewayConfig) -> list[str]:
        """Switch to ``new`` gateway settings live; what was done, in words.  Raises
        (ValueError, OSError) with nothing changed when they cannot be applied."""
        old = self.config
        done: list[str] = []
        publisher: MqttPublisher | None = None
        mqtt_changed = _mqtt_key(old) != _mqtt_key(new)
        if mqtt_changed and new.mqtt is not None and new.mqtt.enabled:
            from ..northbound.mqtt import MqttPublisher

            publisher = MqttPublisher(new.mqtt, gateway_id=new.effective_id)
            try:
                for dev in self.devices.values():
                    publisher.check_item_names(dev.code,
                                               [it.name for it in dev.cfg.address_list])
            except ValueError:
                publisher.stop()
                raise
        if _metrics_key(old) != _metrics_key(new):
            try:
                self._swap_exporter(new)
            except OSError:
                if publisher is not None:
                    publisher.stop()
                raise
            done.append(f"metrics on http://{new.metrics.host}:{self.exporter.port}/metrics"
                        if self.exporter is not None and new.metrics is not None
                        else "metrics off")
        self.config, self.gateway_id = new, new.effective_id
        if mqtt_changed:
            self._swap_publisher(publisher)
            done.append(f"MQTT publisher restarted ({new.mqtt.host}:{new.mqtt.port}, "
                        f"gateway {self.gateway_id})"
                        if publisher is not None and new.mqtt is not None else "MQTT off")
        if _inherited_snapshot(old) != _inherited_snapshot(new):
            restarted = [dev for dev in list(self.devices.values())
                         if "snapshot_interval" not in dev.cfg.communication.model_fields_set]
            for dev in restarted:
                del self.devices[dev.path]
                self._stop_device(dev)
                self._start_device(dev.path, dev.digest, dev.cfg, action="restarted")
            done.append(f"snapshotInterval {_inherited_snapshot(new)} ms: "
                        f"{len(restarted)} devices restarted")
        for key in ("devicePattern", "statusCheckInterval"):
            if old.to_dict()[key] != new.to_dict()[key]:
                done.append(f"{key} {new.to_dict()[key]}")
        return done

    def _swap_exporter(self, new: GatewayConfig) -> None:
        """Stop the exporter, start the one ``new`` asks for; if that cannot listen,
        start the old one again and raise OSError."""
        old = self.exporter
        if old is not None:
            old.stop()
        try:
            exporter = _start_exporter(new)
        except OSError:
            if old is not None:
                try:
                    old.start()
                except OSError as exc:
                    self.exporter = None
                    log.error("metrics: cannot listen on the old address either (%s); "
                              "metrics are off", exc.strerror or exc)
            raise
        if exporter is not None:
            for dev in self.devices.values():
                exporter.attach(dev.driver, dev.code, line_label(dev.cfg.effective_parameters()))
            exporter.set_publisher(self.publisher)
        self.exporter = exporter

    def _swap_publisher(self, new: MqttPublisher | None) -> None:
        """Move every device from the running publisher to ``new`` (not yet started):
        each is detached and re-attached at once, so updates of the moment go to one of
        the two; then the old one flushes and says offline, and the new one connects."""
        old = self.publisher
        for dev in self.devices.values():
            if old is not None:
                old.detach(dev.driver)
            if new is not None:
                new.attach(dev.driver, dev.code)
        self.publisher = new
        if self.exporter is not None:
            self.exporter.set_publisher(new)
        if old is not None:
            old.stop(timeout=0.5, reason="reconfigure")
        if new is not None:
            try:
                new.start()
            except (ValueError, OSError) as exc:
                log.error("MQTT: cannot start the publisher: %s; MQTT is off", exc)
                for dev in self.devices.values():
                    new.detach(dev.driver)
                new.stop()
                self.publisher = None
                if self.exporter is not None:
                    self.exporter.set_publisher(None)

    # -- devices ---------------------------------------------------------------------
    def device_files(self) -> list[Path]:
        files = []
        for path in sorted(self.dir.glob(self.config.device_pattern)):
            if not path.is_file() or path.name.startswith("."):
                continue
            if path.resolve() == self.gateway_file:
                continue
            files.append(path)
        return files

    def reload_devices(self) -> None:
        """Bring the running devices in line with the folder (see the module doc)."""
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
        snapshot_interval = _inherited_snapshot(self.config)
        if snapshot_interval and "snapshot_interval" not in comm.model_fields_set:
            comm = comm.model_copy(update={"snapshot_interval": snapshot_interval})
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


def _gateway_digest(path: Path, config: GatewayConfig) -> str | None:
    """A digest of the gateway file and of the TLS files ``config`` uses (so SIGHUP after
    a certificate renewal reconnects); None when the gateway file does not exist."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    return hashlib.sha256(data + _tls_digest(config).encode()).hexdigest()


def _tls_digest(config: GatewayConfig) -> str:
    """A digest of the contents of the TLS files ``config`` uses ("" for none)."""
    tls = config.mqtt.tls if config.mqtt is not None else None
    if tls is None or not tls.enabled:
        return ""
    digest = hashlib.sha256()
    for name in sorted(tls.files().values()):
        try:
            digest.update(Path(name).read_bytes())
        except OSError as exc:  # reported when the gateway file is loaded
            digest.update(str(exc).encode())
    return digest.hexdigest()


def _mqtt_key(config: GatewayConfig) -> tuple[str, dict[str, Any], str] | None:
    """What the publisher is made from (settings, gateway id, TLS file contents): a
    change of it restarts the publisher.  ``snapshotInterval`` is the devices' business
    (see :func:`_inherited_snapshot`), not the publisher's."""
    mqtt = config.mqtt
    if mqtt is None or not mqtt.enabled:
        return None
    settings = mqtt.to_dict()
    del settings["snapshotInterval"]
    return config.effective_id, settings, _tls_digest(config)


def _metrics_key(config: GatewayConfig) -> dict[str, Any] | None:
    metrics = config.metrics
    return None if metrics is None or not metrics.enabled else metrics.to_dict()


def _inherited_snapshot(config: GatewayConfig) -> int:
    """The snapshot interval devices without their own take from ``mqtt``."""
    mqtt = config.mqtt
    return mqtt.snapshot_interval if mqtt is not None and mqtt.enabled else 0


def _start_exporter(config: GatewayConfig) -> MetricsExporter | None:
    """The exporter ``config`` asks for, listening; OSError names the address."""
    metrics = config.metrics
    if metrics is None or not metrics.enabled:
        return None
    from ..northbound.metrics import MetricsExporter

    exporter = MetricsExporter(metrics, gateway_id=config.effective_id)
    try:
        exporter.start()
    except OSError as exc:
        raise OSError(f"metrics: cannot listen on {metrics.host}:{metrics.port}: "
                      f"{exc.strerror or exc}") from None
    return exporter


def run_service(config_dir: Path, gateway_config: Path | None = None, *,
                seconds: float = 0.0) -> int:
    """Run the gateway until SIGTERM/SIGINT, or for ``seconds`` (0: until a signal);
    SIGHUP reloads.  Returns the exit code: 0 after a clean stop, 2 for a configuration
    error (printed on stderr)."""
    config_dir = Path(config_dir)
    if not seconds >= 0:  # also refuses NaN
        print(f"edgemodbus service: --seconds {seconds}: must be >= 0 (0: run until a "
              "signal)", file=sys.stderr)
        return 2
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
        deadline = time.monotonic() + seconds if seconds > 0 else math.inf
        while not flags["stop"]:
            left = deadline - time.monotonic()
            if left <= 0:
                log.info("%g s elapsed (--seconds)", seconds)
                break
            wake.wait(min(gateway.config.status_check_interval / 1000, left))
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
        prog="python -m edgemodbus.gateway",
        description="Poll every device file in a folder; MQTT and metrics from a gateway "
                    "file; SIGHUP reloads, SIGTERM stops.")
    parser.add_argument("--config-dir", type=Path, required=True,
                        help="folder of device files (*.json)")
    parser.add_argument("--gateway", type=Path, default=None,
                        help=f"gateway file (default: DIR/{GATEWAY_FILE} if present)")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="-v: debug logs of edgemodbus")
    parser.add_argument("--seconds", type=float, default=0.0,
                        help="stop after N s (0: run until SIGTERM or SIGINT)")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    return run_service(args.config_dir, args.gateway, seconds=args.seconds)


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """INFO by default; no timestamps under systemd (the journal has them)."""
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt)

