"""The ``fleet`` section of the gateway file: this instance of a dial-in fleet (N
gateways running one config folder behind a TCP load balancer, docs/deploy.md).

```json
"fleet": {"instanceId": "gw-2", "loadBalancers": ["10.0.5.10", "10.0.5.11"],
          "lease": {"url": "redis://10.0.5.20:6379/0", "leaseMs": 5000}}
```

``instanceId`` names this instance in the retained device statuses it publishes, its
MQTT client id and gateway topic and the ``edgemodbus_dtu_held`` gauge; left out, the
environment's ``EDGEMODBUS_INSTANCE`` (a systemd template unit's ``%i``), else the host
name.  ``loadBalancers``: the balancers' networks; a connection from one of them must
start with a PROXY v2 header (line/proxy_v2.py), which gives the DTU's own address.
``lease``: a redundant pair (docs/deploy.md "Redundant pair"): the instance holding the
lease (gateway/lease.py) runs the connect-mode devices, the other keeps them stopped.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, ClassVar, Protocol
from urllib.parse import urlsplit

from pydantic import AfterValidator, BeforeValidator, Field, field_validator, model_validator

from ..config import DeviceConfig, DriverModbusRtuParameter, Model, Range
from ..config.limits import MAX_NAME
from ..config.listen import allow_list, network
from ..driver import DriverModbusRtu
from ..northbound.mqtt import check_name

if TYPE_CHECKING:
    from ..northbound.metrics import MetricsExporter
    from ..northbound.mqtt import MqttPublisher
    from ..northbound.sparkplug.publisher import SparkplugPublisher

    Publisher = MqttPublisher | SparkplugPublisher

MAX_BALANCERS = 64
INSTANCE_ENV = "EDGEMODBUS_INSTANCE"


def _bounded(nets: tuple[str, ...]) -> tuple[str, ...]:
    if len(nets) > MAX_BALANCERS:
        raise ValueError(f"at most {MAX_BALANCERS} networks, not {len(nets)}")
    return nets


Balancers = Annotated[tuple[Annotated[str, AfterValidator(network)], ...],
                      BeforeValidator(allow_list), AfterValidator(_bounded)]


LEASE_SCHEMES = ("redis", "rediss", "unix")
MAX_LEASE_MS = 600_000


class LeaseSettings(Model):
    """``fleet.lease``: where the pair's lease lives and how long it lasts."""

    _where: ClassVar[str] = "fleet.lease"
    _max_lengths: ClassVar[dict[str, int]] = {"url": 1024, "keyPrefix": MAX_NAME}

    enabled: bool = Field(default=True, description="false: the section is kept, this "
                          "instance runs its devices alone (no lease)")
    url: str = Field(description="The Redis server: redis://host:port/db, rediss:// "
                     "(TLS) or unix:///path")
    key_prefix: str = Field(default="edgemodbus:pair:", description="Prefix of the "
                            "lease's keys (<prefix>leader, <prefix>fence); one per pair")
    # Range, not ge/le: true, 1.5 or [] are refused naming what is allowed (pydantic's
    # own bounds took true as 1 and spoke of "less than or equal to")
    lease_ms: Annotated[int, Range(1_000, MAX_LEASE_MS)] = Field(
        default=10_000, description="Lease time: the standby takes over within it plus a "
        "cycle")
    renew_ms: Annotated[int | None, Range(100, MAX_LEASE_MS // 3)] = Field(
        default=None, description="Renewal period; left out: leaseMs/3; at most leaseMs/3")
    margin_ms: Annotated[int | None, Range(0, MAX_LEASE_MS // 2)] = Field(
        default=None, description="No request to a "
                                  "connect-mode device starts later than this before the "
                                  "lease's known end (the frame's time on the wire, the "
                                  "clocks' rates); left out: leaseMs/10, at least 100; at "
                                  "most leaseMs/2")

    @field_validator("url")
    @classmethod
    def _url(cls, value: str) -> str:
        scheme = urlsplit(value).scheme
        if scheme not in LEASE_SCHEMES:
            raise ValueError(f"{value!r} is not a Redis URL: use "
                             f"{', '.join(s + '://' for s in LEASE_SCHEMES)}")
        return value

    @field_validator("key_prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        if not value or any(c.isspace() for c in value):
            raise ValueError(f"{value!r}: give a non-empty prefix without spaces")
        return value

    @model_validator(mode="after")
    def _three_renewals(self) -> LeaseSettings:
        if self.renew_ms is not None and self.renew_ms * 3 > self.lease_ms:
            raise ValueError(f"renewMs {self.renew_ms} must be at most a third of leaseMs "
                             f"{self.lease_ms} ({self.lease_ms // 3})")
        if self.margin_ms is not None and self.margin_ms * 2 > self.lease_ms:
            raise ValueError(f"marginMs {self.margin_ms} must be at most half of leaseMs "
                             f"{self.lease_ms} ({self.lease_ms // 2}): a renewed lease must "
                             "leave time to poll")
        return self

    @property
    def effective_renew_ms(self) -> int:
        """The renewal period: renewMs, else a third of leaseMs."""
        return self.renew_ms if self.renew_ms is not None else self.lease_ms // 3


class FleetSettings(Model):
    """The ``fleet`` section of the gateway file."""

    _where: ClassVar[str] = "fleet"
    _max_lengths: ClassVar[dict[str, int]] = {"instanceId": MAX_NAME}

    enabled: bool = Field(default=True, description="false: the section is kept, this "
                          "gateway runs alone (publishes every device, reads no PROXY header)")
    instance_id: str | None = Field(default=None, description="This instance's name "
                                    f"(statuses, MQTT client id); left out: ${INSTANCE_ENV}, "
                                    "else the host name")
    load_balancers: Balancers = Field(default=(), description="Networks (CIDR) or addresses "
                                      "of the load balancers that send a PROXY v2 header")
    lease: LeaseSettings | None = Field(default=None, description="A redundant pair: "
                                        "the lease that picks the polling instance")

    @field_validator("instance_id")
    @classmethod
    def _topic_level(cls, value: str | None) -> str | None:
        return None if value is None else check_name("instanceId", value)

    @property
    def effective_instance(self) -> str:
        """The instance id: configured, else $EDGEMODBUS_INSTANCE, else the host name."""
        if self.instance_id:
            return self.instance_id
        env = os.environ.get(INSTANCE_ENV, "").strip()
        if env:
            return check_name(INSTANCE_ENV, env)
        return socket.gethostname().split(".")[0] or "edgemodbus"




class FleetConfig(Protocol):
    """What :func:`apply_fleet` reads of the gateway file (GatewayConfig; config.py
    imports this module)."""

    @property
    def fleet(self) -> FleetSettings | None: ...
    @property
    def instance(self) -> str | None: ...
    @property
    def effective_id(self) -> str: ...


def holder(params: DriverModbusRtuParameter,
           instance: str | None) -> Callable[[], bool] | None:
    """In a fleet, whether a listen-mode device's DTU is connected here now (the
    publisher publishes the device only then); None outside a fleet or for a device on
    another transport (a serial port or a TCP device belongs to every instance alike)."""
    if instance is None or params.transport != "rtu-over-tcp-server":
        return None
    registry = DriverModbusRtu.dtu_registry
    host, port, dtu_id = params.listen_host, params.effective_listen_port, params.dtu_id
    return lambda: registry.connected(host, port, dtu_id)


def attach_device(publisher: Publisher, driver: DriverModbusRtu, code: str,
                  cfg: DeviceConfig, instance: str | None) -> None:
    """Attach a device to the publisher; in a fleet with its :func:`holder` (either
    publisher: per-item/batch statuses, or Sparkplug DBIRTH/DDEATH per instance)."""
    held = holder(cfg.effective_parameters(), instance)
    if held is not None and getattr(publisher, "instance", None) is not None:
        publisher.attach(driver, code, held=held)
    else:
        publisher.attach(driver, code)


def apply_fleet(config: FleetConfig | None, exporter: MetricsExporter | None) -> None:
    """Apply a gateway file's fleet section: its load balancers to every DTU listen port
    of the process (None: none), this instance's name (else the gateway id) to the
    exporter's ``edgemodbus_dtu_held`` gauge."""
    fleet = config.fleet if config is not None else None
    enabled = fleet is not None and fleet.enabled
    DriverModbusRtu.dtu_registry.set_load_balancers(
        fleet.load_balancers if fleet is not None and enabled else ())
    if exporter is not None and config is not None:
        exporter.instance = config.instance or config.effective_id


__all__ = ["INSTANCE_ENV", "MAX_BALANCERS", "FleetSettings", "LeaseSettings", "apply_fleet",
           "attach_device", "holder"]
