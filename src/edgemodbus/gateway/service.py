"""The devices of one config folder with their MQTT publisher and metrics exporter:
started, reloaded (the gateway file, then the device files) and stopped."""

from __future__ import annotations

import logging
import stat
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..config import (
    ConfigError,
    DeviceConfig,
    DriverModbusRtuParameter,
)
from ..console import console_key, start_console
from ..driver import DriverModbusRtu
from .bulk import file_id, read_device, starting_in_bulk, stop_each, thaw
from .config import (
    GATEWAY_FILE,
    GatewayConfig,
    gateway_digest,
    inherited_snapshot,
    load_gateway_config,
    metrics_key,
    mqtt_key,
)
from .fleet import apply_fleet, attach_device
from .fleet import holder as fleet_holder
from .pair import Pair, gated
from .serving import GatewayServer
from .starting import make_publisher, start_exporter
from .status_log import StatusLog

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..console.server import ConsoleServer
    from ..northbound.metrics import MetricsExporter
    from ..northbound.mqtt import MqttPublisher
    from ..northbound.sparkplug.publisher import SparkplugPublisher

    Publisher = MqttPublisher | SparkplugPublisher

log = logging.getLogger("edgemodbus.service")


def line_label(params: DriverModbusRtuParameter) -> str:
    """A name for the line a device is on (metrics label): the serial port,
    transport://host:port, for a DTU that dials in dtu://listenHost:port/dtuId (its
    tcpHost and tcpPort say nothing of it), for an MQTT DTU mqtt-dtu://broker:port/dtuId."""
    if params.transport == "rtu":
        return str(params.com_port)
    if params.transport == "rtu-over-tcp-server":
        return (f"dtu://{params.listen_host}:{params.effective_listen_port}/"
                f"{params.dtu_id or '(single)'}")
    if params.transport == "mqtt-dtu":  # the DTU on its broker
        return f"mqtt-dtu://{params.mqtt_host}:{params.mqtt_port}/{params.dtu_id}"
    return f"{params.transport}://{params.tcp_host}:{params.tcp_port}"


@dataclass
class ServiceDevice:
    """A device file of the folder and the driver running it."""

    path: Path
    digest: str
    cfg: DeviceConfig  # as loaded from the file (reload compares these)
    code: str
    driver: DriverModbusRtu
    status: str
    standby: bool = False  # a pair's standby: loaded, not started (gateway/pair.py)


class Gateway:
    """The devices of one config folder with their MQTT publisher and metrics exporter."""

    def __init__(self, config_dir: Path, config: GatewayConfig,
                 gateway_file: Path | None = None) -> None:
        self.dir = config_dir
        self.config = config
        # watched even when absent: one that appears later is applied on SIGHUP
        self.gateway_file = (gateway_file or config_dir / GATEWAY_FILE).resolve()
        self.gateway_id = config.effective_id
        self.devices: dict[Path, ServiceDevice] = {}
        # deviceCode -> path of the device last started with it (only _start_device adds)
        self._code_paths: dict[str, Path] = {}
        self.publisher: Publisher | None = None
        self.exporter: MetricsExporter | None = None
        self.serving = GatewayServer()  # the Modbus TCP server (gateway file: serve)
        self.console: ConsoleServer | None = None  # the web console (edgemodbus/console/)
        self.reload_hook: Callable[[], None] | None = None  # run.py: a reload, as SIGHUP
        self._gateway_digest = gateway_digest(self.gateway_file, config)
        self.pair: Pair | None = None  # fleet.lease: a redundant pair (gateway/pair.py)
        self._devices_lock = threading.RLock()  # the lease's thread starts/stops devices
        self.status_log = StatusLog()  # the devices whose status changed (status_log.py)

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> None:
        fleet = self.config.fleet
        if fleet is not None and fleet.enabled and fleet.lease is not None \
                and fleet.lease.enabled:  # before the publisher: it may share the node
            self.pair = Pair(fleet.lease, self.gateway_id, self._leadership)
        mqtt = self.config.mqtt
        if mqtt is not None and mqtt.enabled:
            self.publisher = make_publisher(mqtt, self.gateway_id, self.config.instance,
                                            self.pair).start()
            log.info("MQTT: gateway %s publishing to %s:%d (%s)", self.gateway_id, mqtt.host,
                     mqtt.port, mqtt.mode)
        self.exporter = start_exporter(self.config, self.serving)
        apply_fleet(self.config, self.exporter)
        if self.exporter is not None and self.publisher is not None:
            self.exporter.set_publisher(self.publisher)
        with self._devices_lock:
            self.reload_devices()
        if self.pair is not None:
            self.pair.start()
        for done in self.serving.apply(self.config.serve, self._served()):
            log.info("serve: %s", done)
        self.console = start_console(self.config.console, self)

    def _stop_all(self, devices: list[ServiceDevice]) -> None:
        stop_each(devices, self._stop_device)  # a few threads, not one per device

    def _leadership(self, leader: bool) -> None:
        """The lease was gained or lost (on the lease's thread): start or stop (every
        one at once) the connect-mode devices."""
        with self._devices_lock:
            devs = [dev for dev in self.devices.values() if gated(dev.cfg)]
            if not leader:
                self._stop_all([dev for dev in devs if not dev.standby])
            for dev in devs:
                del self.devices[dev.path]
                if leader:
                    self._stop_device(dev)
                self._start_device(dev.path, dev.digest, dev.cfg,
                                   action="started (leader)")

    def request_reload(self) -> None:
        """The console saved a device file: reload as SIGHUP does (on the service's
        thread when run.py set the hook, else here)."""
        (self.reload_hook or self.reload)()

    def stop(self) -> None:
        """Stop the console, the Modbus TCP server, every device in parallel, then the
        publisher and the exporter."""
        if self.console is not None:
            self.console.stop()
            self.console = None
        self.serving.stop()
        with self._devices_lock:
            devices = list(self.devices.values())
            self.devices.clear()
            self._stop_all(devices)
        if self.pair is not None:  # released once nothing polls here any more
            self.pair.stop()
            self.pair = None
        if self.publisher is not None:
            self.publisher.stop(timeout=0.5)
            self.publisher = None
        if self.exporter is not None:
            self.exporter.stop()
            self.exporter = None
        apply_fleet(None, None)  # the process's DTU listen ports: no balancers

    def reload(self) -> None:
        """SIGHUP: the gateway file, then the device files (see gateway/__init__.py).
        Never raises: whatever fails is logged in one line and the running configuration
        of what failed is kept (a reload must not end a running gateway)."""
        try:
            with self._devices_lock:
                self._reload()
        except Exception as exc:  # each step guards itself; this is the last resort
            log.error("reload failed (%s); keeping what is running", one_line(exc))

    def _reload(self) -> None:
        self.reload_gateway()
        self.reload_devices()
        try:
            # the server and the publisher are separate subscribers of each driver: a
            # publisher swapped above left the units' listeners as they were
            for done in self.serving.apply(self.config.serve, self._served()):
                log.info("serve: %s", done)
        except OSError as exc:
            log.error("serve: %s; the Modbus TCP server is off", exc)
        except Exception as exc:
            log.error("serve: not applied (%s)", one_line(exc))

    def _served(self) -> dict[str, tuple[DriverModbusRtu, DeviceConfig]]:
        """What the ``serve`` units may name: device code -> driver and config."""
        return {dev.code: (dev.driver, dev.cfg) for dev in self.devices.values()}

    # -- the gateway file ------------------------------------------------------------
    def reload_gateway(self) -> None:
        """Apply a changed gateway file; a broken one is reported, the running kept."""
        path = self.gateway_file
        keep = "keeping the running gateway settings"
        try:
            digest = gateway_digest(path, self.config)
        except OSError as exc:
            log.error("%s: cannot read: %s; %s", path, exc.strerror or exc, keep)
            return
        except Exception as exc:
            log.error("%s: cannot read (%s); %s", path, one_line(exc), keep)
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
        except Exception as exc:  # e.g. RecursionError of a deeply nested file
            log.error("%s: cannot load (%s); %s", path, one_line(exc), keep)
            return
        try:
            applied = self.apply_gateway(new)
        except (ValueError, OSError, ImportError) as exc:
            log.error("%s: not applied, %s: %s", path, keep, exc)
            return
        except Exception as exc:
            log.error("%s: not applied (%s); %s", path, one_line(exc), keep)
            return
        self._gateway_digest = gateway_digest(path, new)
        log.info("%s: gateway settings applied: %s", path,
                 "; ".join(applied) if applied else "no effective change")

    def apply_gateway(self, new: GatewayConfig) -> list[str]:
        """Switch to ``new`` gateway settings live; what was done, in words.  Raises
        (ValueError, OSError) with nothing changed when they cannot be applied."""
        old = self.config
        done: list[str] = []
        publisher: Publisher | None = None
        mqtt_changed = mqtt_key(old) != mqtt_key(new)
        if mqtt_changed and new.mqtt is not None and new.mqtt.enabled:
            publisher = make_publisher(new.mqtt, new.effective_id, new.instance, self.pair)
            try:
                for dev in self.devices.values():
                    publisher.check_item_names(dev.code,
                                               [it.name for it in dev.cfg.address_list])
            except ValueError:
                publisher.stop()
                raise
        if metrics_key(old) != metrics_key(new):
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
        apply_fleet(new, self.exporter)
        running = self.console.key if self.console is not None else None
        if running != console_key(new.console):  # (the key taken when it started)
            if self.console is not None:
                self.console.stop()
                self.console = None
            try:
                self.console = start_console(new.console, self)
            except (OSError, ValueError) as exc:
                log.error("console: %s; the console is off", exc)
            done.append(f"console on {self.console.url}" if self.console else "console off")
        if mqtt_changed:
            self._swap_publisher(publisher)
            done.append(f"MQTT publisher restarted ({new.mqtt.host}:{new.mqtt.port}, "
                        f"gateway {self.gateway_id})"
                        if publisher is not None and new.mqtt is not None else "MQTT off")
        if inherited_snapshot(old) != inherited_snapshot(new):
            restarted = [dev for dev in list(self.devices.values())
                         if "snapshot_interval" not in dev.cfg.communication.model_fields_set]
            for dev in restarted:
                del self.devices[dev.path]
                self._stop_device(dev)
                self._start_device(dev.path, dev.digest, dev.cfg, action="restarted")
            done.append(f"snapshotInterval {inherited_snapshot(new)} ms: "
                        f"{len(restarted)} devices restarted")
        if (old.fleet and old.fleet.lease) != (new.fleet and new.fleet.lease):
            done.append("fleet.lease changed: applied at the next restart")
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
            exporter = start_exporter(new, self.serving)
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
                params = dev.cfg.effective_parameters()
                exporter.attach(dev.driver, dev.code, line_label(params),
                                held=fleet_holder(params, self.config.instance))
            exporter.set_publisher(self.publisher)
        self.exporter = exporter

    def _swap_publisher(self, new: Publisher | None) -> None:
        """Move every device from the running publisher to ``new`` (not yet started):
        each is detached and re-attached at once, so updates of the moment go to one of
        the two; then the old one flushes and says offline, and the new one connects."""
        old = self.publisher
        for dev in self.devices.values():
            if old is not None:
                old.detach(dev.driver)
            if new is not None:
                attach_device(new, dev.driver, dev.code, dev.cfg, self.config.instance)
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
        """The folder's device files: regular files (or links to one) the pattern
        matches, not hidden, not the gateway file (by device and inode: one stat a file)."""
        gateway = file_id(self.gateway_file)
        files = []
        for path in sorted(self.dir.glob(self.config.device_pattern)):
            if path.name.startswith("."):
                continue
            try:
                info = path.stat()
            except OSError:
                continue
            if stat.S_ISREG(info.st_mode) and (info.st_dev, info.st_ino) != gateway:
                files.append(path)
        return files

    def reload_devices(self) -> None:
        """Bring the running devices in line with the folder (see gateway/__init__.py)."""
        files = self.device_files()
        present = set(files)  # thousands of files: no list scan per device
        gone = [self.devices.pop(path) for path in list(self.devices) if path not in present]
        self._stop_all(gone)
        for dev in gone:
            log.info("%s: stopped (%s removed)", dev.code, dev.path.name)
        before = len(self.devices)
        # frozen after when devices started and none stopped (gateway/bulk.py)
        with starting_in_bulk(lambda: not gone and len(self.devices) > before):
            for path in files:
                current = self.devices.get(path)
                what = "keeping the running version" if current else "not started"
                try:
                    self._reload_device(path, current, what)
                except Exception as exc:  # e.g. RecursionError of a deeply nested file
                    log.error("%s: cannot load (%s); %s", path, one_line(exc), what)

    def _reload_device(self, path: Path, current: ServiceDevice | None, what: str) -> None:
        try:
            digest, load = read_device(path)  # the file read once (gateway/bulk.py)
        except OSError as exc:
            log.error("%s: cannot read: %s", path, exc)
            return
        if current is not None and current.digest == digest:
            return
        try:
            cfg = load()
        except (ConfigError, ValueError, OSError) as exc:
            log.error("%s: invalid, %s:\n%s", path, what, exc)
            return
        if current is None:
            self._start_device(path, digest, cfg)
        else:
            self._change_device(current, digest, cfg)

    def _code(self, path: Path, cfg: DeviceConfig) -> str:
        return cfg.organization.device_code or path.stem

    def _start_device(self, path: Path, digest: str, cfg: DeviceConfig,
                      action: str = "started") -> None:
        code = self._code(path, cfg)
        holder = self.devices.get(self._code_paths.get(code, path))
        if holder is not None and holder.code == code:
            log.error("%s: deviceCode %r is already used by %s; not started", path, code,
                      holder.path.name)
            return
        if self.pair is not None and not self.pair.may_run(cfg):
            self.devices[path] = ServiceDevice(path, digest, cfg, code, self.pair.driver(cfg),
                                               "Standby", standby=True)
            self._code_paths[code] = path
            log.info("%s: standby (%s): polled by the pair's leader", code, path.name)
            return
        org = cfg.organization if cfg.organization.device_code == code else \
            cfg.organization.model_copy(update={"device_code": code})
        comm = cfg.communication
        snapshot_interval = inherited_snapshot(self.config)
        if snapshot_interval and "snapshot_interval" not in comm.model_fields_set:
            comm = comm.model_copy(update={"snapshot_interval": snapshot_interval})
        items = cfg.address_list  # the driver's store holds their state: no copy
        driver = DriverModbusRtu() if self.pair is None else self.pair.driver(cfg)
        try:
            self.status_log.watch(driver, path)
            if self.publisher is not None:
                self.publisher.check_item_names(code, [it.name for it in items])
                attach_device(self.publisher, driver, code, cfg, self.config.instance)
            if self.exporter is not None:
                params = cfg.effective_parameters()
                self.exporter.attach(driver, code, line_label(params),
                                     held=fleet_holder(params, self.config.instance))
            running = driver.start_device(org, comm, items, cfg.actions)
        except (ValueError, OSError) as exc:
            self._detach(driver)
            log.error("%s: not started: %s", path, exc)
            return
        status = driver.device_driver_status.value
        self.devices[path] = ServiceDevice(path, digest, cfg, code, driver, status)
        self._code_paths[code] = path
        if running:
            log.info("%s: %s from %s (%d items)", code, action, path.name, len(items))
        else:
            log.info("%s: %s (%s)", code, status, path.name)

    def _change_device(self, dev: ServiceDevice, digest: str, cfg: DeviceConfig) -> None:
        # secrets compared too (to_dict masks them): a new registrationKey restarts
        same_line = (cfg.organization.to_dict() == dev.cfg.organization.to_dict()
                     and cfg.communication.to_dict(secrets=True)
                     == dev.cfg.communication.to_dict(secrets=True)
                     and cfg.driver_type == dev.cfg.driver_type)
        if same_line and not dev.standby \
                and dev.driver.device_driver_status.value != "Disabled":
            items = cfg.address_list
            try:
                if self.publisher is not None:
                    self.publisher.check_item_names(dev.code, [it.name for it in items])
                dev.driver.update_addresses(items, cfg.actions)
            except (ValueError, RuntimeError) as exc:
                log.error("%s: address list not applied, keeping the running one: %s",
                          dev.path, exc)
                return
            dev.digest, dev.cfg = digest, cfg
            log.info("%s: address list updated from %s (%d items, %d actions)", dev.code,
                     dev.path.name, len(items), len(cfg.actions))
            return
        del self.devices[dev.path]
        self._stop_device(dev)
        self._start_device(dev.path, digest, cfg, action="restarted")

    def _stop_device(self, dev: ServiceDevice) -> None:
        if dev.standby:
            return  # never started nor attached
        thaw()  # the objects a bulk start froze: collected again (gateway/bulk.py)
        try:
            dev.driver.stop_device()
        except Exception:
            log.exception("%s: stop failed", dev.code)
        self._detach(dev.driver)

    def _detach(self, driver: DriverModbusRtu) -> None:
        self.status_log.unwatch(driver)
        if self.publisher is not None:
            self.publisher.detach(driver)
        if self.exporter is not None:
            self.exporter.detach(driver)

    def check_statuses(self) -> None:
        """Log each device status change, once (status_log.py: events, not a poll)."""
        self.status_log.log_changes(self.devices)


def one_line(exc: BaseException, limit: int = 300) -> str:
    """An unexpected exception as one short line: its type and its first line."""
    text = str(exc).strip().splitlines()
    first = text[0] if text else ""
    if len(first) > limit:
        first = first[:limit] + "..."
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__

