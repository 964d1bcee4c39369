"""The gateway file: who this gateway is and where its data goes (``gatewayId``, ``mqtt``,
``metrics``, ``serve``), loaded and checked; and what of it a reload compares."""

from __future__ import annotations

import hashlib
import os
import socket
import stat
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import Field

from ..config import ConfigError, Model, Ms, Problem, load_model
from ..config.files import open_regular
from ..config.jsonfile import MAX_JSON_BYTES
from ..config.limits import MAX_NAME
from ..console import ConsoleSettings
from ..northbound.metrics import MetricsSettings
from ..northbound.mqtt import MqttSettings, check_name
from ..serve import ServeSettings
from .fleet import FleetSettings

GATEWAY_FILE = "gateway.json"


class GatewayConfig(Model):
    """The gateway file: who this gateway is and where its data goes."""

    _where: ClassVar[str] = "gateway"
    _max_lengths: ClassVar[dict[str, int]] = {"gatewayId": MAX_NAME}

    gateway_id: str | None = None  # default: the host name
    mqtt: MqttSettings | None = None
    metrics: MetricsSettings | None = None
    serve: ServeSettings | None = None  # the Modbus TCP server (edgemodbus/serve/)
    console: ConsoleSettings | None = Field(  # the web console (edgemodbus/console/)
        default=None, description="The web console (docs/console.md); left out: no console")
    fleet: FleetSettings | None = Field(  # a dial-in fleet behind a balancer (fleet.py)
        default=None, description="This instance of a dial-in fleet (docs/deploy.md); left "
        "out: one gateway alone")
    device_pattern: str = "*.json"
    status_check_interval: Ms = 500
    log_format: Literal["text", "json"] = Field(
        default="text", description="The service's log lines: text, or JSON lines (time, "
        "level, logger, message) for Loki/ELK (logs.py; `--log-format` on the command line)")

    @property
    def effective_id(self) -> str:
        return self.gateway_id or socket.gethostname().split(".")[0] or "edgemodbus"

    @property
    def instance(self) -> str | None:
        """This instance's id in a fleet (an enabled ``fleet`` section), else None."""
        fleet = self.fleet
        return fleet.effective_instance if fleet is not None and fleet.enabled else None


def load_gateway_config(path: str | os.PathLike[str] | dict[str, Any]) -> GatewayConfig:
    """Load and check a gateway file; ConfigError names the field, value and rule.

    The TLS files of an enabled ``mqtt.tls`` must exist and hold PEM data (checked here,
    so a bad path is reported before anything connects), and so must the folder of
    ``mqtt.storeAndForward.path``; relative paths are taken from
    the gateway file's folder.  So must an enabled ``console.tls``'s files."""
    cfg = load_model(GatewayConfig, path)
    folder = None  # relative paths are taken from the gateway file's folder
    if isinstance(path, os.PathLike) or (
            isinstance(path, str) and not path.lstrip("\ufeff \t\r\n").startswith(("{", "["))):
        folder = Path(path).absolute().parent
    problems: list[Problem] = []
    console = cfg.console
    if console is not None and console.enabled:
        if folder is not None:
            console = console.resolved(folder)
            cfg = cfg.model_copy(update={"console": console})
        problems += console.problems()
    mqtt = cfg.mqtt
    if mqtt is None or not mqtt.enabled:
        if problems:
            raise ConfigError(problems)
        return cfg
    try:
        check_name("gatewayId", cfg.effective_id)
    except ValueError as exc:
        problems.append(Problem("gatewayId", cfg.effective_id, str(exc)))
    if mqtt.tls is not None and mqtt.tls.enabled:
        tls = mqtt.tls
        if folder is not None:
            tls = tls.resolved(folder)
            mqtt = mqtt.model_copy(update={"tls": tls})
            cfg = cfg.model_copy(update={"mqtt": mqtt})
        problems += tls.problems()
    sparkplug = mqtt.sparkplug
    if mqtt.mode == "sparkplug" and sparkplug is not None:
        if folder is not None:
            sparkplug = sparkplug.resolved(folder, os.environ.get("STATE_DIRECTORY"))
            mqtt = mqtt.model_copy(update={"sparkplug": sparkplug})
            cfg = cfg.model_copy(update={"mqtt": mqtt})
        problems += sparkplug.problems()
        lease = cfg.fleet.lease if cfg.fleet is not None and cfg.fleet.enabled else None
        if sparkplug.shared_by_pair and (lease is None or not lease.enabled):
            problems.append(Problem("mqtt.sparkplug.sharedByPair", True, "needs a redundant "
                                    "pair: an enabled fleet.lease section (docs/deploy.md)"))
    spool = mqtt.store_and_forward
    if spool is not None:
        if folder is not None:
            spool = spool.resolved(folder)
            mqtt = mqtt.model_copy(update={"store_and_forward": spool})
            cfg = cfg.model_copy(update={"mqtt": mqtt})
        problems += spool.problems()
    if problems:
        raise ConfigError(problems)
    return cfg


def gateway_digest(path: Path, config: GatewayConfig) -> str | None:
    """A digest of the gateway file and of the TLS files ``config`` uses (so SIGHUP after
    a certificate renewal reconnects); None when the gateway file does not exist."""
    try:
        data = file_bytes(path)
    except FileNotFoundError:
        return None
    console = config.console.files_digest() if config.console is not None else ""
    return hashlib.sha256(data + _tls_digest(config).encode() + console.encode()).hexdigest()


def file_bytes(path: Path) -> bytes:
    """What a digest of a config file is taken of: its bytes, at most one more than a
    JSON file we read may have (loading a larger one says so); for a FIFO, a device or a
    folder a description of it (reading would block: loading it says why).  OSError when
    it cannot be read."""
    info = path.stat()
    if stat.S_ISREG(info.st_mode):
        fd, info = open_regular(path)  # a FIFO put there since: not a blocking open
        with os.fdopen(fd, "rb") as file:
            if stat.S_ISREG(info.st_mode):
                return file.read(MAX_JSON_BYTES + 1)
    return f"not a regular file: {info.st_mode:o} {info.st_ino}".encode()


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


def mqtt_key(config: GatewayConfig) -> tuple[str, dict[str, Any], str, str | None] | None:
    """What the publisher is made from (settings, gateway id, TLS file contents, fleet
    instance): a change of it restarts the publisher.  ``snapshotInterval`` is the devices' business
    (see :func:`inherited_snapshot`), not the publisher's."""
    mqtt = config.mqtt
    if mqtt is None or not mqtt.enabled:
        return None
    settings = mqtt.to_dict()
    del settings["snapshotInterval"]
    return config.effective_id, settings, _tls_digest(config), config.instance


def metrics_key(config: GatewayConfig) -> dict[str, Any] | None:
    """What the exporter is made from: a change of it moves the exporter."""
    metrics = config.metrics
    return None if metrics is None or not metrics.enabled else metrics.to_dict()


def inherited_snapshot(config: GatewayConfig) -> int:
    """The snapshot interval devices without their own take from ``mqtt``."""
    mqtt = config.mqtt
    return mqtt.snapshot_interval if mqtt is not None and mqtt.enabled else 0
